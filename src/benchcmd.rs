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
        /// Step generation threads (default: one per core).
        #[arg(long)]
        threads: Option<usize>,
        /// Maximum step time error of the compression, in microseconds.
        #[arg(long, default_value_t = 25.0)]
        max_error_us: f64,
    },
}

pub fn run(args: &BenchArgs) -> Result<(), String> {
    match &args.what {
        BenchWhat::Plan {
            file,
            config,
            threads,
            max_error_us,
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
            let report = bench::plan::plan_file(file, &cfg, &opts)?;
            println!("{report}");
            Ok(())
        }
    }
}
