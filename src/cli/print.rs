//! `cadence print`: arguments → [`PrintJob`] → [`cadence::job::run`] → the report on stdout.

use std::path::PathBuf;

use cadence::batch::BatchReport;
use cadence::job::{LiveOptions, PrintJob, PrintOutcome};
use clap::Args;

use super::MotionArgs;
use rt_core::logger::Level;

/// Arguments of `cadence print`.
#[derive(Debug, Args)]
pub struct PrintArgs {
    /// The G-code file to print.
    pub file: PathBuf,
    /// Klipper-format printer.cfg (default: the built-in simulated cartesian printer).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// No MCU and no real-time waiting: write the exact wire stream to this file (another MCU
    /// with steppers gets its own file, `-NAME` inserted before the extension).
    #[arg(long)]
    pub batch: Option<PathBuf>,
    /// Data dictionary (zlib-compressed JSON as served by identify, or plain JSON as Klipper's
    /// out/klipper.dict) for --batch; default: the Cadence firmware's own.
    #[arg(long)]
    pub dictionary: Option<PathBuf>,
    /// Save the print's latency histograms to this file (HdrHistogram V2 interval log).
    #[arg(long)]
    pub histograms: Option<PathBuf>,
    /// Stop at the first unknown G-code command (by default it is reported once and skipped,
    /// as Klipper does; same as `unknown_commands: error` in printer.cfg's [gcode]).
    #[arg(long)]
    pub strict: bool,
    /// Time scale, trace, compression bound, real time.
    #[command(flatten)]
    pub motion: MotionArgs,
    /// Logging and where the IO stage runs (see [`LiveArgs`]).
    #[command(flatten)]
    pub live: LiveArgs,
}

/// Options of a live print beyond the G-code and the printer (flattened into `print`'s).
#[derive(Debug, Clone, Args)]
pub struct LiveArgs {
    /// Also write the print's log (records of the planner, IO stage and link threads) to this
    /// file (appended).
    #[arg(long, value_name = "PATH")]
    pub log_file: Option<PathBuf>,
    /// Most verbose log level recorded: error, warn, info, debug or trace.
    #[arg(long, default_value = "info", value_name = "LEVEL")]
    pub log_level: Level,
    /// Run the IO stage (the MCU connections) in a separate `cadence serve --role io` process
    /// started for this print. G28 with endstops is refused in this mode.
    #[arg(long)]
    pub io_process: bool,
    /// Like --io-process, but attach to a running `cadence serve --role io --instance NAME`.
    #[arg(long, value_name = "NAME", conflicts_with = "io_process")]
    pub io_attach: Option<String>,
}

impl PrintArgs {
    /// The library's job description.
    pub fn job(&self) -> PrintJob {
        PrintJob {
            file: self.file.clone(),
            config: self.config.clone(),
            time_scale: self.motion.time_scale,
            batch: self.batch.clone(),
            dictionary: self.dictionary.clone(),
            trace: self.motion.trace.clone(),
            max_error_us: self.motion.max_error_us,
            no_realtime: self.motion.no_realtime,
            histograms: self.histograms.clone(),
            strict: self.strict,
            live: LiveOptions {
                log_file: self.live.log_file.clone(),
                log_level: self.live.log_level,
                io_process: self.live.io_process,
                io_attach: self.live.io_attach.clone(),
            },
        }
    }
}

pub fn run(args: &PrintArgs) -> Result<(), String> {
    let outcome = cadence::job::run(&args.job(), &mut |w| eprintln!("cadence: warning: {w}"))?;
    match outcome {
        PrintOutcome::Batch(report) => print_batch(&report),
        PrintOutcome::Live(live) => {
            for line in live.summary.report_lines(&live.link_stats) {
                println!("{line}");
            }
            for line in live.rt_report {
                eprintln!("cadence: {line}");
            }
        }
    }
    Ok(())
}

fn print_batch(r: &BatchReport) {
    let files: Vec<String> = r.outputs.iter().map(|p| p.display().to_string()).collect();
    println!("batch: {} -> {}", r.file.display(), files.join(", "));
    println!(
        "  lines {}, moves {}, print time {:.3} s",
        r.lines, r.moves, r.print_time
    );
    for (name, n) in &r.steps {
        println!("  {name:<10} {n} steps");
    }
    println!(
        "  queue_step {}, blocks {}, wire bytes {}, wall {:.3} s",
        r.queue_steps, r.blocks, r.wire_bytes, r.wall
    );
    for line in &r.accessories {
        println!("  {line}");
    }
}
