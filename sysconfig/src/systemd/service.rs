//! The systemd unit that runs `cadence serve` on a printer's board: the real-time limits its
//! threads need from printer.cfg's `[realtime]` (`LimitRTPRIO` up to the highest SCHED_FIFO
//! priority, `LimitMEMLOCK=infinity` for mlockall, `CPUAffinity` over the pinned CPUs), a
//! dedicated user in the serial group, `Restart=on-failure`, and hardening that keeps the
//! serial devices, `/dev/shm` (iceoryx2) and the API socket's directory reachable.
//!
//! The process itself is not given `CPUSchedulingPolicy=fifo`: the planner and IO threads set
//! their own SCHED_FIFO priorities from `[realtime]`, while the API server, the worker and the
//! logger stay ordinary threads that must never preempt them.

use std::path::PathBuf;

use super::quote;
use crate::printer::RealtimeSection;

/// What the unit runs.
#[derive(Debug, Clone)]
pub struct ServiceUnit {
    /// Absolute path of the `cadence` executable.
    pub exe: PathBuf,
    /// Absolute path of printer.cfg.
    pub config: PathBuf,
    /// The API socket front ends attach to.
    pub api_socket: PathBuf,
    /// The user the service runs as (a dedicated one: `cadence`).
    pub user: String,
    /// The group that owns the serial devices (`dialout` on Debian).
    pub serial_group: String,
    /// Group also allowed on the API socket (Moonraker's user's group), by gid.
    pub api_group: Option<u32>,
    pub realtime: RealtimeSection,
    /// The log file (its directory is made writable).
    pub log_file: Option<PathBuf>,
}

/// The unit file's text.
pub fn unit_text(u: &ServiceUnit) -> String {
    let mut args = vec![
        u.exe.display().to_string(),
        "serve".into(),
        "--config".into(),
        u.config.display().to_string(),
        "-a".into(),
        u.api_socket.display().to_string(),
    ];
    if let Some(gid) = u.api_group {
        args.extend(["--api-group".into(), gid.to_string()]);
    }
    if let Some(log) = &u.log_file {
        args.extend(["--log-file".into(), log.display().to_string()]);
    }
    let exec: Vec<String> = args.iter().map(|a| quote(a)).collect();
    let rt = &u.realtime;
    let mut t = String::new();
    let mut line = |s: String| {
        t.push_str(&s);
        t.push('\n');
    };
    line("[Unit]".into());
    line(format!(
        "Description=Cadence printer service ({})",
        u.config.display()
    ));
    line("After=network.target".into());
    line(String::new());
    line("[Service]".into());
    line("Type=simple".into());
    line(format!("User={}", u.user));
    line(format!("SupplementaryGroups={}", u.serial_group));
    line(format!("ExecStart={}", exec.join(" ")));
    line("Restart=on-failure".into());
    line("RestartSec=2".into());
    line("# SIGTERM stops motion, closes the printer and flushes the log.".into());
    line("KillSignal=SIGTERM".into());
    line("TimeoutStopSec=30".into());
    if rt.enabled {
        let top = rt.planner_priority.max(rt.io_priority + 5).clamp(1, 99);
        line(format!(
            "# [realtime]: planner SCHED_FIFO {}, IO stage {} (its links' IO threads {}); the threads set them.",
            rt.planner_priority,
            rt.io_priority,
            rt.io_priority + 5
        ));
        line(format!("LimitRTPRIO={top}"));
        if rt.lock_memory {
            line("LimitMEMLOCK=infinity".into());
        }
        if let Some(io) = rt.io_cpu {
            let mut cpus = vec![rt.planner_cpu, io];
            cpus.sort_unstable();
            cpus.dedup();
            let cpus: Vec<String> = cpus.iter().map(usize::to_string).collect();
            line(format!("CPUAffinity={}", cpus.join(" ")));
        }
        if rt.cpu_dma_latency_zero {
            line("# /dev/cpu_dma_latency (root-only) is held at 0 while the service runs.".into());
            line(format!(
                "ExecStartPre=+/bin/chown {} /dev/cpu_dma_latency",
                quote(&u.user)
            ));
        }
    }
    line("# Hardening that keeps the serial devices and /dev/shm (iceoryx2) reachable.".into());
    line("NoNewPrivileges=yes".into());
    line("ProtectSystem=full".into());
    line("ProtectHome=read-only".into());
    line("ProtectKernelTunables=yes".into());
    line("ProtectKernelModules=yes".into());
    line("ProtectControlGroups=yes".into());
    line("RestrictAddressFamilies=AF_UNIX AF_NETLINK".into());
    line("LockPersonality=yes".into());
    line("RemoveIPC=no".into());
    // A socket in /run/NAME: systemd creates that directory for the service's user.
    if let Some(name) = u
        .api_socket
        .parent()
        .filter(|d| d.parent() == Some(std::path::Path::new("/run")))
        .and_then(|d| d.file_name())
    {
        line(format!("RuntimeDirectory={}", name.to_string_lossy()));
        line("RuntimeDirectoryMode=0750".into());
    }
    let mut writable: Vec<String> = Vec::new();
    for p in [Some(&u.api_socket), u.log_file.as_ref()].into_iter().flatten() {
        if let Some(dir) = p.parent().filter(|d| !d.as_os_str().is_empty()) {
            let d = quote(&dir.display().to_string());
            if !writable.contains(&d) {
                writable.push(d);
            }
        }
    }
    if !writable.is_empty() {
        line(format!("ReadWritePaths={}", writable.join(" ")));
    }
    line(String::new());
    line("[Install]".into());
    line("WantedBy=multi-user.target".into());
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec() -> ServiceUnit {
        ServiceUnit {
            exe: "/usr/local/bin/cadence".into(),
            config: "/home/pi/printer data/printer.cfg".into(),
            api_socket: "/run/cadence/klippy.sock".into(),
            user: "cadence".into(),
            serial_group: "dialout".into(),
            api_group: Some(1000),
            realtime: RealtimeSection::default(),
            log_file: Some("/var/log/cadence/cadence.log".into()),
        }
    }

    #[test]
    fn the_unit_runs_the_service_with_the_realtime_settings() {
        let mut s = spec();
        s.realtime.planner_priority = 70;
        s.realtime.io_priority = 80;
        s.realtime.planner_cpu = 2;
        s.realtime.io_cpu = Some(3);
        let u = unit_text(&s);
        assert!(
            u.contains(
                "ExecStart=/usr/local/bin/cadence serve --config \"/home/pi/printer data/printer.cfg\" \
             -a /run/cadence/klippy.sock --api-group 1000 --log-file /var/log/cadence/cadence.log\n"
            ),
            "{u}"
        );
        for want in [
            "User=cadence",
            "SupplementaryGroups=dialout",
            "Restart=on-failure",
            "LimitRTPRIO=85",
            "LimitMEMLOCK=infinity",
            "CPUAffinity=2 3",
            "ReadWritePaths=/run/cadence /var/log/cadence",
            "RuntimeDirectory=cadence",
        ] {
            assert!(u.lines().any(|l| l == want), "missing {want}\n{u}");
        }
        s.realtime.enabled = false;
        let u = unit_text(&s);
        assert!(!u.contains("LimitRTPRIO"), "{u}");
    }
}
