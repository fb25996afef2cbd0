//! Host real-time checks (`cadence doctor`): is this host fit to run Cadence with hard timing?
//!
//! Each check turns one fact about the host (read from `/proc`, `/sys`, or a live attempt such
//! as switching a thread to SCHED_FIFO) into a [`Check`] with a status and, when not fine, a
//! hint saying what to change. The evaluation functions are pure (they take the file contents
//! as strings) so they are tested with fixtures; [`HostFacts::read`] gathers the real ones and
//! [`run_checks`] ties them together. A wake-up latency measurement (a small cyclictest:
//! sleep 1 ms, record how late the thread woke) gives the figure that matters most.
//!
//! Nothing here needs privileges: a refused SCHED_FIFO or mlockall is itself the finding.

use std::fmt;
use std::time::Duration;

use crate::hist::LatencyHist;

/// How a check came out.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Status {
    /// As wanted for hard timing.
    Ok,
    /// Cadence runs, with weaker guarantees.
    Warn,
    /// A guarantee is off: fix before relying on the timing.
    Fail,
}

impl fmt::Display for Status {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.pad(match self {
            Status::Ok => "ok",
            Status::Warn => "warn",
            Status::Fail => "FAIL",
        })
    }
}

/// One finding.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Check {
    /// Short name, e.g. `kernel preemption`.
    pub name: &'static str,
    pub status: Status,
    /// What was found.
    pub detail: String,
    /// What to do about it (empty when ok).
    pub hint: String,
}

impl Check {
    fn new(name: &'static str, status: Status, detail: impl Into<String>, hint: impl Into<String>) -> Check {
        Check {
            name,
            status,
            detail: detail.into(),
            hint: hint.into(),
        }
    }
}

impl fmt::Display for Check {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "[{:>4}] {:<22} {}", self.status, self.name, self.detail)?;
        if !self.hint.is_empty() {
            write!(f, "\n       {:<22} → {}", "", self.hint)?;
        }
        Ok(())
    }
}

/// Raw facts about the host; `None` where the file does not exist.
#[derive(Debug, Clone, Default)]
pub struct HostFacts {
    /// `/proc/sys/kernel/version` (the `uname -v` string).
    pub kernel_version: Option<String>,
    /// `/sys/kernel/realtime` ("1" on PREEMPT_RT kernels).
    pub sys_realtime: Option<String>,
    /// `/proc/cmdline`.
    pub cmdline: Option<String>,
    /// `/sys/devices/system/cpu/isolated`.
    pub isolated: Option<String>,
    /// `/proc/sys/kernel/sched_rt_runtime_us`.
    pub rt_runtime_us: Option<String>,
    /// `/proc/self/limits`.
    pub limits: Option<String>,
    /// `scaling_governor` of each CPU that has one.
    pub governors: Vec<String>,
    /// Online CPUs.
    pub cpus: usize,
}

fn read(path: &str) -> Option<String> {
    std::fs::read_to_string(path).ok()
}

impl HostFacts {
    /// Reads the facts of this host.
    pub fn read() -> HostFacts {
        let cpus = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
        let governors = (0..cpus)
            .filter_map(|c| {
                read(&format!(
                    "/sys/devices/system/cpu/cpu{c}/cpufreq/scaling_governor"
                ))
            })
            .collect();
        HostFacts {
            kernel_version: read("/proc/sys/kernel/version"),
            sys_realtime: read("/sys/kernel/realtime"),
            cmdline: read("/proc/cmdline"),
            isolated: read("/sys/devices/system/cpu/isolated"),
            rt_runtime_us: read("/proc/sys/kernel/sched_rt_runtime_us"),
            limits: read("/proc/self/limits"),
            governors,
            cpus,
        }
    }
}

/// The effective user id from `/proc/self/status` contents (`Uid:` real, effective, ...).
pub fn effective_uid(status: &str) -> Option<u32> {
    let line = status.lines().find(|l| l.starts_with("Uid:"))?;
    line["Uid:".len()..].split_whitespace().nth(1)?.parse().ok()
}

/// True when this process runs with effective uid 0.
pub fn running_as_root() -> bool {
    read("/proc/self/status").and_then(|s| effective_uid(&s)) == Some(0)
}

/// Kernel preemption model: PREEMPT_RT is what the timing guarantees are designed for.
pub fn check_preemption(version: Option<&str>, sys_realtime: Option<&str>) -> Check {
    const NAME: &str = "kernel preemption";
    let v = version.unwrap_or("").trim();
    if sys_realtime.is_some_and(|s| s.trim() == "1") || v.contains("PREEMPT_RT") {
        return Check::new(NAME, Status::Ok, format!("PREEMPT_RT ({v})"), "");
    }
    let hint = "boot a PREEMPT_RT kernel (e.g. Debian's linux-image-rt-*) for bounded wake-up latency";
    if v.contains("PREEMPT_DYNAMIC") || v.contains("PREEMPT ") || v.ends_with("PREEMPT") {
        return Check::new(
            NAME,
            Status::Warn,
            format!("preemptible but not real-time ({v})"),
            format!("{hint}; meanwhile `preempt=full` on the kernel command line helps"),
        );
    }
    Check::new(NAME, Status::Warn, format!("not preemptible ({v})"), hint)
}

/// Whether any CPU is kept free of other work (`isolcpus=` / `nohz_full=`).
pub fn check_isolation(isolated: Option<&str>, cmdline: Option<&str>, cpus: usize) -> Check {
    const NAME: &str = "cpu isolation";
    let iso = isolated.unwrap_or("").trim();
    let cmd = cmdline.unwrap_or("");
    let nohz = cmd.split_whitespace().find(|w| w.starts_with("nohz_full="));
    if !iso.is_empty() {
        let extra = nohz.map(|w| format!(", {w}")).unwrap_or_default();
        return Check::new(NAME, Status::Ok, format!("isolated cpus {iso}{extra}"), "");
    }
    if cpus < 2 {
        return Check::new(
            NAME,
            Status::Warn,
            "one CPU: the real-time threads share it with everything else",
            "use a board with at least 2 cores",
        );
    }
    Check::new(
        NAME,
        Status::Warn,
        format!("none of {cpus} CPUs isolated"),
        format!(
            "add `isolcpus={last} nohz_full={last} rcu_nocbs={last}` to the kernel command line and \
             put the IO threads there ([realtime] io_cpu: {last})",
            last = cpus - 1
        ),
    )
}

/// Real-time throttling: by default the kernel pauses SCHED_FIFO threads for 50 ms each second
/// once they have used 950 ms of it.
pub fn check_rt_throttling(runtime_us: Option<&str>) -> Check {
    const NAME: &str = "rt throttling";
    match runtime_us.map(str::trim) {
        None => Check::new(NAME, Status::Warn, "sched_rt_runtime_us not readable", ""),
        Some("-1") => Check::new(NAME, Status::Ok, "off (sched_rt_runtime_us = -1)", ""),
        Some(v) => Check::new(
            NAME,
            Status::Ok,
            format!("sched_rt_runtime_us = {v}: a runaway SCHED_FIFO thread is paused, not fatal"),
            "",
        ),
    }
}

/// Parses one soft limit (e.g. "Max locked memory") from `/proc/self/limits`; `None` when
/// missing, `Some(None)` for unlimited.
pub fn parse_limit(limits: &str, name: &str) -> Option<Option<u64>> {
    let line = limits.lines().find(|l| l.starts_with(name))?;
    let soft = line[name.len()..].split_whitespace().next()?;
    if soft == "unlimited" {
        return Some(None);
    }
    soft.parse().ok().map(Some)
}

/// RLIMIT_RTPRIO and RLIMIT_MEMLOCK for the user that runs Cadence (root ignores both).
pub fn check_limits(limits: Option<&str>, is_root: bool) -> Vec<Check> {
    let Some(limits) = limits else {
        return vec![Check::new(
            "limits",
            Status::Warn,
            "/proc/self/limits not readable",
            "",
        )];
    };
    let mut out = Vec::new();
    let rtprio = parse_limit(limits, "Max realtime priority");
    out.push(match (is_root, rtprio) {
        (true, _) => Check::new("rtprio limit", Status::Ok, "running as root", ""),
        (false, Some(None)) => Check::new("rtprio limit", Status::Ok, "unlimited", ""),
        (false, Some(Some(p))) if p >= 60 => Check::new("rtprio limit", Status::Ok, format!("{p}"), ""),
        (false, got) => Check::new(
            "rtprio limit",
            Status::Fail,
            format!("{}: SCHED_FIFO will be refused", got.flatten().unwrap_or(0)),
            "set LimitRTPRIO=99 in the systemd unit (`cadence doctor --unit` prints one) or rtprio in \
             /etc/security/limits.conf",
        ),
    });
    let memlock = parse_limit(limits, "Max locked memory");
    out.push(match (is_root, memlock) {
        (true, _) => Check::new("memlock limit", Status::Ok, "running as root", ""),
        (false, Some(None)) => Check::new("memlock limit", Status::Ok, "unlimited", ""),
        (false, got) => Check::new(
            "memlock limit",
            Status::Warn,
            format!(
                "{} bytes: mlockall may be refused and page faults can stall real-time threads",
                got.flatten().unwrap_or(0)
            ),
            "set LimitMEMLOCK=infinity in the systemd unit",
        ),
    });
    out
}

/// CPU frequency scaling: `performance` avoids frequency ramps on wake-up.
pub fn check_governors(governors: &[String]) -> Check {
    const NAME: &str = "cpu frequency";
    if governors.is_empty() {
        return Check::new(
            NAME,
            Status::Ok,
            "no cpufreq scaling exposed (fixed frequency or a VM)",
            "",
        );
    }
    let slow: Vec<&str> = governors
        .iter()
        .map(|g| g.trim())
        .filter(|g| *g != "performance")
        .collect();
    if slow.is_empty() {
        Check::new(NAME, Status::Ok, "governor performance on every CPU", "")
    } else {
        Check::new(
            NAME,
            Status::Warn,
            format!("governor {} on {} CPU(s)", slow[0], slow.len()),
            "echo performance | sudo tee /sys/devices/system/cpu/cpu*/cpufreq/scaling_governor",
        )
    }
}

/// Tries SCHED_FIFO on a scratch thread (the finding is whether the OS allows it).
pub fn check_fifo(priority: i32) -> Check {
    const NAME: &str = "SCHED_FIFO";
    let res = std::thread::spawn(move || crate::os::set_current_thread_fifo(priority))
        .join()
        .map_err(|_| "the probe thread panicked".to_string())
        .and_then(|r| r.map_err(|e| e.to_string()));
    match res {
        Ok(()) => Check::new(NAME, Status::Ok, format!("granted at priority {priority}"), ""),
        Err(e) => Check::new(
            NAME,
            Status::Fail,
            format!("refused: {e}"),
            "run as root, or give the service LimitRTPRIO=99 / CAP_SYS_NICE",
        ),
    }
}

/// Wake-up latency of a thread sleeping `period` (under SCHED_FIFO when allowed), like
/// cyclictest: how late each wake-up comes, in a histogram.
pub fn measure_wakeup(samples: usize, period: Duration, fifo_priority: Option<i32>) -> (LatencyHist, bool) {
    let handle = std::thread::spawn(move || {
        let fifo = fifo_priority.is_some_and(|p| crate::os::set_current_thread_fifo(p).is_ok());
        let mut hist = LatencyHist::new();
        let mut n = 0;
        crate::wakeup::sleep_loop(period, &mut hist, || {
            n += 1;
            n >= samples
        });
        (hist, fifo)
    });
    handle.join().unwrap_or_else(|_| (LatencyHist::new(), false))
}

/// Whether `/dev/cpu_dma_latency` could be held at 0 (what `[realtime] cpu_dma_latency_zero`
/// does while Cadence runs): `held` is the result of trying.
pub fn check_idle_latency(held: Result<(), String>) -> Check {
    const NAME: &str = "cpu idle latency";
    match held {
        Ok(()) => Check::new(
            NAME,
            Status::Ok,
            "/dev/cpu_dma_latency can be held at 0 (idle CPUs poll while Cadence runs)",
            "",
        ),
        Err(e) => Check::new(
            NAME,
            Status::Warn,
            format!("cannot hold /dev/cpu_dma_latency at 0: {e}"),
            "idle CPUs may sleep deeply and wake late (on this kind of VM: p99.9 homing latency \
             1.6 ms with the hold, 17 ms without); run the service as root or give its user \
             write access to /dev/cpu_dma_latency",
        ),
    }
}

/// Judges a wake-up latency histogram: the 100 ms lead tolerates a lot, but the 25 ms homing
/// budget and step lateness need the tail in the low milliseconds.
pub fn check_wakeup(hist: &LatencyHist, fifo: bool) -> Check {
    const NAME: &str = "wake-up latency";
    let s = hist.summary();
    let under = if fifo { "SCHED_FIFO" } else { "SCHED_OTHER" };
    let detail = format!("{} over {} sleeps ({under})", s.format_latency(), hist.count());
    let max_ms = s.max as f64 * hist.ns_per_unit() / 1e6;
    if hist.count() == 0 {
        Check::new(NAME, Status::Warn, "no samples", "")
    } else if max_ms > 10.0 {
        Check::new(
            NAME,
            Status::Warn,
            detail,
            "tails over 10 ms eat into the 25 ms homing budget: PREEMPT_RT, isolated CPUs, SCHED_FIFO",
        )
    } else {
        Check::new(NAME, Status::Ok, detail, "")
    }
}

/// Options of [`run_checks`].
#[derive(Debug, Clone)]
pub struct DoctorOptions {
    /// SCHED_FIFO priority to try.
    pub fifo_priority: i32,
    /// Wake-up samples (1 ms apart); 0 skips the measurement.
    pub wakeup_samples: usize,
    /// Whether the process runs as root.
    pub is_root: bool,
}

/// Every check, in a stable order.
pub fn run_checks(facts: &HostFacts, opts: &DoctorOptions) -> Vec<Check> {
    let mut out = vec![
        check_preemption(facts.kernel_version.as_deref(), facts.sys_realtime.as_deref()),
        check_fifo(opts.fifo_priority),
    ];
    out.extend(check_limits(facts.limits.as_deref(), opts.is_root));
    out.push(check_rt_throttling(facts.rt_runtime_us.as_deref()));
    out.push(check_isolation(
        facts.isolated.as_deref(),
        facts.cmdline.as_deref(),
        facts.cpus,
    ));
    out.push(check_governors(&facts.governors));
    // Held through the wake-up measurement, as while Cadence runs.
    let hold = crate::os::hold_cpu_dma_latency_zero();
    out.push(check_idle_latency(
        hold.as_ref().map(|_| ()).map_err(|e| e.to_string()),
    ));
    if opts.wakeup_samples > 0 {
        let fifo = out
            .iter()
            .any(|c| c.name == "SCHED_FIFO" && c.status == Status::Ok);
        let (hist, fifo) = measure_wakeup(
            opts.wakeup_samples,
            Duration::from_millis(1),
            fifo.then_some(opts.fifo_priority),
        );
        out.push(check_wakeup(&hist, fifo));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    const LIMITS: &str = "Limit                     Soft Limit           Hard Limit           Units     \n\
Max cpu time              unlimited            unlimited            seconds   \n\
Max locked memory         8388608              8388608              bytes     \n\
Max realtime priority     0                    0                    \n";

    #[test]
    fn preemption_models() {
        let rt = check_preemption(Some("#1 SMP PREEMPT_RT Thu Jan 1"), None);
        assert_eq!(rt.status, Status::Ok);
        assert_eq!(check_preemption(Some("#1 SMP"), Some("1\n")).status, Status::Ok);
        let dynamic = check_preemption(Some("#1 SMP PREEMPT_DYNAMIC Tue"), Some("0"));
        assert_eq!(dynamic.status, Status::Warn);
        assert!(dynamic.detail.contains("not real-time"), "{dynamic}");
        let none = check_preemption(Some("#1 SMP Debian"), None);
        assert!(none.detail.contains("not preemptible"));
        assert_eq!(check_preemption(None, None).status, Status::Warn);
    }

    #[test]
    fn limits_parse_and_judge() {
        assert_eq!(parse_limit(LIMITS, "Max locked memory"), Some(Some(8_388_608)));
        assert_eq!(parse_limit(LIMITS, "Max cpu time"), Some(None));
        assert_eq!(parse_limit(LIMITS, "Max nothing"), None);
        let user = check_limits(Some(LIMITS), false);
        assert_eq!(user[0].status, Status::Fail, "{}", user[0]);
        assert!(user[0].hint.contains("LimitRTPRIO"));
        assert_eq!(user[1].status, Status::Warn);
        let root = check_limits(Some(LIMITS), true);
        assert!(root.iter().all(|c| c.status == Status::Ok));
        assert_eq!(check_limits(None, false)[0].status, Status::Warn);
    }

    #[test]
    fn isolation_and_governors() {
        assert_eq!(
            check_isolation(Some("1\n"), Some("isolcpus=1 nohz_full=1"), 2).status,
            Status::Ok
        );
        let none = check_isolation(Some("\n"), Some("quiet"), 4);
        assert_eq!(none.status, Status::Warn);
        assert!(none.hint.contains("isolcpus=3"), "{none}");
        assert_eq!(check_isolation(None, None, 1).status, Status::Warn);
        assert_eq!(check_governors(&[]).status, Status::Ok);
        assert_eq!(check_governors(&["performance\n".into()]).status, Status::Ok);
        let slow = check_governors(&["performance".into(), "ondemand\n".into()]);
        assert_eq!(slow.status, Status::Warn);
        assert!(slow.detail.contains("ondemand on 1"), "{slow}");
        assert_eq!(check_idle_latency(Ok(())).status, Status::Ok);
        let refused = check_idle_latency(Err("Permission denied (os error 13)".into()));
        assert_eq!(refused.status, Status::Warn);
        assert!(refused.detail.contains("Permission denied"), "{refused}");
    }

    #[test]
    fn uid_from_status() {
        assert_eq!(effective_uid("Name:\tx\nUid:\t1000\t0\t0\t0\nGid:\t1\n"), Some(0));
        assert_eq!(effective_uid("Uid:\t1000\t1000\t1000\t1000\n"), Some(1000));
        assert_eq!(effective_uid("Uid:\n"), None);
        assert_eq!(effective_uid(""), None);
    }

    #[test]
    fn throttling() {
        assert_eq!(check_rt_throttling(Some("-1\n")).status, Status::Ok);
        assert!(check_rt_throttling(Some("950000")).detail.contains("950000"));
        assert_eq!(check_rt_throttling(None).status, Status::Warn);
    }

    #[test]
    fn live_checks_run_anywhere() {
        // Whatever this host allows, the checks complete and say something (no privilege needed).
        let facts = HostFacts::read();
        assert!(facts.cpus >= 1);
        let checks = run_checks(
            &facts,
            &DoctorOptions {
                fifo_priority: 10,
                wakeup_samples: 20,
                is_root: false,
            },
        );
        assert!(checks.iter().any(|c| c.name == "SCHED_FIFO"));
        let wake = checks
            .iter()
            .find(|c| c.name == "wake-up latency")
            .expect("measured");
        assert!(wake.detail.contains("over 20 sleeps"), "{wake}");
        for c in &checks {
            assert!(!c.to_string().is_empty());
        }
    }
}
