//! The `cadence` command line: one module per subcommand, each turning its arguments into the
//! library's options, calling the library and printing the result. No engine code lives here.

pub mod check_config;
pub mod decode;
pub mod dictionary;
pub mod doctor;
pub mod home;
pub mod print;
pub mod progress;
pub mod serve;
pub mod service;
pub mod signals;

use std::path::PathBuf;

use clap::Args;

/// Options of the commands that drive the MCUs (`print`, `home`).
#[derive(Debug, Args)]
pub struct MotionArgs {
    /// Simulated MCU clock runs this many times faster than the wall clock (default: the
    /// config's [simulator] time_scale, else 1).
    #[arg(long)]
    pub time_scale: Option<f64>,
    /// Write the simulated MCU's step trace to this file (another MCU's gets `-NAME` inserted).
    #[arg(long)]
    pub trace: Option<PathBuf>,
    /// Maximum step time error of the compression, in microseconds.
    #[arg(long, default_value_t = 25.0)]
    pub max_error_us: f64,
    /// Don't pin threads, use SCHED_FIFO or lock memory (otherwise printer.cfg's `[realtime]`).
    #[arg(long)]
    pub no_realtime: bool,
}
