//! A print job as the `print` command runs it: the G-code file, the printer.cfg (or the
//! built-in simulated printer) and the options; batch mode to wire files, a live print with the
//! IO stage in this process, or with it in a `cadence serve --role io` process.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

use rt_core::logger::Level;
use sysconfig::printer::PrinterConfig;

use crate::batch::{run_batch, BatchJob, BatchReport};
use crate::events::SessionShared;
use crate::gcode_feed::GcodeInput;
use crate::hardware::Machine;
use crate::latency::Hists;
use crate::live;
use crate::logging::Logging;
use crate::mcus::Mcus;
use crate::realtime::RtConfig;
use crate::summary::Summary;

/// Everything a print needs besides the printer.cfg's contents.
#[derive(Debug, Clone)]
pub struct PrintJob {
    /// The G-code file to print.
    pub file: PathBuf,
    /// Klipper-format printer.cfg (`None`: the built-in simulated cartesian printer).
    pub config: Option<PathBuf>,
    /// Simulated MCU clock runs this many times faster than the wall clock (`None`: the
    /// config's [simulator] time_scale, else 1).
    pub time_scale: Option<f64>,
    /// No MCU and no real-time waiting: write the exact wire stream to this file.
    pub batch: Option<PathBuf>,
    /// Data dictionary for `batch` (`None`: the Cadence firmware's own).
    pub dictionary: Option<PathBuf>,
    /// Write the simulated MCU's step trace to this file.
    pub trace: Option<PathBuf>,
    /// Maximum step time error of the compression, in microseconds.
    pub max_error_us: f64,
    /// Don't pin threads, use SCHED_FIFO or lock memory.
    pub no_realtime: bool,
    /// Save the print's latency histograms to this file (HdrHistogram V2 interval log).
    pub histograms: Option<PathBuf>,
    /// An unknown G-code command stops the print (as `[gcode] unknown_commands: error`);
    /// otherwise the config decides (by default it is reported and skipped, as Klipper does).
    pub strict: bool,
    /// Logging and where the IO stage runs.
    pub live: LiveOptions,
}

/// Options of a live print beyond the G-code and the printer.
#[derive(Debug, Clone)]
pub struct LiveOptions {
    /// Also write the print's log (records of the planner, IO stage and link threads) to this
    /// file (appended).
    pub log_file: Option<PathBuf>,
    /// Most verbose log level recorded: error, warn, info, debug or trace.
    pub log_level: Level,
    /// Run the IO stage (the MCU connections) in a separate `cadence serve --role io` process
    /// started for this print. G28 with endstops is refused in this mode.
    pub io_process: bool,
    /// Like --io-process, but attach to a running `cadence serve --role io --instance NAME`.
    pub io_attach: Option<String>,
    /// Once set (by a Ctrl-C, say), a wait in progress (M109/M190/TEMPERATURE_WAIT) ends at
    /// once and the print goes on with what its G-code source still gives.
    pub interrupt: Option<Arc<AtomicBool>>,
}

impl LiveOptions {
    /// True when the IO stage runs in another process.
    pub fn remote(&self) -> bool {
        self.io_process || self.io_attach.is_some()
    }
}

/// What a finished print reports.
#[derive(Debug)]
pub enum PrintOutcome {
    /// `batch` was set: the wire files and figures.
    Batch(BatchReport),
    /// A live print on the MCUs.
    Live(LiveOutcome),
}

/// What a live print reports: its summary, each MCU link's statistics (empty when the IO stage
/// ran in another process, which reports them itself) and which real-time guarantees were off.
#[derive(Debug)]
pub struct LiveOutcome {
    pub summary: Summary,
    pub link_stats: Vec<(String, links::mcu::LinkStats)>,
    pub rt_report: Vec<String>,
}

/// A live print's state as a progress display shows it (taken about 4 times a second).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Progress {
    /// Print time the MCUs executed since the print started (s; 0 until motion starts).
    pub print_time: f64,
    /// Print time planned so far (s since the print's start).
    pub planned: f64,
    /// Planned toolhead position (X, Y, Z, E; mm).
    pub position: [f64; 4],
    /// Smallest lead of a step message when its bytes left, over every MCU so far (ms);
    /// `None` before the first.
    pub min_lead_ms: Option<f64>,
    /// Each MCU's name and, once it shut down or its link failed, why.
    pub mcus: Vec<(String, Option<String>)>,
    /// The simulated clocks' speed-up (1 on real hardware).
    pub time_scale: f64,
}

/// Called with a fresh [`Progress`] about every 250 ms while a live print runs.
pub type ProgressObserver<'a> = &'a (dyn Fn(&Progress) + Sync);

/// How often the observer is called.
const PROGRESS_PERIOD: std::time::Duration = std::time::Duration::from_millis(250);

/// Most time scale the simulator's 32-bit clock allows (it wraps every 86 s / scale at 50 MHz).
const MAX_TIME_SCALE: f64 = 50.0;

/// Why a print job failed.
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    /// `--max-error-us` out of range.
    #[error("--max-error-us {0}: must be in (0, 1000]")]
    MaxError(f64),
    /// `--time-scale` out of range.
    #[error("--time-scale {scale}: must be in (0, {max}]")]
    TimeScale { scale: f64, max: f64 },
    /// `--time-scale` given for real MCUs.
    #[error("--time-scale only applies to a simulated printer")]
    TimeScaleNotSimulated,
    /// The G-code file could not be opened.
    #[error("{}: {source}", .path.display())]
    Open {
        path: std::path::PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// printer.cfg could not be read or describes no printer Cadence can drive.
    #[error(transparent)]
    Config(#[from] crate::hardware::HardwareError),
    /// The batch print failed.
    #[error(transparent)]
    Batch(Box<crate::batch::BatchError>),
    /// The print with the IO stage in another process failed.
    #[error(transparent)]
    IoProcess(Box<crate::io_process::IoProcessError>),
    /// The logger thread did not start.
    #[error(transparent)]
    Logger(#[from] rt_core::logger::LoggerError),
    /// An MCU did not start, connect or configure.
    #[error(transparent)]
    Mcu(#[from] crate::mcus::McuError),
    /// The live print failed.
    #[error(transparent)]
    Live(Box<crate::live::LiveError>),
    /// The histograms file.
    #[error(transparent)]
    Histograms(#[from] crate::latency::HistogramsError),
}

from_boxed!(JobError, Batch, crate::batch::BatchError);
from_boxed!(JobError, IoProcess, crate::io_process::IoProcessError);
from_boxed!(JobError, Live, crate::live::LiveError);

/// The CLI's view (the message as shown).
impl From<JobError> for String {
    fn from(e: JobError) -> String {
        e.to_string()
    }
}

/// Runs a print job; `warn` gets the printer.cfg's warnings.
pub fn run(args: &PrintJob, warn: &mut dyn FnMut(&str)) -> Result<PrintOutcome, JobError> {
    run_with(args, None, warn, None)
}

/// [`run`] with the G-code from `gcode` (named as the file; `None`: the job's file opened
/// here) and an observer of the live print's progress (not called in batch mode or with the
/// IO stage in another process).
pub fn run_with(
    args: &PrintJob,
    gcode: Option<GcodeInput>,
    warn: &mut dyn FnMut(&str),
    observer: Option<ProgressObserver<'_>>,
) -> Result<PrintOutcome, JobError> {
    if !(args.max_error_us > 0.0 && args.max_error_us <= 1000.0) {
        return Err(JobError::MaxError(args.max_error_us));
    }
    if let Some(scale) = args.time_scale {
        if !(scale > 0.0 && scale <= MAX_TIME_SCALE) {
            return Err(JobError::TimeScale {
                scale,
                max: MAX_TIME_SCALE,
            });
        }
    }
    // Open the G-code first: a missing file must not start any MCU.
    let gcode = match gcode {
        Some(g) => g,
        None => GcodeInput::open(&args.file).map_err(|source| JobError::Open {
            path: args.file.clone(),
            source,
        })?,
    };
    let mut cfg = crate::hardware::load_config(args.config.as_deref())?;
    // The run's time scale is the simulated printer's (heater safety windows follow it).
    if let Some(scale) = args.time_scale {
        cfg.simulator.time_scale = scale;
    }
    if args.strict {
        cfg.gcode.unknown_commands = sysconfig::printer::UnknownCommands::Error;
    }
    for w in &cfg.warnings {
        warn(w);
    }
    let machine = Machine::from_config(&cfg)?;
    match &args.batch {
        Some(out) => {
            let job = BatchJob {
                out,
                dictionary: args.dictionary.as_deref(),
                max_error_us: args.max_error_us,
            };
            Ok(run_batch(&job, &cfg, &machine, gcode).map(PrintOutcome::Batch)?)
        }
        None => run_live(args, &cfg, &machine, gcode, observer).map(PrintOutcome::Live),
    }
}

fn run_live(
    args: &PrintJob,
    cfg: &PrinterConfig,
    machine: &Machine,
    gcode: GcodeInput,
    observer: Option<ProgressObserver<'_>>,
) -> Result<LiveOutcome, JobError> {
    if args.live.remote() {
        return Ok(crate::io_process::planner_side::run(args, cfg, machine, gcode)?);
    }
    let started = Instant::now();
    let simulated = cfg.mcus.iter().any(|m| m.is_simulated());
    if args.time_scale.is_some() && !simulated {
        return Err(JobError::TimeScaleNotSimulated);
    }
    let time_scale = args.time_scale.unwrap_or(cfg.simulator.time_scale);
    let logging = Logging::start(args.live.log_level, args.live.log_file.clone())?;
    let rt = RtConfig::from_section(&cfg.realtime, args.no_realtime);
    let _idle_hold = rt.hold_idle_latency();
    let (hists, mut mcus) = live::connect_mcus(cfg, machine, time_scale, args.trace.clone(), &rt, &logging)?;
    let log = logging.handle("main");
    let shared = SessionShared::new(None).with_interrupt(args.live.interrupt.clone());
    let run = live::LiveRun {
        max_error_s: args.max_error_us * 1e-6,
        started,
        scale: time_scale,
        rt: &rt,
        hists: &hists,
        log: &log,
        session: Some(&shared),
        instance: &format!("p{}", std::process::id()),
    };
    let result = match observer {
        None => live::print_on(gcode, machine, &mcus, &run),
        Some(observe) => {
            let done = AtomicBool::new(false);
            std::thread::scope(|scope| {
                let watch = Watch {
                    mcus: &mcus,
                    shared: &shared,
                    time_scale,
                    start: print_now(&mcus) + (0.5f64).max(0.25 * time_scale),
                };
                let done = &done;
                let watcher = std::thread::Builder::new()
                    .name("progress".to_string())
                    .spawn_scoped(scope, move || {
                        while !done.load(Ordering::Acquire) {
                            observe(&watch.progress());
                            std::thread::sleep(PROGRESS_PERIOD);
                        }
                    });
                let r = live::print_on(gcode, machine, &mcus, &run);
                done.store(true, Ordering::Release);
                if let Ok(w) = watcher {
                    let _ = w.join();
                }
                r
            })
        }
    };
    let stats = mcus.close();
    Ok(live_outcome(
        result?,
        started,
        args.histograms.as_deref(),
        &hists,
        logging,
        stats,
    )?)
}

/// What the progress thread reads.
struct Watch<'a> {
    mcus: &'a Mcus,
    shared: &'a SessionShared,
    time_scale: f64,
    /// The print's start in print time (as the planner picks it: a little ahead of now).
    start: f64,
}

impl Watch<'_> {
    fn progress(&self) -> Progress {
        let motion = self.shared.motion();
        let mut min_lead_ms: Option<f64> = None;
        let mut mcus = Vec::with_capacity(self.mcus.list.len());
        for m in &self.mcus.list {
            let stats = m.link.stats();
            if let Some(t) = stats.min_lead_margin_ticks {
                let ms = t as f64 / m.clock_freq * 1e3;
                min_lead_ms = Some(min_lead_ms.map_or(ms, |v| v.min(ms)));
            }
            let down = m
                .link
                .shutdown_reason()
                .or_else(|| m.link.error().map(|e| e.to_string()));
            mcus.push((m.name.clone(), down));
        }
        let planned = if motion.planned_until > self.start {
            motion.planned_until - self.start
        } else {
            0.0
        };
        Progress {
            print_time: (print_now(self.mcus) - self.start).clamp(0.0, planned),
            planned,
            position: motion.position,
            min_lead_ms,
            mcus,
            time_scale: self.time_scale,
        }
    }
}

/// The main MCU's print time now.
fn print_now(mcus: &Mcus) -> f64 {
    let main = mcus.main();
    main.link.clock().clock_at(links::mcu::McuLink::system_now()) / main.clock_freq
}

/// The end of a live print: wall time, the histograms saved if asked, the logger's line.
pub(crate) fn live_outcome(
    mut summary: Summary,
    started: Instant,
    histograms: Option<&std::path::Path>,
    hists: &Hists,
    logging: Logging,
    link_stats: Vec<(String, links::mcu::LinkStats)>,
) -> Result<LiveOutcome, crate::latency::HistogramsError> {
    summary.wall = started.elapsed().as_secs_f64();
    if let Some(path) = histograms {
        hists.save(path, summary.wall)?;
    }
    summary.extra.push(logging.finish());
    Ok(LiveOutcome {
        summary,
        link_stats,
        rt_report: rt_core::os::rt_report(),
    })
}
