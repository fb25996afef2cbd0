//! `cadence bench wakeup|handoff|plan|pipeline|homing`: the command line of the benchmarks.
//! `wakeup`, `handoff` and `plan` run in the `bench` crate (which prints their reports); this
//! module only turns arguments into their options. `pipeline` and `homing` need the running
//! printer, so they run here ([`pipeline`], [`homing`]) over the `cadence` library and report
//! through `bench`'s session (same schema, logs and plots). Every mode takes the common
//! options (`--json`, `--hlog`, `--plot`, `--load`, `--budget-us`, `--no-progress`).

mod error;
mod homing;
mod pipeline;
mod trace_dir;

use std::path::PathBuf;
use std::time::Duration;

use bench::handoff::{ChildCommand, HandoffOpts};
use bench::load::{LoadKind, LoadTool};
use bench::modes::wakeup::WakeupMode;
use bench::run::Common;
use bench::wakeup::{Stop, Wait, WakeupOptions};
use clap::{Args, Subcommand};

pub use error::{ArgError, BenchCmdError, McuTraceError, PrintFailure};

/// Arguments of `cadence bench`.
#[derive(Debug, Args)]
pub struct BenchArgs {
    #[command(subcommand)]
    pub what: BenchWhat,
}

/// Options every mode takes.
#[derive(Debug, Clone, Args)]
pub struct CommonArgs {
    /// Print the results as one JSON document (schema `cadence-bench/1`, see README) instead of
    /// text.
    #[arg(long)]
    pub json: bool,
    /// Write the latencies as an HdrHistogram V2 interval log (one tagged interval per thread
    /// and second) that HdrHistogram's tools read.
    #[arg(long, value_name = "FILE")]
    pub hlog: Option<PathBuf>,
    /// Draw the latency histogram and percentile distribution (log-scaled, with the budget
    /// line) to FILE.svg or FILE.png.
    #[arg(long, value_name = "FILE")]
    pub plot: Option<PathBuf>,
    /// Stress the machine during the run: cpu, io or mem (stress-ng when installed, else
    /// built-in threads).
    #[arg(long, value_name = "cpu|io|mem")]
    pub load: Option<LoadKind>,
    /// Which stressor `--load` uses: auto, stress-ng or builtin.
    #[arg(long, default_value = "auto", value_name = "TOOL")]
    pub load_tool: LoadTool,
    /// The budget drawn in plots and judged in the verdict, in µs (wakeup: 25000, the homing
    /// budget; 0 = none).
    #[arg(long, value_name = "US", value_parser = parse_budget)]
    pub budget_us: Option<f64>,
    /// No progress bar (it only shows on a terminal, on runs of 3 s or more).
    #[arg(long)]
    pub no_progress: bool,
    /// A saved `--json` report of the same mode: print this run's figures and percentiles over
    /// its, figure by figure.
    #[arg(long, value_name = "REPORT.json")]
    pub compare: Option<PathBuf>,
}

/// What to measure.
#[derive(Debug, Subcommand)]
pub enum BenchWhat {
    /// Wake-up latency like cyclictest: a pinned SCHED_FIFO thread per CPU sleeping to absolute
    /// deadlines (or busy-waiting); with --compare-cyclictest, cyclictest in alternating slices.
    Wakeup {
        /// CPUs to measure on, one pinned thread each (default: every CPU).
        #[arg(long, value_delimiter = ',', value_name = "LIST")]
        cpus: Vec<usize>,
        /// SCHED_FIFO priority of the threads (0 = normal scheduling); refused → normal, noted.
        #[arg(long, default_value_t = 80, value_parser = clap::value_parser!(i32).range(0..=99))]
        priority: i32,
        /// Wake-up period in µs.
        #[arg(long, default_value_t = 1000, value_parser = clap::value_parser!(u64).range(50..=10_000_000))]
        interval_us: u64,
        /// How long to run: 10, 10s, 500ms, 2m, 1h.
        #[arg(long, default_value = "10s", value_parser = parse_duration, conflicts_with = "loops")]
        duration: Duration,
        /// Stop after this many wake-ups per thread instead of a duration.
        #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
        loops: Option<u64>,
        /// Spin on the clock until each deadline instead of sleeping.
        #[arg(long)]
        busy_wait: bool,
        /// Do not lock memory (mlockall).
        #[arg(long)]
        no_mlock: bool,
        /// Also run cyclictest (Debian: rt-tests) with the same settings in alternating slices
        /// and print each percentile's ratio.
        #[arg(long)]
        compare_cyclictest: bool,
        /// Seconds each tool runs per slice with --compare-cyclictest.
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..=3600))]
        slice_s: u64,
        #[command(flatten)]
        common: CommonArgs,
    },
    /// Hand-off latency between two pinned threads or processes: ArrayQueue and the project's
    /// HandoffQueue polled, a parking consumer, iceoryx2 polled and event-woken.
    Handoff {
        /// Messages per transport.
        #[arg(long, default_value_t = 50_000, value_parser = clap::value_parser!(u64).range(1..))]
        samples: u64,
        /// Time between messages in µs.
        #[arg(long, default_value_t = 20)]
        gap_us: u64,
        /// SCHED_FIFO priority of producer and consumer (default: normal scheduling).
        #[arg(long, value_parser = clap::value_parser!(i32).range(1..=99))]
        fifo: Option<i32>,
        /// Producer and consumer CPUs.
        #[arg(
            long,
            value_delimiter = ',',
            num_args = 1,
            default_value = "0,1",
            value_name = "P,C"
        )]
        cores: Vec<usize>,
        /// Skip the transports whose consumer is another process.
        #[arg(long)]
        no_process: bool,
        #[command(flatten)]
        common: CommonArgs,
    },
    /// The consumer process of `bench handoff` (started by it).
    #[command(hide = true)]
    HandoffChild {
        service: String,
        samples: u64,
        mode: String,
        core: usize,
    },
    /// A live print on the simulated printer (or --config): lead-margin histogram against the
    /// 100 ms lead, planner→IO hand-off, planner wake-up lateness, serial round trip.
    Pipeline {
        /// The G-code file (default: the built-in reference print, examples/square.gcode).
        file: Option<PathBuf>,
        /// Klipper-format printer.cfg (default: the built-in simulated printer).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Simulated MCU clocks run N× faster than the wall clock (up to 50; default: the
        /// config's).
        #[arg(long, value_parser = parse_time_scale)]
        time_scale: Option<f64>,
        /// Maximum step time error of the compression, in microseconds.
        #[arg(long, default_value_t = 25.0)]
        max_error_us: f64,
        /// Don't pin threads, use SCHED_FIFO or lock memory.
        #[arg(long)]
        no_realtime: bool,
        #[command(flatten)]
        common: CommonArgs,
    },
    /// Repeated homing on the simulated single-MCU and multi-MCU printers (or --config):
    /// trigger→stop against the 25 ms budget, overshoot, the machine's wake-up beside it.
    Homing {
        /// Which simulated printers: single, multi (Z endstop on a second MCU) or both.
        #[arg(long, default_value = "both", value_parser = ["single", "multi", "both"], conflicts_with = "config")]
        printer: String,
        /// Home this printer.cfg instead of the simulated ones.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Axes to home, as letters (default: xyz; z on the multi-MCU printer).
        #[arg(long)]
        axes: Option<String>,
        /// Homing cycles per printer.
        #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u32).range(1..=100_000))]
        cycles: u32,
        /// Distance (mm) the axes move off their endstops between cycles.
        #[arg(long, default_value_t = 5.0)]
        away: f64,
        /// Simulated MCU clocks run N× faster than the wall clock (up to 50).
        #[arg(long, value_parser = parse_time_scale)]
        time_scale: Option<f64>,
        /// Don't pin threads, use SCHED_FIFO or lock memory.
        #[arg(long)]
        no_realtime: bool,
        #[command(flatten)]
        common: CommonArgs,
    },
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
        /// Also count the instructions of one planning process (all threads) under valgrind's
        /// callgrind (skipped with a note when valgrind is not installed).
        #[arg(long)]
        instructions: bool,
        /// Find every command by the per-step search, none from a cruise line's formula (the
        /// reference the line commands are measured against).
        #[arg(long)]
        per_step: bool,
        /// Commands off the cruise lines as before the per-command design: the search over
        /// adds (24 passes at most) with the latest-end search, curves included (README
        /// "Per-command design"); the options below change it from there.
        #[arg(long, conflicts_with = "per_step")]
        search: bool,
        /// Commands from a constant-acceleration curve take the add of the curve's formula, their
        /// interval and count from at most --curve-passes exact passes.
        #[arg(long, conflicts_with = "per_step")]
        curve_formula: bool,
        /// The search for a command from a curve tries the curve formula's add first.
        #[arg(long, conflicts_with = "per_step")]
        curve_guess: bool,
        /// Among the longest commands, search for the one ending latest (more instructions,
        /// fewer commands).
        #[arg(long, conflicts_with = "per_step")]
        latest_end: bool,
        /// Take the first longest command found, without the search for the one ending latest.
        #[arg(long, conflicts_with_all = ["per_step", "latest_end"])]
        no_latest_end: bool,
        /// Most adds the search for the longest command tries per command (1..=24).
        #[arg(long, conflicts_with = "per_step", value_parser = clap::value_parser!(u32).range(1..=24))]
        max_passes: Option<u32>,
        /// Most passes over the steps per command from a curve's formula (with --curve-formula).
        #[arg(long, conflicts_with = "per_step", value_parser = clap::value_parser!(u32).range(1..=24))]
        curve_passes: Option<u32>,
        /// Steps the compression's lookahead may end a command early when the next command
        /// then covers more (0: plain greedy; default 1).
        #[arg(long, value_parser = clap::value_parser!(u32).range(0..=4))]
        lookahead: Option<u32>,
        /// Data dictionary to encode with (message ids and MCU clock), and to read a stream
        /// given to --compare with: e.g. Klipper's out/klipper.dict (default: the Cadence
        /// firmware's own).
        #[arg(long, value_name = "FILE")]
        dictionary: Option<PathBuf>,
        #[command(flatten)]
        common: CommonArgs,
    },
}

pub fn run(args: &BenchArgs) -> Result<(), BenchCmdError> {
    let mut out = std::io::stdout().lock();
    match &args.what {
        BenchWhat::Wakeup { common, .. } => {
            let mode = wakeup_mode(&args.what)?;
            bench::modes::wakeup::run(&mode, &common_options(common), &mut out)?;
        }
        BenchWhat::Handoff {
            samples,
            gap_us,
            fifo,
            cores,
            no_process,
            common,
        } => {
            let &[producer, consumer] = cores.as_slice() else {
                return Err(BenchCmdError::Cores(cores.clone()));
            };
            let o = HandoffOpts {
                samples: *samples,
                gap: Duration::from_micros(*gap_us),
                fifo: *fifo,
                cores: (producer, consumer),
                ..HandoffOpts::default()
            };
            let exe = std::env::current_exe().map_err(BenchCmdError::Executable)?;
            let child = ChildCommand {
                exe,
                args: vec!["bench".into(), "handoff-child".into()],
            };
            let child = (!no_process).then_some(&child);
            bench::modes::handoff::run(&o, child, &common_options(common), &mut out)?;
        }
        BenchWhat::HandoffChild {
            service,
            samples,
            mode,
            core,
        } => {
            let poll = match mode.as_str() {
                "poll" => true,
                "event" => false,
                other => return Err(BenchCmdError::ChildMode(other.to_string())),
            };
            let line =
                bench::handoff::child_main(service, *samples, poll, *core).map_err(BenchCmdError::Harness)?;
            println!("{line}");
        }
        BenchWhat::Pipeline { common, .. } => {
            pipeline::run(&pipeline_mode(&args.what)?, &common_options(common), &mut out)?;
        }
        BenchWhat::Homing { common, .. } => {
            homing::run(&homing_mode(&args.what)?, &common_options(common), &mut out)?;
        }
        BenchWhat::Plan {
            file,
            config,
            threads,
            max_error_us,
            clock_freq,
            runs,
            instructions,
            per_step,
            search,
            curve_formula,
            curve_guess,
            latest_end,
            no_latest_end,
            max_passes,
            curve_passes,
            lookahead,
            dictionary,
            common,
        } => {
            let cfg = crate::machine::load_config(config.as_deref())?;
            let dict = crate::decode::load_dictionary(dictionary.as_deref())?;
            let cores = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
            let opts = bench::plan::PlanOptions {
                threads: threads.unwrap_or(cores),
                max_error_s: max_error_us * 1e-6,
                per_step: *per_step,
                tuning: tuning_of(
                    *search,
                    *curve_formula,
                    *curve_guess,
                    (*latest_end, *no_latest_end),
                    *max_passes,
                    *curve_passes,
                ),
                lookahead: lookahead.map(|n| n as usize),
                ..Default::default()
            }
            .with_dictionary(&dict)
            .map_err(BenchCmdError::Harness)?;
            let opts = bench::plan::PlanOptions {
                clock_freq: clock_freq.unwrap_or(opts.clock_freq),
                ..opts
            };
            let counted = if *instructions {
                Some(plan_child(file, config.as_deref(), dictionary.as_deref(), &opts)?)
            } else {
                None
            };
            // `--compare` takes a saved report, or another host's wire stream of the file.
            let mut common = common_options(common);
            let stream = match &common.compare {
                Some(path) if is_wire_stream(path) => common.compare.take(),
                _ => None,
            };
            let steppers = match &stream {
                Some(_) => stream_steppers(&cfg, &dict)?,
                None => Vec::new(),
            };
            let extras = bench::modes::plan::Extras {
                instructions: counted.as_ref(),
                against: stream.as_deref().map(|path| bench::modes::plan::Against {
                    path,
                    dict: &dict,
                    steppers: &steppers,
                }),
            };
            bench::modes::plan::run(file, &cfg, &opts, *runs, &extras, &common, &mut out)?;
        }
    }
    Ok(())
}

/// Whether `path` holds a wire stream (a batch file: blocks of at least 5 bytes, each ending
/// in the sync byte) rather than a JSON report (`{` first); unreadable files are left to the
/// report reader, which names the error.
fn is_wire_stream(path: &std::path::Path) -> bool {
    use std::io::Read;
    let mut head = [0u8; 1];
    let read = std::fs::File::open(path).and_then(|mut f| f.read(&mut head));
    matches!(read, Ok(1))
        && (links::proto::MESSAGE_MIN..=links::proto::MESSAGE_MAX).contains(&usize::from(head[0]))
}

/// The printer's steppers in the planner's order, each with its step pin in `dict` when it is
/// on the main MCU (a batch stream is one MCU's: Klipper's `-o` writes the main one's).
fn stream_steppers(
    cfg: &sysconfig::printer::PrinterConfig,
    dict: &links::dict::Dictionary,
) -> Result<Vec<(String, Option<u32>)>, BenchCmdError> {
    let machine = cadence::hardware::Machine::from_config(cfg)?;
    Ok(machine
        .steppers
        .iter()
        .map(|s| {
            let pin = (s.mcu == "mcu").then(|| dict.pin(&s.step_pin.pin).ok()).flatten();
            (s.name.clone(), pin)
        })
        .collect())
}

/// `cadence bench plan` of the same file with the same options, planned once: the process
/// whose instructions `--instructions` counts.
fn plan_child(
    file: &std::path::Path,
    config: Option<&std::path::Path>,
    dictionary: Option<&std::path::Path>,
    opts: &bench::plan::PlanOptions,
) -> Result<ChildCommand, BenchCmdError> {
    let exe = std::env::current_exe().map_err(BenchCmdError::Executable)?;
    let mut args: Vec<String> = vec!["bench".into(), "plan".into(), file.display().to_string()];
    if let Some(c) = config {
        args.extend(["--config".into(), c.display().to_string()]);
    }
    if let Some(d) = dictionary {
        args.extend(["--dictionary".into(), d.display().to_string()]);
    }
    args.extend([
        "--threads".into(),
        opts.threads.to_string(),
        "--max-error-us".into(),
        (opts.max_error_s * 1e6).to_string(),
        "--clock-freq".into(),
        opts.clock_freq.to_string(),
        "--no-progress".into(),
    ]);
    if opts.per_step {
        args.push("--per-step".into());
    }
    if let Some(n) = opts.lookahead {
        args.extend(["--lookahead".into(), n.to_string()]);
    }
    if !opts.per_step {
        let t = opts.tuning;
        for (on, flag) in [
            (t.curve_commands, "--curve-formula"),
            (t.curve_guess, "--curve-guess"),
            (t.latest_end, "--latest-end"),
            (!t.latest_end, "--no-latest-end"),
        ] {
            if on {
                args.push(flag.into());
            }
        }
        args.extend([
            "--max-passes".into(),
            t.max_passes.to_string(),
            "--curve-passes".into(),
            t.curve_passes.to_string(),
        ]);
    }
    Ok(ChildCommand { exe, args })
}

/// The compression's tuning from `bench plan`'s options: the default or, with `search`, the
/// search before the per-command design, then each option given.
fn tuning_of(
    search: bool,
    curve_formula: bool,
    curve_guess: bool,
    (latest_end, no_latest_end): (bool, bool),
    max_passes: Option<u32>,
    curve_passes: Option<u32>,
) -> planner::compress::SearchTuning {
    use planner::compress::SearchTuning;
    let mut t = if search {
        SearchTuning::SEARCH
    } else {
        SearchTuning::default()
    };
    t.curve_commands |= curve_formula;
    t.curve_guess |= curve_guess;
    if latest_end || no_latest_end {
        t.latest_end = latest_end;
    }
    if let Some(n) = max_passes {
        t.max_passes = n as usize;
    }
    if let Some(n) = curve_passes {
        t.curve_passes = n as usize;
    }
    t
}

/// The library's common options.
fn common_options(a: &CommonArgs) -> Common {
    Common {
        json: a.json,
        hlog: a.hlog.clone(),
        plot: a.plot.clone(),
        load: a.load,
        load_tool: a.load_tool,
        budget_ns: a.budget_us.map(|us| (us * 1e3).round() as u64),
        progress: !a.no_progress,
        compare: a.compare.clone(),
    }
}

/// The pipeline mode of `bench pipeline` arguments.
fn pipeline_mode(what: &BenchWhat) -> Result<pipeline::PipelineMode, BenchCmdError> {
    let BenchWhat::Pipeline {
        file,
        config,
        time_scale,
        max_error_us,
        no_realtime,
        ..
    } = what
    else {
        return Err(BenchCmdError::NotMode("pipeline"));
    };
    if !(*max_error_us > 0.0 && *max_error_us <= 1000.0) {
        return Err(BenchCmdError::MaxError(*max_error_us));
    }
    Ok(pipeline::PipelineMode {
        file: file.clone(),
        config: config.clone(),
        time_scale: *time_scale,
        max_error_us: *max_error_us,
        realtime: !no_realtime,
    })
}

/// The homing mode of `bench homing` arguments.
fn homing_mode(what: &BenchWhat) -> Result<homing::HomingMode, BenchCmdError> {
    let BenchWhat::Homing {
        printer,
        config,
        axes,
        cycles,
        away,
        time_scale,
        no_realtime,
        ..
    } = what
    else {
        return Err(BenchCmdError::NotMode("homing"));
    };
    let printers = match (config, printer.as_str()) {
        (Some(c), _) => homing::Printers::Config(c.clone()),
        (None, "single") => homing::Printers::Single,
        (None, "multi") => homing::Printers::Multi,
        _ => homing::Printers::Both,
    };
    let axes = match axes {
        None => None,
        Some(text) => {
            let mut a = [false; 3];
            for c in text.chars() {
                match cadence::homing::AXIS_NAMES
                    .iter()
                    .position(|&n| n == c.to_ascii_lowercase())
                {
                    Some(i) => a[i] = true,
                    None => {
                        return Err(BenchCmdError::Axis {
                            text: text.clone(),
                            letter: c,
                        })
                    }
                }
            }
            if a == [false; 3] {
                return Err(BenchCmdError::NoAxes);
            }
            Some(a)
        }
    };
    if !(away.is_finite() && *away > 0.0) {
        return Err(BenchCmdError::Away(*away));
    }
    Ok(homing::HomingMode {
        printers,
        axes,
        cycles: *cycles,
        away: *away,
        time_scale: *time_scale,
        realtime: !no_realtime,
    })
}

/// The wakeup mode of `bench wakeup` arguments.
fn wakeup_mode(what: &BenchWhat) -> Result<WakeupMode, BenchCmdError> {
    let BenchWhat::Wakeup {
        cpus,
        priority,
        interval_us,
        duration,
        loops,
        busy_wait,
        no_mlock,
        compare_cyclictest,
        slice_s,
        ..
    } = what
    else {
        return Err(BenchCmdError::NotMode("wakeup"));
    };
    let online = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    let cpus = if cpus.is_empty() {
        (0..online).collect()
    } else {
        cpus.clone()
    };
    if let Some((_, c)) = cpus.iter().enumerate().find(|(i, c)| cpus[..*i].contains(c)) {
        return Err(BenchCmdError::CpuTwice(*c));
    }
    if let Some(&cpu) = cpus.iter().find(|&&c| c >= online) {
        return Err(BenchCmdError::NoSuchCpu {
            cpu,
            last: online - 1,
        });
    }
    Ok(WakeupMode {
        measure: WakeupOptions {
            cpus,
            priority: (*priority > 0).then_some(*priority),
            interval: Duration::from_micros(*interval_us),
            stop: loops.map_or(Stop::Duration(*duration), Stop::Loops),
            wait: if *busy_wait { Wait::Busy } else { Wait::Sleep },
            log_interval: Duration::from_secs(1),
        },
        lock_memory: !no_mlock,
        compare_cyclictest: *compare_cyclictest,
        slice: Duration::from_secs(*slice_s),
    })
}

/// `10`, `10s`, `500ms`, `2m`, `1h`: a positive duration.
fn parse_duration(s: &str) -> Result<Duration, ArgError> {
    let bad = || ArgError::Duration(s.to_string());
    let (num, unit) = match s.find(|c: char| !c.is_ascii_digit() && c != '.') {
        Some(i) => s.split_at(i),
        None => (s, "s"),
    };
    let v: f64 = num.parse().map_err(|_| bad())?;
    let secs = match unit {
        "ms" => v / 1e3,
        "s" => v,
        "m" => v * 60.0,
        "h" => v * 3600.0,
        _ => return Err(bad()),
    };
    if !(secs.is_finite() && secs > 0.0 && secs <= 7.0 * 86400.0) {
        return Err(ArgError::DurationRange(s.to_string()));
    }
    Ok(Duration::from_secs_f64(secs))
}

/// A budget in µs, 0 or more.
fn parse_budget(s: &str) -> Result<f64, ArgError> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(ArgError::Budget(s.to_string())),
    }
}

/// A simulated time scale in (0, 50].
fn parse_time_scale(s: &str) -> Result<f64, ArgError> {
    match s.parse::<f64>() {
        Ok(v) if v > 0.0 && v <= 50.0 => Ok(v),
        _ => Err(ArgError::TimeScale(s.to_string())),
    }
}

/// A clock frequency between 1 MHz and 1 GHz.
fn parse_clock_freq(s: &str) -> Result<f64, ArgError> {
    match s.parse::<f64>() {
        Ok(f) if (1e6..=1e9).contains(&f) => Ok(f),
        _ => Err(ArgError::ClockFreq(s.to_string())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct Cli {
        #[command(subcommand)]
        what: BenchWhat,
    }

    fn parse(args: &[&str]) -> Result<BenchWhat, clap::Error> {
        Cli::try_parse_from(std::iter::once("bench").chain(args.iter().copied())).map(|c| c.what)
    }

    #[test]
    fn wakeup_options_parse_into_the_mode() {
        let w = parse(&[
            "wakeup",
            "--cpus",
            "0",
            "--priority",
            "90",
            "--interval-us",
            "250",
            "--duration",
            "3s",
            "--compare-cyclictest",
            "--slice-s",
            "1",
            "--json",
            "--hlog",
            "x.hlog",
            "--plot",
            "x.svg",
            "--load",
            "cpu",
            "--budget-us",
            "1000",
        ])
        .unwrap();
        let mode = wakeup_mode(&w).unwrap();
        assert_eq!(mode.measure.cpus, vec![0]);
        assert_eq!(mode.measure.priority, Some(90));
        assert_eq!(mode.measure.interval, Duration::from_micros(250));
        assert_eq!(mode.measure.stop, Stop::Duration(Duration::from_secs(3)));
        assert!(mode.compare_cyclictest && mode.lock_memory);
        let BenchWhat::Wakeup { common, .. } = &w else {
            unreachable!()
        };
        let c = common_options(common);
        assert!(c.json && c.progress);
        assert_eq!(c.load, Some(LoadKind::Cpu));
        assert_eq!(c.budget_ns, Some(1_000_000));
        assert_eq!(c.plot, Some(PathBuf::from("x.svg")));

        let w = parse(&[
            "wakeup",
            "--loops",
            "100",
            "--busy-wait",
            "--priority",
            "0",
            "--no-mlock",
        ])
        .unwrap();
        let mode = wakeup_mode(&w).unwrap();
        assert_eq!(
            (mode.measure.stop, mode.measure.wait),
            (Stop::Loops(100), Wait::Busy)
        );
        assert_eq!(mode.measure.priority, None);
        assert!(!mode.lock_memory);
        assert!(!mode.measure.cpus.is_empty());
    }

    #[test]
    fn bad_options_are_clear_errors() {
        for (args, want) in [
            (&["wakeup", "--priority", "100"][..], "100"),
            (&["wakeup", "--interval-us", "10"], "10"),
            (&["wakeup", "--duration", "0"], "more than 0"),
            (&["wakeup", "--duration", "5parsecs"], "expected e.g."),
            (
                &["wakeup", "--loops", "5", "--duration", "1s"],
                "cannot be used with",
            ),
            (&["wakeup", "--load", "gpu"], "expected cpu, io or mem"),
            (&["wakeup", "--load-tool", "x"], "auto, stress-ng or builtin"),
            (&["wakeup", "--budget-us=-1"], "0 or more"),
            (&["handoff", "--fifo", "0"], "0"),
            (&["plan"], "FILE"),
        ] {
            let e = parse(args).unwrap_err().to_string();
            assert!(e.contains(want), "{args:?}: {e}");
        }
        let w = parse(&["wakeup", "--cpus", "4096"]).unwrap();
        let e = wakeup_mode(&w).unwrap_err();
        assert!(matches!(e, BenchCmdError::NoSuchCpu { cpu: 4096, .. }), "{e:?}");
        assert!(e.to_string().contains("CPU 4096 does not exist"));
        let w = parse(&["wakeup", "--cpus", "0,0"]).unwrap();
        assert!(wakeup_mode(&w)
            .unwrap_err()
            .to_string()
            .contains("CPU 0 is given twice"));
    }

    #[test]
    fn pipeline_and_homing_options_parse_into_their_modes() {
        let p = parse(&[
            "pipeline",
            "print.gcode",
            "--config",
            "printer.cfg",
            "--time-scale",
            "5",
            "--no-realtime",
            "--json",
            "--plot",
            "p.png",
        ])
        .unwrap();
        let m = pipeline_mode(&p).unwrap();
        assert_eq!(m.file, Some(PathBuf::from("print.gcode")));
        assert_eq!(m.config, Some(PathBuf::from("printer.cfg")));
        assert_eq!(
            (m.time_scale, m.max_error_us, m.realtime),
            (Some(5.0), 25.0, false)
        );
        let m = pipeline_mode(&parse(&["pipeline"]).unwrap()).unwrap();
        assert_eq!((m.file, m.config, m.time_scale), (None, None, None));
        assert!(m.realtime);

        let h = parse(&[
            "homing",
            "--printer",
            "multi",
            "--axes",
            "Zx",
            "--cycles",
            "3",
            "--away",
            "2",
        ])
        .unwrap();
        let m = homing_mode(&h).unwrap();
        assert_eq!(m.printers, homing::Printers::Multi);
        assert_eq!(m.axes, Some([true, false, true]));
        assert_eq!((m.cycles, m.away), (3, 2.0));
        let m = homing_mode(&parse(&["homing", "--config", "a.cfg", "--load", "io"]).unwrap()).unwrap();
        assert_eq!(m.printers, homing::Printers::Config(PathBuf::from("a.cfg")));
        assert_eq!((m.axes, m.cycles), (None, 10));
        let m = homing_mode(&parse(&["homing"]).unwrap()).unwrap();
        assert_eq!(m.printers, homing::Printers::Both);
    }

    #[test]
    fn bad_pipeline_and_homing_options_are_clear_errors() {
        for (args, want) in [
            (&["pipeline", "--time-scale", "0"][..], "at most 50"),
            (&["pipeline", "--time-scale", "51"], "at most 50"),
            (&["homing", "--printer", "three"], "three"),
            (&["homing", "--cycles", "0"], "0"),
            (
                &["homing", "--printer", "multi", "--config", "x.cfg"],
                "cannot be used with",
            ),
        ] {
            let e = parse(args).unwrap_err().to_string();
            assert!(e.contains(want), "{args:?}: {e}");
        }
        let e = homing_mode(&parse(&["homing", "--axes", "xw"]).unwrap()).unwrap_err();
        assert!(matches!(e, BenchCmdError::Axis { letter: 'w', .. }), "{e:?}");
        assert!(e.to_string().contains("'w' is not x, y or z"), "{e}");
        let e = homing_mode(&parse(&["homing", "--away", "0"]).unwrap()).unwrap_err();
        assert!(e.to_string().contains("more than 0"), "{e}");
        let e = pipeline_mode(&parse(&["pipeline", "--max-error-us", "0"]).unwrap()).unwrap_err();
        assert!(e.to_string().contains("(0, 1000]"), "{e}");
    }

    #[test]
    fn durations_parse() {
        assert_eq!(parse_duration("10"), Ok(Duration::from_secs(10)));
        assert_eq!(parse_duration("500ms"), Ok(Duration::from_millis(500)));
        assert_eq!(parse_duration("2m"), Ok(Duration::from_secs(120)));
        assert_eq!(parse_duration("1.5s"), Ok(Duration::from_millis(1500)));
        assert!(parse_duration("").is_err());
        assert!(parse_duration("-1s").is_err());
    }

    #[test]
    fn clock_freq_is_checked() {
        assert_eq!(parse_clock_freq("16000000"), Ok(16e6));
        assert!(parse_clock_freq("10")
            .unwrap_err()
            .to_string()
            .contains("expected Hz"));
        assert!(parse_clock_freq("fast").is_err());
    }
}
