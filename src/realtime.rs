//! Thread placement and priorities of a live print ([`RtConfig`], from printer.cfg's
//! `[realtime]`): which core and SCHED_FIFO priority each stage thread gets, memory locking,
//! the `/dev/cpu_dma_latency` hold and idle polling during homing. When the OS refuses one of
//! them the threads run anyway and rt-core reports once which guarantee is off.

use rt_core::os::RtSpec;

/// Thread placement and priorities of a live print (from printer.cfg's `[realtime]`).
#[derive(Debug, Clone)]
pub struct RtConfig {
    /// Apply pinning / SCHED_FIFO / mlockall at all.
    pub enabled: bool,
    pub planner_core: usize,
    /// `None`: IO threads unpinned (`[realtime] io_cpu: any`).
    pub io_core: Option<usize>,
    pub planner_priority: i32,
    pub io_priority: i32,
    pub lock_memory: bool,
    /// Hold `/dev/cpu_dma_latency` at 0 while running.
    pub cpu_dma_latency_zero: bool,
    /// Keep idle CPUs polling while a homing or probing move runs.
    pub idle_poll_homing: bool,
}

impl RtConfig {
    /// From printer.cfg's `[realtime]`; `no_realtime` (the `--no-realtime` flag) turns it off.
    pub fn from_section(r: &sysconfig::printer::RealtimeSection, no_realtime: bool) -> RtConfig {
        RtConfig {
            enabled: r.enabled && !no_realtime,
            planner_core: r.planner_cpu,
            io_core: r.io_cpu,
            planner_priority: r.planner_priority,
            io_priority: r.io_priority,
            lock_memory: r.lock_memory,
            cpu_dma_latency_zero: r.cpu_dma_latency_zero,
            idle_poll_homing: r.idle_poll_homing,
        }
    }

    /// Holds `/dev/cpu_dma_latency` at 0 while the returned guard lives (when real time is on
    /// and `[realtime] cpu_dma_latency_zero` is true); a refusal is reported once.
    pub fn hold_idle_latency(&self) -> Option<rt_core::os::DmaLatencyHold> {
        if !(self.enabled && self.cpu_dma_latency_zero) {
            return None;
        }
        rt_core::os::ok_or_report(
            rt_core::os::hold_cpu_dma_latency_zero(),
            rt_core::os::Guarantee::DmaLatency,
            "idle CPUs may sleep deeply (slower wake-ups)",
        )
    }

    /// Whether homing and probing moves keep the idle CPUs polling (real time on and
    /// `[realtime] idle_poll_homing` true).
    pub fn idle_poll_homing(&self) -> bool {
        self.enabled && self.idle_poll_homing
    }

    /// Starts idle polling (see [`rt_core::os::IdlePoll`]) when [`Self::idle_poll_homing`];
    /// a refusal is reported once and homing goes on without it.
    pub fn start_idle_poll(&self) -> Option<rt_core::os::IdlePoll> {
        if !self.idle_poll_homing() {
            return None;
        }
        rt_core::os::ok_or_report(
            rt_core::os::IdlePoll::start(),
            rt_core::os::Guarantee::IdlePoll,
            "idle CPUs may halt during homing (slower trigger relay wake-ups)",
        )
    }

    /// Settings of the MCU links' own IO threads: on the IO core, above the IO stage (they
    /// write the bytes and relay homing triggers).
    pub fn link_spec(&self) -> RtSpec {
        self.spec("io-link", self.io_core, self.io_priority + 5)
    }

    /// Settings of the IO stage thread of MCU `mcu`.
    pub fn io_spec(&self, mcu: &str) -> RtSpec {
        self.spec(&format!("io-{mcu}"), self.io_core, self.io_priority)
    }

    /// Settings of the planner thread.
    pub fn planner_spec(&self) -> RtSpec {
        self.spec("planner", Some(self.planner_core), self.planner_priority)
    }

    fn spec(&self, name: &str, core: Option<usize>, priority: i32) -> RtSpec {
        let mut spec = RtSpec::new(name);
        if self.enabled {
            spec.core = core.map(|c| c % available_cores());
            spec.fifo_priority = Some(priority);
            spec.lock_memory = self.lock_memory;
        }
        spec
    }
}

fn available_cores() -> usize {
    std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
}
