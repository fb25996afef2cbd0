//! `cadence serve`: the printer service (arguments → [`cadence::service::ServiceOptions`] →
//! [`cadence::service::run`] until SIGTERM/SIGINT), or with `--role io` the IO stage in its own
//! process (→ [`cadence::io_process::server`] → its report on stdout).

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

use cadence::io_process::server::{self, ServeOptions};
use cadence::printer::{PrinterOptions, PrinterSource};
use cadence::service::ServiceOptions;
use clap::{Args, ValueEnum};
use rt_core::logger::Level;

/// The stages `serve` can run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Role {
    /// The IO stage: MCU connections, fed from the step channels.
    Io,
}

/// Arguments of `cadence serve`.
#[derive(Debug, Args)]
pub struct ServeArgs {
    /// Run one stage only (`io`: the MCU connections for a `print --io-process`); without it,
    /// the printer service.
    #[arg(long, value_enum)]
    pub role: Option<Role>,
    /// Klipper-format printer.cfg (default: the built-in simulated cartesian printer).
    #[arg(long, conflicts_with = "simulated")]
    pub config: Option<PathBuf>,
    /// The built-in simulated cartesian printer (the default without --config).
    #[arg(long)]
    pub simulated: bool,
    /// Klipper's API server socket (Moonraker attaches here), created owner-only.
    #[arg(short = 'a', long = "api-socket", value_name = "PATH")]
    pub api_socket: Option<PathBuf>,
    /// A G-code pseudo-terminal linked at this path (OctoPrint-style senders: `ok` replies,
    /// `!! ` errors).
    #[arg(short = 'I', long = "gcode-pty", value_name = "PATH")]
    pub gcode_pty: Option<PathBuf>,
    /// Also let this group (numeric gid) read and write the API socket.
    #[arg(long, value_name = "GID")]
    pub api_group: Option<u32>,
    /// Service instance: services are named `cadence/<instance>/...` (default `p<pid>`).
    #[arg(long)]
    pub instance: Option<String>,
    /// Simulated MCU clock runs this many times faster than the wall clock.
    #[arg(long)]
    pub time_scale: Option<f64>,
    /// Write the simulated MCU's step trace to this file.
    #[arg(long)]
    pub trace: Option<PathBuf>,
    /// Don't pin threads, use SCHED_FIFO or lock memory.
    #[arg(long)]
    pub no_realtime: bool,
    /// Also write the log to this file (appended).
    #[arg(long, value_name = "PATH")]
    pub log_file: Option<PathBuf>,
    /// Most verbose log level recorded: error, warn, info, debug or trace.
    #[arg(long, default_value = "info", value_name = "LEVEL")]
    pub log_level: Level,
    /// Stop (and fail) when the process with this pid (the planner that started us) is gone
    /// (`--role io`).
    #[arg(long)]
    pub parent_pid: Option<u32>,
    /// Fail when neither a step batch nor a command arrived for this many seconds (0: wait
    /// forever; `--role io`).
    #[arg(long, default_value_t = 120.0)]
    pub idle_timeout: f64,
    /// The virtual sdcard's directory (default: `[virtual_sdcard] path` of the config).
    #[arg(long, value_name = "DIR")]
    pub virtual_sdcard: Option<PathBuf>,
    /// Seconds between attempts to open a printer that failed to start (the service).
    #[arg(long, default_value_t = 5.0)]
    pub retry: f64,
}

pub fn run(args: &ServeArgs) -> Result<(), String> {
    match args.role {
        Some(Role::Io) => run_io(args),
        None => run_service(args),
    }
}

fn run_service(args: &ServeArgs) -> Result<(), String> {
    let quit = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGTERM, signal_hook::consts::SIGINT] {
        signal_hook::flag::register(signal, Arc::clone(&quit))
            .map_err(|e| format!("cannot handle signal {signal}: {e}"))?;
    }
    // `info` reports the config file by its absolute path.
    let config_file = match &args.config {
        Some(p) => Some(std::fs::canonicalize(p).map_err(|e| format!("{}: {e}", p.display()))?),
        None => None,
    };
    let source = match &args.config {
        Some(p) => PrinterSource::ConfigFile(p.clone()),
        None => PrinterSource::Simulated,
    };
    let opts = ServiceOptions {
        source,
        config_file,
        printer: PrinterOptions {
            time_scale: args.time_scale,
            trace: args.trace.clone(),
            realtime: !args.no_realtime,
            log_level: args.log_level,
            log_file: args.log_file.clone(),
            log_to_stderr: true,
            idle_flush: Duration::from_millis(200),
            ..PrinterOptions::default()
        },
        api_socket: args.api_socket.clone(),
        gcode_pty: args.gcode_pty.clone(),
        virtual_sdcard: args.virtual_sdcard.clone(),
        retry_s: args.retry,
    };
    if !(args.retry > 0.0 && args.retry.is_finite()) {
        return Err(format!(
            "--retry {}: must be a positive number of seconds",
            args.retry
        ));
    }
    cadence::service::run(&opts, quit, args.api_group)?;
    eprintln!("cadence serve: stopped");
    Ok(())
}

fn run_io(args: &ServeArgs) -> Result<(), String> {
    let opts = ServeOptions {
        config: args.config.clone(),
        instance: args.instance.clone(),
        time_scale: args.time_scale,
        trace: args.trace.clone(),
        no_realtime: args.no_realtime,
        log_file: args.log_file.clone(),
        log_level: args.log_level,
        parent_pid: args.parent_pid,
        idle_timeout: args.idle_timeout,
    };
    let outcome = server::run(&opts, &mut |w| eprintln!("cadence serve: warning: {w}"))?;
    for line in &outcome.report {
        println!("{line}");
    }
    for line in &outcome.rt_report {
        eprintln!("cadence serve: {line}");
    }
    Ok(outcome.result?)
}
