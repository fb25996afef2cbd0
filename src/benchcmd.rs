//! `cadence bench plan FILE [--config printer.cfg]`: planning + step compression throughput in
//! batch mode (moves/s, steps/s, queue_step commands, wire bytes, wall time, peak RSS), using
//! the `bench` crate (also available as a criterion bench: `cargo bench -p bench`).

use std::path::PathBuf;

use clap::{Args, Subcommand};

/// Arguments of `cadence bench`.
#[derive(Debug, Args)]
pub struct BenchArgs {
    #[command(subcommand)]
    pub what: BenchWhat,
}

/// What to measure.
#[derive(Debug, Subcommand)]
pub enum BenchWhat {
    /// Plan and compress a G-code file flat out and print the figures.
    Plan {
        /// The G-code file.
        file: PathBuf,
        /// Klipper-format printer.cfg (default: the built-in simulated printer).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Threads generating and compressing steps, this one included (default: one per core;
        /// 1 and 2 both start one worker beside this thread; 0 = all on this thread).
        #[arg(long)]
        threads: Option<usize>,
        /// Maximum step time error of the compression, in microseconds.
        #[arg(long, default_value_t = 25.0)]
        max_error_us: f64,
        /// MCU clock in Hz (default: the Cadence firmware's, 50 MHz); e.g. 16000000 to compare
        /// with an ATmega2560 board.
        #[arg(long, value_parser = parse_clock_freq)]
        clock_freq: Option<f64>,
    },
}

pub fn run(args: &BenchArgs) -> Result<(), String> {
    match &args.what {
        BenchWhat::Plan {
            file,
            config,
            threads,
            max_error_us,
            clock_freq,
        } => {
            let cfg = match config {
                Some(p) => sysconfig::printer::load(p).map_err(|e| e.to_string())?,
                None => sysconfig::printer::builtin_simulated().map_err(|e| e.to_string())?,
            };
            let dict = crate::decode::load_dictionary(None)?;
            let cores = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
            let opts = bench::plan::PlanOptions {
                threads: threads.unwrap_or(cores),
                max_error_s: max_error_us * 1e-6,
                ..Default::default()
            }
            .with_dictionary(&dict)?;
            let opts = bench::plan::PlanOptions {
                clock_freq: clock_freq.unwrap_or(opts.clock_freq),
                ..opts
            };
            let report = bench::plan::plan_file(file, &cfg, &opts)?;
            println!("{report}");
            Ok(())
        }
    }
}

/// A clock frequency between 1 MHz and 1 GHz.
fn parse_clock_freq(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(f) if (1e6..=1e9).contains(&f) => Ok(f),
        _ => Err(format!(
            "clock frequency {s:?}: expected Hz between 1000000 and 1000000000"
        )),
    }
}
