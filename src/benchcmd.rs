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
        /// Plan the file this many times in this process and also print the wall time's
        /// minimum, median and maximum (this VM's speed varies by tens of percent from one
        /// minute to the next; every run must give the same commands).
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=1000))]
        runs: u32,
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
            runs,
        } => {
            let cfg = crate::machine::load_config(config.as_deref())?;
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
            if *runs > 1 {
                let mut walls = vec![report.wall_s];
                for run in 2..=*runs {
                    let again = bench::plan::plan_file(file, &cfg, &opts)?;
                    if (again.queue_steps, again.wire_bytes) != (report.queue_steps, report.wire_bytes) {
                        return Err(format!(
                            "run {run} gave {} queue_step in {} wire bytes, the first {} in {}: \
                             planning is not deterministic",
                            again.queue_steps, again.wire_bytes, report.queue_steps, report.wire_bytes
                        ));
                    }
                    walls.push(again.wall_s);
                }
                println!("{}", wall_spread(&mut walls));
            }
            Ok(())
        }
    }
}

/// `wall over N runs: min …, median …, max … s` (sorts `walls`, which holds at least one).
fn wall_spread(walls: &mut [f64]) -> String {
    walls.sort_by(f64::total_cmp);
    let n = walls.len();
    let median = if n % 2 == 1 {
        walls[n / 2]
    } else {
        (walls[n / 2 - 1] + walls[n / 2]) / 2.0
    };
    format!(
        "wall over {n} runs: min {:.4} s, median {median:.4} s, max {:.4} s",
        walls[0],
        walls[n - 1]
    )
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wall_spread_gives_min_median_max() {
        assert_eq!(
            wall_spread(&mut [0.3, 0.1, 0.2]),
            "wall over 3 runs: min 0.1000 s, median 0.2000 s, max 0.3000 s"
        );
        assert_eq!(
            wall_spread(&mut [0.4, 0.1, 0.2, 0.3]),
            "wall over 4 runs: min 0.1000 s, median 0.2500 s, max 0.4000 s"
        );
    }

    #[test]
    fn clock_freq_is_checked() {
        assert_eq!(parse_clock_freq("16000000"), Ok(16e6));
        assert!(parse_clock_freq("10").unwrap_err().contains("expected Hz"));
        assert!(parse_clock_freq("fast").is_err());
    }
}
