//! The systemd unit that runs Cadence's IO stage alone as a service on a PREEMPT_RT board.
//!
//! That service is the IO stage (`cadence serve --role io`): it owns the MCU connections and
//! serves prints that attach to it (`cadence print --io-attach INSTANCE FILE.gcode`). The unit
//! grants what the real-time threads need without running as root: `LimitRTPRIO` (SCHED_FIFO),
//! `LimitMEMLOCK` (mlockall), access to serial devices through the `dialout` group, and
//! `Restart=always` so that a new IO stage is ready after each print or MCU failure.

use std::fmt::Write as _;
use std::path::PathBuf;

use super::quote;

/// What the generated unit runs.
#[derive(Debug, Clone, PartialEq)]
pub struct UnitSpec {
    /// Absolute path of the `cadence` executable.
    pub exe: PathBuf,
    /// Absolute path of the printer.cfg.
    pub config: PathBuf,
    /// Service instance name (`cadence/<instance>/...` services; prints attach to it).
    pub instance: String,
    /// User the service runs as.
    pub user: String,
    /// CPUs the service may use (`CPUAffinity=`); empty = all. The [realtime] section still
    /// pins each thread inside this set.
    pub cpus: Vec<usize>,
}

/// The unit file text.
pub fn unit(spec: &UnitSpec) -> String {
    let exec = [
        spec.exe.display().to_string(),
        "serve".into(),
        "--role".into(),
        "io".into(),
        "--config".into(),
        spec.config.display().to_string(),
        "--instance".into(),
        spec.instance.clone(),
        "--idle-timeout".into(),
        "0".into(),
    ]
    .iter()
    .map(|a| quote(a))
    .collect::<Vec<_>>()
    .join(" ");
    let mut u = String::new();
    let _ = writeln!(u, "[Unit]");
    let _ = writeln!(
        u,
        "Description=Cadence motion kernel (IO stage, instance {})",
        spec.instance
    );
    let _ = writeln!(u, "After=network.target");
    let _ = writeln!(u);
    let _ = writeln!(u, "[Service]");
    let _ = writeln!(u, "Type=simple");
    let _ = writeln!(u, "User={}", spec.user);
    let _ = writeln!(u, "SupplementaryGroups=dialout");
    let _ = writeln!(u, "ExecStart={exec}");
    let _ = writeln!(u, "Restart=always");
    let _ = writeln!(u, "RestartSec=1");
    let _ = writeln!(u, "# SCHED_FIFO and mlockall without root:");
    let _ = writeln!(u, "LimitRTPRIO=99");
    let _ = writeln!(u, "LimitMEMLOCK=infinity");
    let _ = writeln!(
        u,
        "# [realtime] cpu_dma_latency_zero holds /dev/cpu_dma_latency (root-only) at 0 while it runs:"
    );
    let _ = writeln!(
        u,
        "ExecStartPre=+/bin/chown {} /dev/cpu_dma_latency",
        quote(&spec.user)
    );
    if !spec.cpus.is_empty() {
        let cpus: Vec<String> = spec.cpus.iter().map(|c| c.to_string()).collect();
        let _ = writeln!(u, "CPUAffinity={}", cpus.join(" "));
    }
    let _ = writeln!(
        u,
        "# iceoryx2 shared memory lives in /dev/shm; keep it across restarts of others."
    );
    let _ = writeln!(u, "RemoveIPC=no");
    let _ = writeln!(u);
    let _ = writeln!(u, "[Install]");
    let _ = writeln!(u, "WantedBy=multi-user.target");
    u
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec() -> UnitSpec {
        UnitSpec {
            exe: "/usr/local/bin/cadence".into(),
            config: "/home/pi/printer data/printer.cfg".into(),
            instance: "printer".into(),
            user: "pi".into(),
            cpus: vec![1, 2],
        }
    }

    #[test]
    fn unit_runs_the_io_stage_with_rt_limits() {
        let u = unit(&spec());
        assert!(u.contains(
            "ExecStart=/usr/local/bin/cadence serve --role io --config \"/home/pi/printer data/printer.cfg\" \
             --instance printer --idle-timeout 0\n"
        ));
        for line in [
            "User=pi",
            "LimitRTPRIO=99",
            "LimitMEMLOCK=infinity",
            "ExecStartPre=+/bin/chown pi /dev/cpu_dma_latency",
            "CPUAffinity=1 2",
            "Restart=always",
        ] {
            assert!(u.lines().any(|l| l == line), "missing {line}\n{u}");
        }
        assert!(u.starts_with("[Unit]\n"));
    }

    #[test]
    fn no_affinity_line_without_cpus() {
        let u = unit(&UnitSpec {
            cpus: vec![],
            ..spec()
        });
        assert!(!u.contains("CPUAffinity"));
    }
}
