//! The host facts printed above every benchmark (and in its JSON): kernel and preemption model,
//! CPU frequency governor, isolated CPUs, real-time throttling and SMT. The raw facts come from
//! `rt_core::host_check::HostFacts` (what `cadence doctor` reads); this module only adds SMT and
//! the kernel release and turns them into short strings.

use rt_core::host_check::HostFacts;
use serde::{Deserialize, Serialize};

/// What a latency figure depends on, in words.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Host {
    /// Kernel release (`uname -r`).
    pub kernel: String,
    /// Preemption model: `PREEMPT_RT`, `PREEMPT_DYNAMIC (full)`, `PREEMPT`, `none`.
    pub preempt: String,
    /// Frequency governors of the CPUs (`none` without cpufreq, e.g. in a VM).
    pub governor: String,
    /// `/sys/devices/system/cpu/isolated` (`none` when empty).
    pub isolated_cpus: String,
    /// `off`, or the SCHED_FIFO budget as `runtime/period µs`.
    pub rt_throttling: String,
    /// SMT control and whether it is active (`on, active`, `notsupported`...).
    pub smt: String,
    /// Online CPUs.
    pub cpus: usize,
}

fn read(path: &str) -> Option<String> {
    std::fs::read_to_string(path).ok().map(|s| s.trim().to_string())
}

impl Host {
    /// Reads this host.
    pub fn read() -> Host {
        let facts = HostFacts::read();
        Host::from_facts(
            &facts,
            read("/proc/sys/kernel/osrelease"),
            read("/sys/kernel/debug/sched/preempt"),
            read("/proc/sys/kernel/sched_rt_period_us"),
            read("/sys/devices/system/cpu/smt/control"),
            read("/sys/devices/system/cpu/smt/active"),
        )
    }

    /// The facts in words (pure: tests give fixtures).
    pub fn from_facts(
        facts: &HostFacts,
        release: Option<String>,
        debug_preempt: Option<String>,
        rt_period_us: Option<String>,
        smt_control: Option<String>,
        smt_active: Option<String>,
    ) -> Host {
        let mut governors: Vec<&str> = facts.governors.iter().map(|g| g.trim()).collect();
        governors.sort_unstable();
        governors.dedup();
        let isolated = facts.isolated.as_deref().map(str::trim).unwrap_or("");
        Host {
            kernel: release.unwrap_or_else(|| "unknown".into()),
            preempt: preempt_model(
                facts.kernel_version.as_deref(),
                facts.sys_realtime.as_deref(),
                debug_preempt.as_deref(),
            ),
            governor: if governors.is_empty() {
                "none (no cpufreq)".into()
            } else {
                governors.join(",")
            },
            isolated_cpus: if isolated.is_empty() {
                "none".into()
            } else {
                isolated.into()
            },
            rt_throttling: match (facts.rt_runtime_us.as_deref().map(str::trim), rt_period_us) {
                (Some("-1"), _) => "off".into(),
                (Some(rt), Some(period)) => format!("{rt}/{period} µs"),
                (Some(rt), None) => format!("{rt} µs per period"),
                (None, _) => "unknown".into(),
            },
            smt: match (smt_control, smt_active.as_deref()) {
                (Some(c), Some("1")) => format!("{c}, active"),
                (Some(c), Some(_)) => format!("{c}, inactive"),
                (Some(c), None) => c,
                (None, _) => "unknown".into(),
            },
            cpus: facts.cpus,
        }
    }

    /// Two lines for the text header.
    pub fn header(&self) -> [String; 2] {
        [
            format!(
                "host: kernel {} ({}), {} CPUs, SMT {}",
                self.kernel, self.preempt, self.cpus, self.smt
            ),
            format!(
                "      governor {}, isolated CPUs {}, RT throttling {}",
                self.governor, self.isolated_cpus, self.rt_throttling
            ),
        ]
    }
}

/// The preemption model from the kernel version string (`uname -v`), `/sys/kernel/realtime`,
/// and `/sys/kernel/debug/sched/preempt` (the dynamic model's choice in parentheses).
pub fn preempt_model(
    version: Option<&str>,
    sys_realtime: Option<&str>,
    debug_preempt: Option<&str>,
) -> String {
    let v = version.unwrap_or("");
    if sys_realtime.is_some_and(|s| s.trim() == "1") || v.contains("PREEMPT_RT") {
        return "PREEMPT_RT".into();
    }
    let chosen = debug_preempt.and_then(|s| {
        let open = s.find('(')?;
        let close = s[open..].find(')')?;
        Some(s[open + 1..open + close].to_string())
    });
    if v.contains("PREEMPT_DYNAMIC") {
        return match chosen {
            Some(c) => format!("PREEMPT_DYNAMIC ({c})"),
            None => "PREEMPT_DYNAMIC".into(),
        };
    }
    if v.split_whitespace().any(|w| w == "PREEMPT") {
        return "PREEMPT".into();
    }
    if version.is_none() {
        return "unknown".into();
    }
    "none (not preemptible)".into()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn preempt_models() {
        assert_eq!(
            preempt_model(Some("#1 SMP PREEMPT_RT Thu"), None, None),
            "PREEMPT_RT"
        );
        assert_eq!(preempt_model(Some("#1 SMP"), Some("1\n"), None), "PREEMPT_RT");
        assert_eq!(
            preempt_model(
                Some("#1 SMP PREEMPT_DYNAMIC @0"),
                None,
                Some("none voluntary (full) lazy")
            ),
            "PREEMPT_DYNAMIC (full)"
        );
        assert_eq!(
            preempt_model(Some("#1 SMP PREEMPT_DYNAMIC"), None, None),
            "PREEMPT_DYNAMIC"
        );
        assert_eq!(preempt_model(Some("#1 SMP PREEMPT Tue"), None, None), "PREEMPT");
        assert_eq!(
            preempt_model(Some("#1 SMP Debian"), None, None),
            "none (not preemptible)"
        );
        assert_eq!(preempt_model(None, None, None), "unknown");
    }

    #[test]
    fn facts_in_words() {
        let facts = HostFacts {
            kernel_version: Some("#1 SMP PREEMPT_DYNAMIC".into()),
            isolated: Some("\n".into()),
            rt_runtime_us: Some("950000\n".into()),
            governors: vec!["performance\n".into(), "performance".into()],
            cpus: 2,
            ..HostFacts::default()
        };
        let h = Host::from_facts(
            &facts,
            Some("6.1.0".into()),
            None,
            Some("1000000".into()),
            Some("on".into()),
            Some("1".into()),
        );
        assert_eq!(h.governor, "performance");
        assert_eq!(h.isolated_cpus, "none");
        assert_eq!(h.rt_throttling, "950000/1000000 µs");
        assert_eq!(h.smt, "on, active");
        assert!(
            h.header()[0].contains("kernel 6.1.0 (PREEMPT_DYNAMIC), 2 CPUs"),
            "{:?}",
            h.header()
        );
        let off = HostFacts {
            rt_runtime_us: Some("-1".into()),
            isolated: Some("1\n".into()),
            ..HostFacts::default()
        };
        let h = Host::from_facts(&off, None, None, None, None, None);
        assert_eq!((h.rt_throttling.as_str(), h.isolated_cpus.as_str()), ("off", "1"));
        assert_eq!(h.governor, "none (no cpufreq)");
    }

    #[test]
    fn this_host_reads() {
        let h = Host::read();
        assert!(h.cpus >= 1);
        assert!(!h.kernel.is_empty());
    }
}
