//! `[realtime]` (Cadence-specific, optional): where the live print's threads run and with which
//! SCHED_FIFO priorities, and whether memory is locked. When the OS refuses any of it the host
//! runs anyway and says once which guarantee is off.

use super::error::ConfigError;
use super::reader::SectionReader;

/// Thread placement of a live print.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RealtimeSection {
    /// Apply pinning, SCHED_FIFO and mlockall at all (default true).
    pub enabled: bool,
    /// CPU of the planner thread (default 0).
    pub planner_cpu: usize,
    /// CPU of the IO stage and the MCU links' IO threads (default 1); `io_cpu: any` leaves
    /// them unpinned (still SCHED_FIFO), so a woken IO thread runs on whichever core is free.
    pub io_cpu: Option<usize>,
    /// SCHED_FIFO priority of the planner, 1..=99 (default 30).
    pub planner_priority: i32,
    /// SCHED_FIFO priority of the IO stage, 1..=94 (default 40; the links' IO threads run 5 above).
    pub io_priority: i32,
    /// mlockall(MCL_CURRENT | MCL_FUTURE) (default true).
    pub lock_memory: bool,
    /// Hold `/dev/cpu_dma_latency` at 0 while running (default true), as `cyclictest` does:
    /// idle CPUs then poll instead of halting, so a woken real-time thread (an endstop trigger
    /// to relay) does not first wait for its CPU to leave a sleep state.
    pub cpu_dma_latency_zero: bool,
    /// While a homing or probing move runs, keep every CPU polling with a SCHED_IDLE thread
    /// (default false): no CPU halts meanwhile, so the trigger relay's wake-ups never wait for
    /// a CPU to leave its idle state, also where the kernel ignores `/dev/cpu_dma_latency`
    /// (no cpuidle driver, as on many VMs). The threads yield at once to any other work.
    /// Off by default: on the 2-vCPU VM it was measured on, it cut the median wake-up
    /// (29 → 6 µs) but made the VM's own 25 ms pauses more frequent while other work ran
    /// (11 homing timeouts in 12 runs of 20 cycles, against none in 6 runs without it); on a quiet
    /// machine 200 passes gave trigger → stop max 430–450 µs with it, 155–196 µs without.
    pub idle_poll_homing: bool,
}

impl Default for RealtimeSection {
    fn default() -> Self {
        RealtimeSection {
            enabled: true,
            planner_cpu: 0,
            io_cpu: Some(1),
            planner_priority: 30,
            io_priority: 40,
            lock_memory: true,
            cpu_dma_latency_zero: true,
            idle_poll_homing: false,
        }
    }
}

pub(crate) fn read_realtime(s: &SectionReader<'_>) -> Result<RealtimeSection, ConfigError> {
    let d = RealtimeSection::default();
    Ok(RealtimeSection {
        enabled: s.opt_bool("enabled")?.unwrap_or(d.enabled),
        planner_cpu: s.int("planner_cpu", Some(d.planner_cpu), 0..=1023)?,
        io_cpu: match s.value("io_cpu") {
            Some(v) if v.text.trim().eq_ignore_ascii_case("any") => None,
            _ => Some(s.int("io_cpu", d.io_cpu, 0..=1023)?),
        },
        planner_priority: s.int("planner_priority", Some(d.planner_priority), 1..=99)?,
        io_priority: s.int("io_priority", Some(d.io_priority), 1..=94)?,
        lock_memory: s.opt_bool("lock_memory")?.unwrap_or(d.lock_memory),
        cpu_dma_latency_zero: s
            .opt_bool("cpu_dma_latency_zero")?
            .unwrap_or(d.cpu_dma_latency_zero),
        idle_poll_homing: s.opt_bool("idle_poll_homing")?.unwrap_or(d.idle_poll_homing),
    })
}

#[cfg(test)]
mod tests {

    fn with(section: &str) -> Result<super::RealtimeSection, String> {
        crate::printer::simulated_with(section).map(|c| c.realtime)
    }

    #[test]
    fn defaults_and_values() {
        assert_eq!(with("").unwrap(), super::RealtimeSection::default());
        let rt = with("[realtime]\nplanner_cpu: 1\nio_cpu: 0\nio_priority: 50\nlock_memory: False").unwrap();
        assert_eq!(
            (rt.planner_cpu, rt.io_cpu, rt.io_priority, rt.lock_memory),
            (1, Some(0), 50, false)
        );
        assert_eq!(with("[realtime]\nio_cpu: any").unwrap().io_cpu, None);
        assert_eq!(with("[realtime]\nio_cpu: ANY").unwrap().io_cpu, None);
        assert!(with("").unwrap().cpu_dma_latency_zero);
        assert!(
            !with("[realtime]\ncpu_dma_latency_zero: False")
                .unwrap()
                .cpu_dma_latency_zero
        );
        assert!(!with("").unwrap().idle_poll_homing);
        assert!(
            with("[realtime]\nidle_poll_homing: True")
                .unwrap()
                .idle_poll_homing
        );
    }

    #[test]
    fn bad_values_name_section_and_option() {
        let e = with("[realtime]\nio_priority: 120").unwrap_err();
        assert!(e.contains("[realtime]") && e.contains("io_priority"), "{e}");
        let e = with("[realtime]\nio_cpu: anywhere").unwrap_err();
        assert!(e.contains("[realtime]") && e.contains("io_cpu"), "{e}");
        let e = with("[realtime]\nspin: 1").unwrap_err();
        assert!(e.contains("spin") && e.contains("realtime"), "{e}");
    }
}
