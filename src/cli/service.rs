//! `cadence service print|install`: the systemd unit of `cadence serve` for a printer.cfg
//! (`sysconfig::systemd::service`), printed or installed (the unit file written, the dedicated
//! user created in the serial group when missing, systemd reloaded).

use std::path::PathBuf;
use std::process::Command;

use clap::{Args, Subcommand};
use sysconfig::systemd::{unit_text, ServiceUnit};

#[derive(Debug, Args)]
pub struct ServiceArgs {
    #[command(subcommand)]
    pub action: Action,
}

#[derive(Debug, Subcommand)]
pub enum Action {
    /// Print the unit on stdout.
    Print(UnitArgs),
    /// Write the unit to the unit directory, create the user if missing, reload systemd.
    Install {
        #[command(flatten)]
        unit: UnitArgs,
        /// Where unit files go.
        #[arg(long, default_value = "/etc/systemd/system")]
        unit_dir: PathBuf,
        /// The unit's file name.
        #[arg(long, default_value = "cadence.service")]
        name: String,
    },
}

#[derive(Debug, Args)]
pub struct UnitArgs {
    /// printer.cfg the service loads (made absolute; its [realtime] sets the limits).
    #[arg(long)]
    pub config: PathBuf,
    /// The API socket front ends (Moonraker) attach to.
    #[arg(short = 'a', long = "api-socket", default_value = "/run/cadence/klippy.sock")]
    pub api_socket: PathBuf,
    /// The dedicated user the service runs as.
    #[arg(long, default_value = "cadence")]
    pub user: String,
    /// The group owning the serial devices.
    #[arg(long, default_value = "dialout")]
    pub serial_group: String,
    /// Also let this group (gid; Moonraker's user's) use the API socket.
    #[arg(long, value_name = "GID")]
    pub api_group: Option<u32>,
    /// The service's log file.
    #[arg(long)]
    pub log_file: Option<PathBuf>,
}

pub fn run(args: &ServiceArgs) -> Result<(), String> {
    match &args.action {
        Action::Print(u) => {
            print!("{}", unit_text(&unit(u)?));
            Ok(())
        }
        Action::Install {
            unit: u,
            unit_dir,
            name,
        } => install(&unit(u)?, unit_dir, name),
    }
}

fn unit(args: &UnitArgs) -> Result<ServiceUnit, String> {
    let exe = std::env::current_exe().map_err(|e| format!("cannot find the cadence executable: {e}"))?;
    let config =
        std::fs::canonicalize(&args.config).map_err(|e| format!("{}: {e}", args.config.display()))?;
    let cfg = sysconfig::printer::load(&config).map_err(|e| format!("{}: {e}", config.display()))?;
    Ok(ServiceUnit {
        exe,
        config,
        api_socket: args.api_socket.clone(),
        user: args.user.clone(),
        serial_group: args.serial_group.clone(),
        api_group: args.api_group,
        realtime: cfg.realtime,
        log_file: args.log_file.clone(),
    })
}

fn install(unit: &ServiceUnit, dir: &std::path::Path, name: &str) -> Result<(), String> {
    let path = dir.join(name);
    std::fs::write(&path, unit_text(unit)).map_err(|e| format!("{}: {e}", path.display()))?;
    println!("wrote {}", path.display());
    let known = Command::new("id")
        .arg("-u")
        .arg(&unit.user)
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    if !known {
        let status = Command::new("useradd")
            .args([
                "--system",
                "--no-create-home",
                "--shell",
                "/usr/sbin/nologin",
                "--groups",
            ])
            .arg(&unit.serial_group)
            .arg(&unit.user)
            .status()
            .map_err(|e| format!("useradd: {e}"))?;
        if !status.success() {
            return Err(format!("useradd {} failed ({status})", unit.user));
        }
        println!("created user {} in group {}", unit.user, unit.serial_group);
    }
    match Command::new("systemctl").arg("daemon-reload").status() {
        Ok(s) if s.success() => println!("systemd reloaded: `systemctl enable --now {name}` starts it"),
        Ok(s) => println!("systemctl daemon-reload failed ({s}): reload systemd before starting {name}"),
        Err(e) => println!("no systemctl here ({e}): reload systemd before starting {name}"),
    }
    Ok(())
}
