//! `cadence home`: arguments → [`HomeOptions`] → [`cadence::home_cycles::run`], its report on
//! stdout and its notes on stderr.

use std::path::PathBuf;

use cadence::home_cycles::{HomeOptions, HomeOutput};
use cadence::homing::AXIS_NAMES;
use clap::Args;

use super::MotionArgs;

/// Arguments of `cadence home`.
#[derive(Debug, Args)]
pub struct HomeArgs {
    /// Klipper-format printer.cfg (default: the built-in simulated cartesian printer).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Axes to home, as letters (e.g. `z`, `xy`).
    #[arg(long, default_value = "xyz")]
    pub axes: String,
    /// Homing cycles; before each one after the first, the axes move `--away` mm off their
    /// endstops.
    #[arg(long, default_value_t = 1)]
    pub cycles: u32,
    /// Distance (mm) the axes move off their endstops between cycles.
    #[arg(long, default_value_t = 5.0)]
    pub away: f64,
    /// Load every core with a SCHED_OTHER busy-spinning thread while homing (stopped at the
    /// end): the loaded latency measurement.
    #[arg(long)]
    pub cpu_load: bool,
    /// Time scale, trace, compression bound, real time.
    #[command(flatten)]
    pub motion: MotionArgs,
}

/// Report lines to stdout, notes to stderr.
struct Console;

impl HomeOutput for Console {
    fn out(&mut self, line: String) {
        println!("{line}");
    }
    fn err(&mut self, line: String) {
        eprintln!("cadence: {line}");
    }
}

pub fn run(args: &HomeArgs) -> Result<(), String> {
    let mut axes = [false; 3];
    for c in args.axes.chars() {
        match AXIS_NAMES.iter().position(|&a| a == c.to_ascii_lowercase()) {
            Some(i) => axes[i] = true,
            None => return Err(format!("--axes {}: '{c}' is not x, y or z", args.axes)),
        }
    }
    let opts = HomeOptions {
        config: args.config.clone(),
        axes,
        cycles: args.cycles,
        away: args.away,
        cpu_load: args.cpu_load,
        time_scale: args.motion.time_scale,
        trace: args.motion.trace.clone(),
        max_error_us: args.motion.max_error_us,
        no_realtime: args.motion.no_realtime,
    };
    Ok(cadence::home_cycles::run(&opts, &mut Console)?)
}
