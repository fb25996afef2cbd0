//! `cadence serve --role io`: arguments → [`ServeOptions`] → [`cadence::io_process::server`]
//! → its report on stdout.

use std::path::PathBuf;

use cadence::io_process::server::{self, ServeOptions};
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
    /// The stage to run in this process.
    #[arg(long, value_enum)]
    pub role: Role,
    /// Klipper-format printer.cfg (default: the built-in simulated cartesian printer); the
    /// planner must load the same one (checked through the configuration CRC).
    #[arg(long)]
    pub config: Option<PathBuf>,
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
    /// Stop (and fail) when the process with this pid (the planner that started us) is gone.
    #[arg(long)]
    pub parent_pid: Option<u32>,
    /// Fail when neither a step batch nor a command arrived for this many seconds (0: wait
    /// forever).
    #[arg(long, default_value_t = 120.0)]
    pub idle_timeout: f64,
}

pub fn run(args: &ServeArgs) -> Result<(), String> {
    let Role::Io = args.role;
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
    outcome.result
}
