//! `cadence print`: arguments → [`PrintJob`] → [`cadence::job::run_with`] → the report on
//! stdout. A live print shows its progress on stderr ([`super::progress`]) and ends cleanly on
//! Ctrl-C or SIGTERM ([`super::signals`]): the file is read no further, what was planned moves,
//! the summary follows an "interrupted at line N" note and the exit status is 130 or 143.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use cadence::batch::BatchReport;
use cadence::gcode_feed::GcodeInput;
use cadence::job::{LiveOptions, PrintJob, PrintOutcome, Progress};
use cadence::summary::human_duration;
use clap::Args;

use super::progress::Display;
use super::signals::{self, StopRequest};
use super::MotionArgs;
use cadence::gcode_source::GcodeSource;
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
    /// Write the summary as JSON on stdout instead of text.
    #[arg(long)]
    pub json: bool,
    /// No progress display on stderr.
    #[arg(long)]
    pub no_progress: bool,
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
    /// started for this print. G28 with endstops and heater/fan commands that turn something on
    /// are refused in this mode.
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
                interrupt: None,
            },
        }
    }
}

/// Runs `cadence print`; the exit status (0, or 130/143 after SIGINT/SIGTERM).
pub fn run(args: &PrintArgs) -> Result<u8, String> {
    let file_bytes = std::fs::metadata(&args.file)
        .map_err(|e| format!("{}: {e}", args.file.display()))?
        .len();
    if file_bytes == 0 {
        eprintln!(
            "cadence: warning: {} is empty: nothing to print",
            args.file.display()
        );
        return Ok(0);
    }
    let mut job = args.job();
    let mut warn = |w: &str| eprintln!("cadence: warning: {w}");
    let stop = StopRequest::default();
    if job.batch.is_none() {
        let interrupt = Arc::new(AtomicBool::new(false));
        job.live.interrupt = Some(interrupt.clone());
        signals::install(&stop, move |sig| {
            interrupt.store(true, Ordering::Release);
            eprintln!("\ncadence: {sig}: stopping after the moves already planned (again to exit at once)");
        })?;
    }
    let (source, pos) =
        GcodeSource::open(&args.file, stop.clone()).map_err(|e| format!("{}: {e}", args.file.display()))?;
    let input = GcodeInput::from_reader(args.file.clone(), source);
    if job.batch.is_some() {
        let outcome = cadence::job::run_with(&job, Some(input), &mut warn, None)?;
        report(args, &outcome);
        return Ok(0);
    }
    let plain = args.live.log_file.is_some();
    let display = (!args.no_progress).then(|| Display::new(pos.clone(), file_bytes, plain));
    let observe = |p: &Progress| {
        if let Some(d) = &display {
            d.update(p);
        }
    };
    let result = cadence::job::run_with(&job, Some(input), &mut warn, Some(&observe));
    if let Some(d) = &display {
        d.finish();
    }
    let outcome = result.map_err(|e| explain(&e.to_string(), args.motion.time_scale))?;
    let code = match stop.signal() {
        Some(sig) if pos.cut.load(Ordering::Acquire) => {
            let bytes = pos.bytes.load(Ordering::Relaxed);
            let line = pos.lines.load(Ordering::Relaxed);
            let print_time = match &outcome {
                PrintOutcome::Live(l) => l.summary.print_time,
                PrintOutcome::Batch(b) => b.print_time,
            };
            eprintln!(
                "cadence: interrupted ({sig}) at line {line} ({:.1} % of the file, print time {})",
                bytes as f64 * 100.0 / file_bytes as f64,
                human_duration(print_time)
            );
            signals::exit_code(sig)
        }
        Some(sig) => {
            eprintln!("cadence: {sig} came after the whole file was read: the print ran to its end");
            signals::exit_code(sig)
        }
        None => 0,
    };
    report(args, &outcome);
    Ok(code)
}

/// `error` with a plain explanation when, at a raised time scale, a step reached the simulated
/// MCU too late (`Timer too close`) or could not leave the host in time (`fell behind`): the
/// simulation did not keep up with its clock on this machine.
fn explain(error: &str, time_scale: Option<f64>) -> String {
    match time_scale {
        Some(scale)
            if scale > 1.0 && (error.contains("Timer too close") || error.contains("fell behind")) =>
        {
            let load = super::progress::load_average();
            let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
            let lower = (scale / 2.5).floor().max(1.0);
            format!(
                "{error}\n  the simulation could not keep up at --time-scale {scale}: the simulated MCU has \
                 to run {scale} s of printer time (and emit {scale}× the steps) every second, and on \
                 this machine (load average {load} on {cpus} CPUs) a step command did not reach it \
                 in time; try --time-scale {lower}"
            )
        }
        _ => error.to_string(),
    }
}

fn report(args: &PrintArgs, outcome: &PrintOutcome) {
    match outcome {
        PrintOutcome::Batch(report) => print_batch(report),
        PrintOutcome::Live(live) if args.json => {
            println!("{}", live.summary.to_json(&live.link_stats));
        }
        PrintOutcome::Live(live) => {
            println!("print: {}", live.summary.file.display());
            for line in live.summary.report_lines(&live.link_stats) {
                println!("{line}");
            }
            for line in &live.rt_report {
                eprintln!("cadence: {line}");
            }
        }
    }
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

#[cfg(test)]
mod tests {
    use super::explain;

    #[test]
    fn a_late_step_at_a_raised_time_scale_is_explained() {
        let e = explain("mcu 'mcu' shut down: Timer too close", Some(50.0));
        assert!(e.starts_with("mcu 'mcu' shut down: Timer too close\n"), "{e}");
        assert!(
            e.contains("could not keep up at --time-scale 50") && e.ends_with("try --time-scale 20"),
            "{e}"
        );
        assert_eq!(
            explain("mcu 'mcu' shut down: Timer too close", None),
            "mcu 'mcu' shut down: Timer too close"
        );
        assert_eq!(explain("bad line", Some(50.0)), "bad line");
    }
}
