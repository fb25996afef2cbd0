//! The running printer behind one API: [`Printer::open`] loads a printer.cfg (or the built-in
//! simulated printer), connects and configures its MCUs and starts the live pipeline (planner
//! thread, one IO stage per MCU with steppers, telemetry), which then waits for G-code: a file
//! ([`Printer::run_gcode_file`]), any reader ([`Printer::run_gcode_stream`]) or one command at
//! a time ([`Printer::send_line`]), all planned in order on one timeline. When no G-code comes
//! for [`PrinterOptions::idle_flush`] the lookahead is flushed so everything sent moves, and the
//! next command starts from the MCUs' time then.
//!
//! What comes back: typed [`Event`]s ([`Printer::events`]), a [`Status`] snapshot, the latency
//! histograms ([`Printer::latency`]) and, from [`Printer::close`], the summary with each
//! stepper's position read back from its MCU. [`PrinterHandle`] (cloneable, `Send`) stops the
//! printer or stops it in an emergency from any thread.
//!
//! A G-code line that does not parse is refused by `send_line` and the session goes on; a
//! command given to [`Printer::run_command`] that the planner refuses fails alone (the printer
//! stays ready, as a service needs); through `send_line` or a file, a command the planner
//! refuses (an unknown command, a move out of range), an MCU shutdown or a stop ends the session: the printer is then [`PrinterState::Shutdown`] with the reason, and
//! every later call returns [`PrinterError::Shutdown`].

use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{self, Receiver, SyncSender};
use std::sync::{Arc, Weak};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use links::mcu::McuLink;
use planner::gcode::{parse_line, GcodeError};
use rt_core::hist::Summary as HistSummary;
use rt_core::logger::{Level, LoggerHandle};
use sysconfig::printer::PrinterConfig;

use crate::events::{Event, PrinterState, SessionShared, Status};
use crate::gcode_feed::{FeedMsg, GcodeInput};
use crate::hardware::{HardwareError, Machine};
use crate::homing::HomingReport;
use crate::latency::Hists;
use crate::live::{self, LiveRun};
use crate::logging::Logging;
use crate::mcus::{McuError, Mcus};
use crate::realtime::RtConfig;
use crate::summary::Summary;

/// Which printer to open.
#[derive(Debug, Clone)]
pub enum PrinterSource {
    /// The built-in simulated cartesian printer (`examples/simulated-cartesian.cfg`): its MCU
    /// is the firmware's Linux-process target, started as a child process on a pty.
    Simulated,
    /// A Klipper-format printer.cfg on disk.
    ConfigFile(PathBuf),
    /// A printer.cfg already loaded.
    Config(Box<PrinterConfig>),
}

/// How to run the printer.
#[derive(Debug, Clone)]
pub struct PrinterOptions {
    /// Simulated MCU clocks run this many times faster than the wall clock (`None`: the
    /// config's `[simulator] time_scale`); only for simulated printers, at most 50.
    pub time_scale: Option<f64>,
    /// Step trace of the simulated MCU(s).
    pub trace: Option<PathBuf>,
    /// Maximum step time error of the compression (µs).
    pub max_error_us: f64,
    /// Apply printer.cfg's `[realtime]` (pinning, SCHED_FIFO, locked memory where allowed).
    pub realtime: bool,
    /// Most verbose log level recorded.
    pub log_level: Level,
    /// Also write the log to this file.
    pub log_file: Option<PathBuf>,
    /// Write the log to stderr too.
    pub log_to_stderr: bool,
    /// After this long without G-code the lookahead is flushed (what was sent moves).
    pub idle_flush: Duration,
}

impl Default for PrinterOptions {
    fn default() -> Self {
        PrinterOptions {
            time_scale: None,
            trace: None,
            max_error_us: 25.0,
            realtime: true,
            log_level: Level::Warn,
            log_file: None,
            log_to_stderr: true,
            idle_flush: Duration::from_millis(200),
        }
    }
}

/// Why a printer could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    /// printer.cfg could not be read, is invalid or describes no printer Cadence can drive
    /// (the message names file, line, section and option).
    #[error("printer config: {0}")]
    Config(#[from] HardwareError),
    /// A bad option.
    #[error("{what}: {value}: {why}")]
    Option {
        what: &'static str,
        value: f64,
        why: &'static str,
    },
    /// An MCU did not start, connect, identify or configure ([`McuError::mcu`] names it).
    #[error("connecting the MCUs: {0}")]
    Connect(#[from] McuError),
    /// A thread (logger, session) could not start.
    #[error("cannot start the {what}: {why}")]
    Thread { what: &'static str, why: String },
}

/// Why a call on an open printer failed.
#[derive(Debug, thiserror::Error)]
pub enum PrinterError {
    /// A G-code file or stream could not be read.
    #[error("{path}: {source}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A line given to `send_line` does not parse (the session goes on).
    #[error("G-code: {0}")]
    Gcode(#[from] GcodeError),
    /// A command given to [`Printer::run_command`] was refused (unknown, out of range, a macro
    /// error); the printer stays ready.
    #[error("{message}")]
    Command { message: String },
    /// The session ended: a G-code error, an MCU shutdown, a stop or `close`.
    #[error("the printer shut down: {reason}")]
    Shutdown { reason: String },
    /// The MCUs did not reach the end of the planned moves in time.
    #[error("timed out after {seconds:.1} s waiting for {what}")]
    Timeout { what: &'static str, seconds: f64 },
}

/// Why closing failed: the session's own error, or a check at the end (a position the MCU
/// reports differently from the host's, a step command that reached its MCU late).
#[derive(Debug, thiserror::Error)]
#[error("{reason}")]
pub struct CloseError {
    pub reason: String,
    /// The MCU links' statistics, gathered anyway.
    pub link_stats: Vec<(String, links::mcu::LinkStats)>,
}

/// The latency histograms of the session so far.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Latency {
    /// Lead margin of every step message when its bytes left, in ticks of the main MCU's
    /// clock (`clock_freq`): must stay above 100 ms.
    pub lead_margin: HistSummary,
    /// Planner → IO stage hand-off (ns).
    pub handoff: HistSummary,
    /// Planner thread wake-up lateness after a flow-control sleep (ns).
    pub wake_planner: HistSummary,
    /// The main MCU's CLOCK_FREQ (Hz).
    pub clock_freq: f64,
}

impl Latency {
    /// A lead margin in milliseconds.
    pub fn lead_ms(&self, ticks: u64) -> f64 {
        ticks as f64 / self.clock_freq * 1e3
    }
}

/// What a closed printer reports.
#[derive(Debug)]
pub struct PrinterReport {
    /// Lines, moves, print and wall time, each stepper's position read back from its MCU
    /// (equal to the host's: checked), homing reports, histograms and allocation figures.
    pub summary: Summary,
    pub link_stats: Vec<(String, links::mcu::LinkStats)>,
    /// Which real-time guarantees were off.
    pub rt_report: Vec<String>,
}

/// What the session's threads share with the printer and its handles.
#[derive(Debug)]
struct Inner {
    machine: Machine,
    mcus: Mcus,
    rt: RtConfig,
    hists: Arc<Hists>,
    shared: Arc<SessionShared>,
    log: LoggerHandle,
    time_scale: f64,
    max_error_s: f64,
    instance: String,
    started: Instant,
}

/// Printers opened by this process (each gets its own service instance).
static OPENED: AtomicU64 = AtomicU64::new(0);
/// Commands queued to the planner before `send_line` waits (back-pressure).
const FEED_DEPTH: usize = 1024;
/// Events kept for a slow reader before new ones are dropped (and counted).
const EVENT_DEPTH: usize = 1024;

/// A running printer (see the module docs).
#[derive(Debug)]
pub struct Printer {
    inner: Arc<Inner>,
    session: Session,
    events: Option<Receiver<Event>>,
    logging: Logging,
    _idle_hold: Option<rt_core::os::DmaLatencyHold>,
}

/// Why a session ended without its summary.
#[derive(Debug, thiserror::Error)]
enum SessionError {
    /// The live print failed.
    #[error(transparent)]
    Print(#[from] crate::live::LiveError),
    /// The session thread panicked.
    #[error("the session thread panicked")]
    Panicked,
    /// `finish` came twice.
    #[error("the session was already closed")]
    Closed,
    /// A handle still holds the printer.
    #[error("the printer is still in use by a handle")]
    InUse,
}

/// The session thread and its feed; a printer dropped without `close` stops and joins it.
#[derive(Debug)]
struct Session {
    feed: Option<SyncSender<FeedMsg>>,
    thread: Option<JoinHandle<Result<Summary, crate::live::LiveError>>>,
    shared: Arc<SessionShared>,
}

impl Session {
    /// Ends the feed (the planner finishes what was sent) and waits for the session's result.
    fn finish(&mut self) -> Result<Summary, SessionError> {
        self.feed = None;
        match self.thread.take().map(JoinHandle::join) {
            Some(Ok(r)) => Ok(r?),
            Some(Err(_)) => Err(SessionError::Panicked),
            None => Err(SessionError::Closed),
        }
    }
}

impl Drop for Session {
    fn drop(&mut self) {
        if self.thread.is_some() {
            self.shared.request_stop("the printer was dropped");
            let _ = self.finish();
        }
    }
}

/// Stops a printer from any thread; cloneable.
#[derive(Debug, Clone)]
pub struct PrinterHandle {
    inner: Weak<Inner>,
    shared: Arc<SessionShared>,
}

impl Printer {
    /// Loads the printer, connects and configures its MCUs (starting simulated ones) and
    /// starts the pipeline threads, ready for G-code.
    pub fn open(source: PrinterSource, opts: PrinterOptions) -> Result<Printer, OpenError> {
        let mut cfg = match source {
            PrinterSource::Simulated => crate::hardware::load_config(None)?,
            PrinterSource::ConfigFile(p) => crate::hardware::load_config(Some(&p))?,
            PrinterSource::Config(c) => *c,
        };
        if !(opts.max_error_us > 0.0 && opts.max_error_us <= 1000.0) {
            return Err(OpenError::Option {
                what: "max_error_us",
                value: opts.max_error_us,
                why: "must be in (0, 1000]",
            });
        }
        let simulated = cfg.mcus.iter().any(|m| m.is_simulated());
        let time_scale = opts.time_scale.unwrap_or(cfg.simulator.time_scale);
        if opts.time_scale.is_some() && !simulated {
            return Err(OpenError::Option {
                what: "time_scale",
                value: time_scale,
                why: "only applies to a simulated printer",
            });
        }
        if !(time_scale > 0.0 && time_scale <= 50.0) {
            return Err(OpenError::Option {
                what: "time_scale",
                value: time_scale,
                why: "must be in (0, 50]",
            });
        }
        // The run's time scale is the simulated printer's (heater safety windows follow it).
        cfg.simulator.time_scale = time_scale;
        let machine = Machine::from_config(&cfg)?;
        let logging = Logging::start_with(opts.log_level, opts.log_file.clone(), opts.log_to_stderr)
            .map_err(|e| OpenError::Thread {
                what: "logger",
                why: e.to_string(),
            })?;
        let rt = RtConfig::from_section(&cfg.realtime, !opts.realtime);
        let idle_hold = rt.hold_idle_latency();
        let (hists, mcus) =
            live::connect_mcus(&cfg, &machine, time_scale, opts.trace.clone(), &rt, &logging)?;
        let (events_tx, events_rx) = mpsc::sync_channel(EVENT_DEPTH);
        let n = OPENED.fetch_add(1, Ordering::Relaxed);
        let inner = Arc::new(Inner {
            machine,
            mcus,
            rt,
            hists,
            shared: Arc::new(SessionShared::new(Some(events_tx))),
            log: logging.handle("main"),
            time_scale,
            max_error_s: opts.max_error_us * 1e-6,
            instance: format!("p{}-{n}", std::process::id()),
            started: Instant::now(),
        });
        let (feed_tx, feed_rx) = mpsc::sync_channel(FEED_DEPTH);
        let input = GcodeInput::session("session", feed_rx, opts.idle_flush);
        let session_inner = Arc::clone(&inner);
        let session = std::thread::Builder::new()
            .name("session".to_string())
            .spawn(move || run_session(&session_inner, input))
            .map_err(|e| OpenError::Thread {
                what: "session",
                why: e.to_string(),
            })?;
        let session = Session {
            feed: Some(feed_tx),
            thread: Some(session),
            shared: Arc::clone(&inner.shared),
        };
        Ok(Printer {
            inner,
            session,
            events: Some(events_rx),
            logging,
            _idle_hold: idle_hold,
        })
    }

    /// The printer's events (state changes, homing results, probe responses, warnings); the
    /// first call takes the receiver, later ones get `None`. Unread events beyond 1024 are
    /// dropped and counted in [`Status::events_dropped`].
    pub fn events(&mut self) -> Option<Receiver<Event>> {
        self.events.take()
    }

    /// A cloneable handle that stops this printer from any thread.
    pub fn handle(&self) -> PrinterHandle {
        PrinterHandle {
            inner: Arc::downgrade(&self.inner),
            shared: Arc::clone(&self.inner.shared),
        }
    }

    /// Queues one G-code command (planned after everything sent before). A line that does not
    /// parse is refused here and the session goes on; waits while 1024 commands are queued.
    pub fn send_line(&self, line: &str) -> Result<(), PrinterError> {
        parse_line(0, line.trim_end_matches(['\n', '\r']).as_bytes())?;
        self.feed(FeedMsg::Line(line.to_string()))
    }

    /// Runs one G-code command and waits until it is planned (its moves are queued, as
    /// Klipper's `gcode/script` answers). A command the planner refuses (it does not parse, is
    /// unknown, moves out of range, a macro fails) returns [`PrinterError::Command`] and the
    /// printer stays ready, unlike `send_line`, where such a command ends the session. An MCU
    /// error or a stop while it runs ends the session ([`PrinterError::Shutdown`]).
    pub fn run_command(&self, line: &str) -> Result<(), PrinterError> {
        let (tx, rx) = mpsc::sync_channel(1);
        self.feed(FeedMsg::Checked(line.to_string(), tx))?;
        match rx.recv() {
            Ok(Ok(())) => Ok(()),
            Ok(Err(e)) if !e.ends_session => Err(PrinterError::Command { message: e.message }),
            Ok(Err(_)) | Err(_) => Err(self.shutdown_error()),
        }
    }

    /// Waits until everything sent so far is planned and handed on to the MCUs, with the
    /// lookahead flushed: the next command starts from the MCUs' time then (a service calls it
    /// at the end of each script, whose next one may come any time later).
    pub fn flush(&self) -> Result<(), PrinterError> {
        self.sync()
    }

    /// Plans and streams a G-code file; returns once every command of it is planned and handed
    /// to the IO stages (use [`Printer::wait_moves`] to wait until the MCUs executed them).
    pub fn run_gcode_file(&self, path: &Path) -> Result<(), PrinterError> {
        let file = std::fs::File::open(path).map_err(|source| PrinterError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        self.run_gcode_stream(path, std::io::BufReader::with_capacity(1 << 16, file))
    }

    /// [`Printer::run_gcode_file`] for any reader, named `name` in errors.
    pub fn run_gcode_stream(&self, name: impl AsRef<Path>, reader: impl BufRead) -> Result<(), PrinterError> {
        for line in reader.lines() {
            let line = line.map_err(|source| PrinterError::Read {
                path: name.as_ref().to_path_buf(),
                source,
            })?;
            self.feed(FeedMsg::Line(line))?;
        }
        self.sync()
    }

    /// Homes the given axes (X, Y, Z) with motion: `G28` on the session's timeline. On a
    /// printer without endstops the axes are declared homed and the report is empty.
    pub fn home(&self, axes: [bool; 3]) -> Result<HomingReport, PrinterError> {
        let mut cmd = String::from("G28");
        for (on, name) in axes.iter().zip([" X", " Y", " Z"]) {
            if *on {
                cmd.push_str(name);
            }
        }
        if let Ok(mut last) = self.inner.shared.last_homing.lock() {
            *last = None;
        }
        self.feed(FeedMsg::Line(cmd))?;
        self.sync()?;
        Ok(self
            .inner
            .shared
            .last_homing
            .lock()
            .ok()
            .and_then(|mut l| l.take())
            .unwrap_or_default())
    }

    /// Waits until everything sent so far is planned and handed on, then until the main
    /// MCU's clock passed the end of it (bounded by that time at the clock's speed + 10 s).
    pub fn wait_moves(&self) -> Result<(), PrinterError> {
        self.sync()?;
        let end = self.inner.shared.motion().planned_until;
        let remaining = (end - self.print_time()).max(0.0);
        let seconds = remaining / self.inner.time_scale + 10.0;
        let deadline = Instant::now() + Duration::from_secs_f64(seconds);
        while self.print_time() < end {
            self.check_running()?;
            if Instant::now() > deadline {
                return Err(PrinterError::Timeout {
                    what: "the MCUs to execute the planned moves",
                    seconds,
                });
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        Ok(())
    }

    /// A snapshot: state, toolhead position, homed axes, print times, link statistics.
    pub fn status(&self) -> Status {
        status_of(&self.inner)
    }

    /// The latency histograms so far.
    pub fn latency(&self) -> Latency {
        latency_of(&self.inner)
    }

    /// A copy of the latency histograms so far (full histograms, where [`Printer::latency`]
    /// gives their summaries).
    pub fn latency_histograms(&self) -> crate::latency::HistSnapshot {
        self.inner.hists.snapshot(self.inner.mcus.main().clock_freq)
    }

    /// Stops the session (see [`PrinterHandle::stop`]).
    pub fn stop(&self) {
        self.handle().stop();
    }

    /// Ends the session: plans what is left, waits for the MCUs to execute it, reads every
    /// stepper's position back (it must equal the host's), closes the MCUs.
    pub fn close(mut self) -> Result<PrinterReport, CloseError> {
        let result = self.session.finish();
        let reason = match &result {
            Ok(_) => "closed".to_string(),
            Err(e) => e.to_string(),
        };
        self.inner.shared.set_shutdown(reason);
        let inner = match take_inner(self.inner) {
            Ok(inner) => inner,
            Err(e) => {
                return Err(CloseError {
                    reason: e.to_string(),
                    link_stats: Vec::new(),
                })
            }
        };
        let Inner {
            mut mcus, started, ..
        } = inner;
        let link_stats = mcus.close();
        let mut summary = match result {
            Ok(s) => s,
            Err(e) => {
                return Err(CloseError {
                    reason: e.to_string(),
                    link_stats,
                })
            }
        };
        summary.wall = started.elapsed().as_secs_f64();
        summary.extra.push(self.logging.finish());
        Ok(PrinterReport {
            summary,
            link_stats,
            rt_report: rt_core::os::rt_report(),
        })
    }

    /// The main MCU's print time now.
    fn print_time(&self) -> f64 {
        print_time_of(&self.inner)
    }

    fn check_running(&self) -> Result<(), PrinterError> {
        match self.inner.shared.shutdown_reason() {
            Some(reason) => Err(PrinterError::Shutdown { reason }),
            None => Ok(()),
        }
    }

    fn feed(&self, msg: FeedMsg) -> Result<(), PrinterError> {
        self.check_running()?;
        let sent = self
            .session
            .feed
            .as_ref()
            .map(|f| f.send(msg).is_ok())
            .unwrap_or(false);
        if sent {
            Ok(())
        } else {
            Err(self.shutdown_error())
        }
    }

    /// Waits until the planner took and planned everything sent before.
    fn sync(&self) -> Result<(), PrinterError> {
        let (tx, rx) = mpsc::sync_channel(1);
        self.feed(FeedMsg::Barrier(tx))?;
        rx.recv().map_err(|_| self.shutdown_error())?;
        self.check_running()
    }

    /// The session's end as an error (waiting briefly for its reason to be recorded).
    fn shutdown_error(&self) -> PrinterError {
        let deadline = Instant::now() + Duration::from_secs(5);
        loop {
            if let Some(reason) = self.inner.shared.shutdown_reason() {
                return PrinterError::Shutdown { reason };
            }
            if Instant::now() > deadline {
                return PrinterError::Shutdown {
                    reason: "the session ended".to_string(),
                };
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }
}

impl PrinterHandle {
    /// Stops the session at the planner's next check (within a few ms): nothing more is
    /// planned or sent; steps already at the MCUs still run. The printer is then shut down
    /// with reason "stopped by the host".
    pub fn stop(&self) {
        self.shared.request_stop("stopped by the host");
    }

    /// Sends `emergency_stop` to every MCU at once (they stop all motion and shut down), then
    /// stops the session.
    pub fn emergency_stop(&self) {
        self.shared.request_stop("emergency stop");
        if let Some(heaters) = self.shared.heaters.get() {
            heaters.turn_off_all();
        }
        if let Some(inner) = self.inner.upgrade() {
            for m in &inner.mcus.list {
                if let Ok(cmd) = m.link.dictionary().encode("emergency_stop", &[]) {
                    let _ = m.link.send(cmd);
                }
            }
        }
    }

    /// The printer's state.
    pub fn state(&self) -> PrinterState {
        state_of(&self.shared)
    }

    /// The latency histograms so far (`None` once the printer is closed).
    pub fn latency(&self) -> Option<Latency> {
        self.inner.upgrade().map(|inner| latency_of(&inner))
    }

    /// A snapshot (without link statistics once the printer is closed).
    pub fn status(&self) -> Status {
        match self.inner.upgrade() {
            Some(inner) => status_of(&inner),
            None => {
                let (heaters, fans, sensors) = self.shared.heater_status();
                Status {
                    state: state_of(&self.shared),
                    position: self.shared.motion().position,
                    homed: self.shared.motion().homed,
                    planned_until: self.shared.motion().planned_until,
                    print_time: 0.0,
                    mcus: Vec::new(),
                    events_dropped: self.shared.events_dropped(),
                    bed_mesh: None,
                    heaters,
                    fans,
                    sensors,
                    save_config_pending: self.shared.save_pending(),
                }
            }
        }
    }
}

/// The session thread: the live print of the session's feed, on the printer's MCUs.
fn run_session(inner: &Inner, input: GcodeInput) -> Result<Summary, crate::live::LiveError> {
    let run = LiveRun {
        started: inner.started,
        scale: inner.time_scale,
        max_error_s: inner.max_error_s,
        rt: &inner.rt,
        hists: &inner.hists,
        log: &inner.log,
        session: Some(&inner.shared),
        instance: &inner.instance,
    };
    let result = live::print_on(input, &inner.machine, &inner.mcus, &run);
    let reason = match &result {
        Ok(_) => "closed".to_string(),
        Err(e) => e.to_string(),
    };
    inner.shared.set_shutdown(reason);
    result
}

/// The only reference left once the session thread ended (a handle may hold one briefly).
fn take_inner(mut inner: Arc<Inner>) -> Result<Inner, SessionError> {
    for _ in 0..200 {
        match Arc::try_unwrap(inner) {
            Ok(i) => return Ok(i),
            Err(again) => inner = again,
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    Err(SessionError::InUse)
}

fn print_time_of(inner: &Inner) -> f64 {
    let main = inner.mcus.main();
    main.link.clock().clock_at(McuLink::system_now()) / main.clock_freq
}

fn state_of(shared: &SessionShared) -> PrinterState {
    match shared.shutdown_reason() {
        Some(reason) => PrinterState::Shutdown { reason },
        None if shared.motion().busy => PrinterState::Printing,
        None => PrinterState::Ready,
    }
}

fn status_of(inner: &Inner) -> Status {
    let motion = inner.shared.motion();
    let (heaters, fans, sensors) = inner.shared.heater_status();
    Status {
        state: state_of(&inner.shared),
        position: motion.position,
        homed: motion.homed,
        planned_until: motion.planned_until,
        print_time: print_time_of(inner),
        mcus: inner
            .mcus
            .list
            .iter()
            .map(|m| (m.name.clone(), m.link.stats()))
            .collect(),
        events_dropped: inner.shared.events_dropped(),
        bed_mesh: inner
            .machine
            .bed_mesh
            .as_ref()
            .map(crate::homing::bed_mesh::BedMeshOut::status),
        heaters,
        fans,
        sensors,
        save_config_pending: inner.shared.save_pending(),
    }
}

fn latency_of(inner: &Inner) -> Latency {
    let summary =
        |m: &std::sync::Mutex<rt_core::hist::LatencyHist>| m.lock().map(|h| h.summary()).unwrap_or_default();
    Latency {
        lead_margin: summary(&inner.hists.lead),
        handoff: summary(&inner.hists.handoff),
        wake_planner: summary(&inner.hists.wake_planner),
        clock_freq: inner.mcus.main().clock_freq,
    }
}
