//! The live print on real-time threads:
//!
//! ```text
//! [planner] G-code → lookahead → steps → compression ──StepBatch (iceoryx2)──► [io-mcu] ──► link IO thread ──► pty/tty
//!  core 0, SCHED_FIFO                                   cadence/<instance>/mcu/mcu/steps      core 1, SCHED_FIFO
//! ```
//!
//! The planner thread runs the G-code loop with flow control (buffered print time between a
//! low and a high water mark) and publishes encoded step messages in batches over iceoryx2
//! shared memory (no loss: safe overflow off, back-pressure, sequence numbers). Each MCU with
//! steppers has its own channel (`cadence/<instance>/mcu/<mcu>/steps`) and its own IO stage
//! thread (`io-<mcu>`), whose steps the planner counts in that MCU's clock (see `streams`). An
//! IO stage subscribes, checks each step message's lead (in its MCU's clock) before handing it
//! to the MCU link, and the link's own IO thread writes it. Histograms recorded on the way: lead margin of every step
//! message (in the link IO thread, when its bytes leave), hand-off latency planner → IO stage,
//! and each stage's wake-up lateness. When the OS refuses pinning or SCHED_FIFO, the threads run
//! anyway and rt-core reports once which guarantees are off.
//!
//! The planner reaches the MCUs through [`McuSide`]: in this process (the IO stage is a thread
//! here; homing works) or in a `cadence serve --role io` process (`--io-process`, see
//! `remote`): then the dictionary, move queue size and clock snapshots come over shared memory
//! (the main MCU's only: a printer with steppers on other MCUs is refused there).
//!
//! Logging during a print: the threads push fixed-size records to rt-core's logger thread
//! ([`Logging`]), the only one that formats or writes; nobody prints from a real-time thread.
//! Telemetry is published by a thread of its own ([`telemetry_thread`]), off the planner's loop.

use std::cell::{Cell, RefCell};
use std::fs::File;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicI64, AtomicU64, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use clap::Args;
use links::clocksync::ClockEstimate;
use links::dict::Cmd;
use links::mcu::McuLink;
use planner::pipeline::Pipeline;
use planner::stepgen::StepCmd;
use rt_core::alloc_count::AllocCounter;
use rt_core::hist::LatencyHist;
use rt_core::logger::{Arg, Level, Logger, LoggerConfig, LoggerHandle};
use rt_core::os::{apply_rt, RtSpec};
use rt_core::shm::{
    open_node, steps_service_name, telemetry_kind, telemetry_service_name, ChannelConfig, ShmPublisher,
    ShmSubscriber, StepBatch, Telemetry, WireMsg,
};

use crate::accessories::Accessories;
use crate::homing::{run_motion, HomingCtx};
use crate::machine::Machine;
use crate::mcus::Mcus;
use crate::print::{plan_file, MotionCmd, PrintArgs, Summary, MIN_LEAD_S};
use crate::sink::Sink;
use crate::streams::{McuParams, StepStreams};

/// `ipc::Service` with pooled per-loan state: a loan allocates nothing after warm-up (see
/// rt-core's `shm::pooled`); it talks to `ipc::Service` ports of other processes unchanged.
type Ipc = rt_core::shm::pooled::Ipc;

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

impl LiveArgs {
    /// True when the IO stage runs in another process.
    pub fn remote(&self) -> bool {
        self.io_process || self.io_attach.is_some()
    }
}

/// The print's logger thread: the only thread that formats or writes log text during a print.
#[derive(Debug)]
pub struct Logging {
    pub handle: LoggerHandle,
    join: Option<JoinHandle<u64>>,
}

impl Logging {
    /// Starts the logger thread (stderr, plus `file` if given).
    pub fn start(level: Level, file: Option<PathBuf>) -> Result<Logging, String> {
        let (handle, join) = Logger::start(LoggerConfig {
            level,
            file,
            stderr: true,
            ..LoggerConfig::default()
        })
        .map_err(|e| e.to_string())?;
        Ok(Logging {
            handle,
            join: Some(join),
        })
    }

    /// A handle for thread `tag`.
    pub fn handle(&self, tag: &'static str) -> LoggerHandle {
        self.handle.with_tag(tag)
    }

    /// Drains and stops the logger thread; returns the report line (records written, dropped).
    pub fn finish(mut self) -> String {
        let written = self.stop();
        format!(
            "log: {written} records written, {} dropped (queue full)",
            self.handle.dropped()
        )
    }

    fn stop(&mut self) -> u64 {
        self.handle.shutdown();
        self.join.take().and_then(|j| j.join().ok()).unwrap_or(0)
    }
}

impl Drop for Logging {
    fn drop(&mut self) {
        if self.join.is_some() {
            self.stop();
        }
    }
}

/// Where the planner thread's MCU-side needs come from.
#[derive(Debug, Clone, Copy)]
pub(crate) enum McuSide<'a> {
    /// The MCUs are connected in this process (the IO stage is a thread here).
    Local(&'a Mcus),
    /// The MCUs live in a `cadence serve --role io` process.
    Remote(&'a crate::remote::RemoteMcu),
}

impl<'a> McuSide<'a> {
    /// What the step streams need of each MCU that gets one (the main MCU first).
    fn stream_params(&self, machine: &Machine) -> Result<Vec<McuParams<'a>>, String> {
        match *self {
            McuSide::Local(m) => Ok(m.stream_params(machine)),
            McuSide::Remote(r) => {
                crate::remote::check_single_mcu(machine)?;
                Ok(vec![McuParams {
                    name: &r.name,
                    mcu_index: 0,
                    dict: &r.dict,
                    clock_freq: r.clock_freq,
                    move_count: r.move_count,
                }])
            }
        }
    }

    /// The clock fit of MCU `mcu_index` (in `[mcu]` order; lock-free).
    fn clock(&self, mcu_index: usize) -> ClockEstimate {
        match self {
            McuSide::Local(m) => m
                .list
                .get(mcu_index)
                .map_or(ClockEstimate::INVALID, |c| c.link.clock()),
            McuSide::Remote(r) => r.clock(),
        }
    }

    /// An MCU shutdown or a failed IO process, as an error.
    fn check(&self) -> Result<(), String> {
        match self {
            McuSide::Local(m) => m.check(),
            McuSide::Remote(r) => r.check(),
        }
    }
}

/// Thread placement and priorities of a live print (from printer.cfg's `[realtime]`).
#[derive(Debug, Clone)]
pub struct RtConfig {
    /// Apply pinning / SCHED_FIFO / mlockall at all.
    pub enabled: bool,
    pub planner_core: usize,
    /// `None`: IO threads unpinned (`[realtime] io_cpu: any`).
    pub io_core: Option<usize>,
    pub planner_priority: i32,
    pub io_priority: i32,
    pub lock_memory: bool,
    /// Hold `/dev/cpu_dma_latency` at 0 while running.
    pub cpu_dma_latency_zero: bool,
    /// Keep idle CPUs polling while a homing or probing move runs.
    pub idle_poll_homing: bool,
}

impl RtConfig {
    /// From printer.cfg's `[realtime]`; `no_realtime` (the `--no-realtime` flag) turns it off.
    pub fn from_section(r: &sysconfig::printer::RealtimeSection, no_realtime: bool) -> RtConfig {
        RtConfig {
            enabled: r.enabled && !no_realtime,
            planner_core: r.planner_cpu,
            io_core: r.io_cpu,
            planner_priority: r.planner_priority,
            io_priority: r.io_priority,
            lock_memory: r.lock_memory,
            cpu_dma_latency_zero: r.cpu_dma_latency_zero,
            idle_poll_homing: r.idle_poll_homing,
        }
    }

    /// Holds `/dev/cpu_dma_latency` at 0 while the returned guard lives (when real time is on
    /// and `[realtime] cpu_dma_latency_zero` is true); a refusal is reported once.
    pub fn hold_idle_latency(&self) -> Option<rt_core::os::DmaLatencyHold> {
        if !(self.enabled && self.cpu_dma_latency_zero) {
            return None;
        }
        rt_core::os::ok_or_report(
            rt_core::os::hold_cpu_dma_latency_zero(),
            rt_core::os::Guarantee::DmaLatency,
            "idle CPUs may sleep deeply (slower wake-ups)",
        )
    }

    /// Whether homing and probing moves keep the idle CPUs polling (real time on and
    /// `[realtime] idle_poll_homing` true).
    pub fn idle_poll_homing(&self) -> bool {
        self.enabled && self.idle_poll_homing
    }

    /// Starts idle polling (see [`rt_core::os::IdlePoll`]) when [`Self::idle_poll_homing`];
    /// a refusal is reported once and homing goes on without it.
    pub fn start_idle_poll(&self) -> Option<rt_core::os::IdlePoll> {
        if !self.idle_poll_homing() {
            return None;
        }
        rt_core::os::ok_or_report(
            rt_core::os::IdlePoll::start(),
            rt_core::os::Guarantee::IdlePoll,
            "idle CPUs may halt during homing (slower trigger relay wake-ups)",
        )
    }

    /// Settings of the MCU links' own IO threads: on the IO core, above the IO stage (they
    /// write the bytes and relay homing triggers).
    pub fn link_spec(&self) -> RtSpec {
        self.spec("io-link", self.io_core, self.io_priority + 5)
    }

    /// Settings of the IO stage thread of MCU `mcu`.
    pub fn io_spec(&self, mcu: &str) -> RtSpec {
        self.spec(&format!("io-{mcu}"), self.io_core, self.io_priority)
    }

    /// Settings of the planner thread.
    pub fn planner_spec(&self) -> RtSpec {
        self.spec("planner", Some(self.planner_core), self.planner_priority)
    }

    fn spec(&self, name: &str, core: Option<usize>, priority: i32) -> RtSpec {
        let mut spec = RtSpec::new(name);
        if self.enabled {
            spec.core = core.map(|c| c % available_cores());
            spec.fifo_priority = Some(priority);
            spec.lock_memory = self.lock_memory;
        }
        spec
    }
}

fn available_cores() -> usize {
    std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
}

/// MCUs whose lead margins [`Hists::lead_hook`] records (the first ones in `[mcu]` order;
/// the link statistics of every MCU keep its minimum anyway).
pub const LEAD_MCUS: usize = 8;

/// Latency histograms recorded during a live print.
#[derive(Debug)]
pub struct Hists {
    /// Lead margin of each step message when its bytes left, every MCU's, in ticks of the
    /// main MCU's clock (print ticks: another MCU's margins are scaled).
    pub lead: Mutex<LatencyHist>,
    /// Planner → IO stage hand-off (ns).
    pub handoff: Mutex<LatencyHist>,
    /// Planner thread wake-up lateness after a flow-control sleep (ns).
    pub wake_planner: Mutex<LatencyHist>,
    /// Per MCU: a step message leaving with less lead than this (its ticks) is logged as an
    /// error (0 until the MCU's clock frequency is known: then only negative margins are).
    pub min_lead_ticks: [AtomicI64; LEAD_MCUS],
    /// Per MCU: main ticks per tick of this MCU (f64 bits; 1.0 until known).
    lead_scale: [AtomicU64; LEAD_MCUS],
}

impl Hists {
    pub fn new() -> Arc<Hists> {
        let ticks = || LatencyHist::with_bounds(1, 1 << 42, 3, 1.0).unwrap_or_else(|_| LatencyHist::new());
        Arc::new(Hists {
            lead: Mutex::new(ticks()),
            handoff: Mutex::new(LatencyHist::new()),
            wake_planner: Mutex::new(LatencyHist::new()),
            min_lead_ticks: std::array::from_fn(|_| AtomicI64::new(0)),
            lead_scale: std::array::from_fn(|_| AtomicU64::new(1f64.to_bits())),
        })
    }

    /// A link margin hook for MCU `mcu` (index in `[mcu]` order) recording into `lead` (runs
    /// in the link's IO thread; a `try_lock` so the IO thread never waits on a reader) and
    /// logging a message that left late. `None` past [`LEAD_MCUS`].
    pub fn lead_hook(
        self: &Arc<Self>,
        log: LoggerHandle,
        mcu: usize,
    ) -> Option<links::serialqueue::MarginHook> {
        if mcu >= LEAD_MCUS {
            return None;
        }
        let h = Arc::clone(self);
        let hook: links::serialqueue::MarginHook = Box::new(move |req: u64, margin: i64| {
            // Relaxed: a scale and threshold set once before the print starts.
            let scale = f64::from_bits(h.lead_scale[mcu].load(Ordering::Relaxed));
            if let Ok(mut hist) = h.lead.try_lock() {
                hist.record_signed((margin as f64 * scale) as i64);
            }
            if margin < h.min_lead_ticks[mcu].load(Ordering::Relaxed) {
                log.log(
                    Level::Error,
                    "step message left with too little lead: mcu index, req_clock, margin ticks",
                    [Arg::U(mcu as u64), Arg::U(req), Arg::I(margin)],
                );
            }
        });
        Some(hook)
    }

    /// Hooks for `ConnectOptions::lead_hooks`.
    pub fn lead_hooks(self: &Arc<Self>, log: LoggerHandle) -> crate::mcus::LeadHooks {
        let h = Arc::clone(self);
        Box::new(move |mcu| {
            h.lead_hook(log.clone(), mcu)
                .unwrap_or_else(|| -> links::serialqueue::MarginHook { Box::new(|_, _| {}) })
        })
    }

    /// Sets, for every connected MCU, the lead below which a step message is logged as late
    /// and the scale of its margins into the main MCU's ticks.
    pub fn set_min_lead(&self, mcus: &Mcus) {
        let main_freq = mcus.main().clock_freq;
        for (i, m) in mcus.list.iter().enumerate().take(LEAD_MCUS) {
            self.min_lead_ticks[i].store((MIN_LEAD_S * m.clock_freq) as i64, Ordering::Relaxed);
            self.lead_scale[i].store((main_freq / m.clock_freq).to_bits(), Ordering::Relaxed);
        }
    }

    /// Report lines (margins in ms of print time).
    pub fn report(&self, clock_freq: f64) -> Vec<String> {
        let mut out = Vec::new();
        if let Ok(h) = self.lead.lock() {
            let s = h.summary();
            if s.count > 0 {
                let ms = |t: u64| t as f64 / clock_freq * 1e3;
                out.push(format!(
                    "lead margin (ms): min {:.1} p0.1 {:.1} p1 {:.1} p50 {:.1} over {} step messages{}",
                    ms(s.min),
                    ms(s.p0_1),
                    ms(s.p1),
                    ms(s.p50),
                    s.count,
                    if s.negative > 0 {
                        format!(", {} LATE", s.negative)
                    } else {
                        String::new()
                    }
                ));
            }
        }
        for (name, m) in [
            ("hand-off planner→io", &self.handoff),
            ("wake-up lateness planner", &self.wake_planner),
        ] {
            if let Ok(h) = m.lock() {
                let s = h.summary();
                if s.count > 0 {
                    out.push(format!("{name}: {} ({} samples)", s.format_latency(), s.count));
                }
            }
        }
        out
    }

    /// Publishes a summary of each histogram on the telemetry service (see the module docs):
    /// kind `HIST_SUMMARY`, values = [count, negative, min, p0.1, p1, p50, p99, p99.9, max,
    /// mean, ns_per_unit], source 0 = lead margin (MCU ticks), 1 = hand-off (ns), 2 = planner
    /// wake-up lateness (ns). Monitors never stall the printer (safe overflow on). Only the
    /// sources in `sources` (bit n = source n) are published: with the IO stage in another
    /// process, each process publishes the histograms it records.
    pub(crate) fn publish<S: iceoryx2::service::Service>(
        &self,
        publisher: &mut ShmPublisher<S, Telemetry>,
        t_ns: u64,
        sources: u32,
    ) {
        for (source, m) in [(0u32, &self.lead), (1, &self.handoff), (2, &self.wake_planner)] {
            if sources & (1 << source) == 0 {
                continue;
            }
            let Ok(h) = m.try_lock() else { continue };
            let x = h.summary();
            drop(h);
            let values = [
                x.count as f64,
                x.negative as f64,
                x.min as f64,
                x.p0_1 as f64,
                x.p1 as f64,
                x.p50 as f64,
                x.p99 as f64,
                x.p999 as f64,
                x.max as f64,
                x.mean,
                x.ns_per_unit,
            ];
            let _ = publisher.send_with(|t| {
                t.kind = telemetry_kind::HIST_SUMMARY;
                t.source = source;
                t.t_ns = t_ns;
                t.count = values.len() as u32;
                t.values[..values.len()].copy_from_slice(&values);
            });
        }
    }

    /// Saves every histogram as an HdrHistogram V2 interval log.
    pub fn save(&self, path: &std::path::Path, wall_s: f64) -> Result<(), String> {
        let file = File::create(path).map_err(|e| format!("{}: {e}", path.display()))?;
        let err = |e: rt_core::hist::HistError| format!("{}: {e}", path.display());
        let mut log = rt_core::hist::IntervalLog::begin(
            std::io::BufWriter::new(file),
            "cadence print latency histograms",
        )
        .map_err(err)?;
        for (tag, m) in [
            ("lead_margin_ticks", &self.lead),
            ("handoff_ns", &self.handoff),
            ("wake_planner_ns", &self.wake_planner),
        ] {
            if let Ok(h) = m.lock() {
                log.write(tag, &h, Duration::ZERO, Duration::from_secs_f64(wall_s.max(0.0)))
                    .map_err(err)?;
            }
        }
        log.finish().map_err(err)?;
        Ok(())
    }
}

/// Telemetry sources of [`Hists::publish`].
pub(crate) const ALL_SOURCES: u32 = 0b111;
pub(crate) const LEAD_SOURCE: u32 = 0b001;
pub(crate) const PLANNER_SOURCES: u32 = 0b110;

fn mono_ns() -> u64 {
    (McuLink::system_now() * 1e9) as u64
}

/// The planner side of the shared-memory hand-off: packs messages into batches.
pub(crate) struct ShmSink {
    publisher: ShmPublisher<Ipc, StepBatch>,
    batch: StepBatch,
}

impl ShmSink {
    fn push(&mut self, m: WireMsg) -> Result<(), String> {
        if !self.batch.push(m) {
            self.flush()?;
            self.batch.push(m);
        }
        Ok(())
    }

    /// Publishes the pending batch (if any).
    fn flush(&mut self) -> Result<(), String> {
        if self.batch.count == 0 {
            return Ok(());
        }
        let batch = self.batch;
        self.publisher
            .send_with(|b| {
                *b = batch;
                b.t_ns = mono_ns();
            })
            .map_err(|e| format!("planner → io hand-off: {e}"))?;
        self.batch.count = 0;
        Ok(())
    }
}

impl Sink for ShmSink {
    fn send(&mut self, cmd: Cmd) -> Result<(), String> {
        self.push(WireMsg::new(0, 0, cmd.as_bytes()).unwrap_or_default())
    }
    fn send_clocked(&mut self, cmd: Cmd, min_clock: u64, req_clock: u64) -> Result<(), String> {
        self.push(WireMsg::new(min_clock, req_clock, cmd.as_bytes()).unwrap_or_default())
    }
}

/// What the IO stage reports.
#[derive(Debug, Default)]
pub(crate) struct IoReport {
    pub batches: u64,
    pub allocations_after_warmup: Option<u64>,
    /// Batches taken after warm-up (the loop iterations `allocations_after_warmup` covers).
    pub batches_after_warmup: u64,
}

/// A stage's heap allocations after warm-up and the step batches it handled meanwhile (so a
/// 0 means something only with batches > 0). Homing and probing moves in the middle of a print
/// leave the streaming loop (the planner drains the hand-off and drives the MCUs directly,
/// building and parsing their messages): their allocations are counted apart. Displayed as
/// "`allocations` (`batches` batches)", then "; `n` more in `m` homing/probing commands".
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(crate) struct AfterWarmup {
    pub allocations: u64,
    pub batches: u64,
    /// Allocations during homing/probing commands after warm-up (not in `allocations`).
    pub motion_allocations: u64,
    /// Homing/probing commands after warm-up.
    pub motions: u64,
}

impl std::fmt::Display for AfterWarmup {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} ({} batches", self.allocations, self.batches)?;
        if self.motions > 0 {
            write!(
                f,
                "; {} more in {} homing/probing command{}",
                self.motion_allocations,
                self.motions,
                if self.motions == 1 { "" } else { "s" }
            )?;
        }
        write!(f, ")")
    }
}

/// Batches after which a stage counts as warmed up (allocation accounting starts).
const WARMUP_BATCHES: u64 = 64;

/// The IO stage: shared memory → lead check → the MCU link. Runs until `done` is set and no
/// batch is pending; `consumed` counts the batches taken.
#[allow(clippy::too_many_arguments)]
pub(crate) fn io_stage(
    link: &McuLink,
    service: &str,
    ready: mpsc::Sender<Result<(), String>>,
    done: &AtomicBool,
    consumed: &AtomicU64,
    hists: &Hists,
    clock_freq: f64,
    log: &LoggerHandle,
) -> Result<IoReport, String> {
    let setup = || -> Result<_, String> {
        let (node, _) =
            open_node::<Ipc>(&format!("cadence-io-{}", std::process::id())).map_err(|e| e.to_string())?;
        let sub = ShmSubscriber::<Ipc, StepBatch>::open(&node, service, &ChannelConfig::steps())
            .map_err(|e| e.to_string())?;
        Ok((node, sub))
    };
    // The node stays alive as long as its port.
    let (_node, mut sub) = match setup() {
        Ok(s) => {
            let _ = ready.send(Ok(()));
            s
        }
        Err(e) => {
            let _ = ready.send(Err(e.clone()));
            return Err(e);
        }
    };
    log.log(Level::Info, "io stage subscribed to its step channel", []);
    let lead_ticks = MIN_LEAD_S * clock_freq;
    let idle_wait = Duration::from_millis(5);
    let mut report = IoReport::default();
    let mut warm: Option<AllocCounter> = None;
    loop {
        let was_done = done.load(Ordering::Acquire);
        let got = sub
            .recv_timeout_with(idle_wait, |b| *b)
            .map_err(|e| format!("io stage: {e}"))?;
        let Some(batch) = got else {
            if was_done {
                break;
            }
            continue;
        };
        if let Ok(mut h) = hists.handoff.try_lock() {
            h.record(mono_ns().saturating_sub(batch.t_ns));
        }
        let now_clock = link.clock().clock_at(McuLink::system_now());
        for m in batch.messages() {
            if m.req_clock > 0 && (m.req_clock as f64) < now_clock + lead_ticks {
                log.log(
                    Level::Error,
                    "io stage fell behind: req_clock, ms before due",
                    [
                        Arg::U(m.req_clock),
                        Arg::F((m.req_clock as f64 - now_clock) / clock_freq * 1e3),
                    ],
                );
                return Err(format!(
                    "the IO stage fell behind: a step message for clock {} reached it {:.1} ms before it is due \
                     (at least {:.0} ms required); print stopped before sending it",
                    m.req_clock,
                    (m.req_clock as f64 - now_clock) / clock_freq * 1e3,
                    MIN_LEAD_S * 1e3
                ));
            }
            let cmd = Cmd::from_bytes(m.bytes()).ok_or("io stage: malformed message in a step batch")?;
            if m.req_clock == 0 && m.min_clock == 0 {
                link.send(cmd).map_err(|e| e.to_string())?;
            } else {
                link.send_clocked(cmd, m.min_clock, m.req_clock)
                    .map_err(|e| e.to_string())?;
            }
        }
        report.batches += 1;
        // Pairs with the planner's Acquire load before homing talks to the link directly.
        consumed.store(batch.seq + 1, Ordering::Release);
        if report.batches == WARMUP_BATCHES {
            warm = Some(AllocCounter::snapshot());
        }
    }
    report.allocations_after_warmup = warm.map(|w| AllocCounter::snapshot().since(w).allocations());
    report.batches_after_warmup = report.batches.saturating_sub(WARMUP_BATCHES);
    log.log(Level::Info, "io stage done: batches", [Arg::U(report.batches)]);
    Ok(report)
}

/// How a live print runs: when it started, the simulator's time scale, thread placement and
/// where its histograms go.
#[derive(Debug)]
pub struct LiveRun<'a> {
    pub started: Instant,
    pub scale: f64,
    pub rt: &'a RtConfig,
    pub hists: &'a Arc<Hists>,
    pub log: &'a LoggerHandle,
}

/// Runs the live print of `gcode` on the connected MCUs: one IO stage thread per MCU with
/// steppers (each subscribed to its own step channel), the planner thread feeding them all.
pub fn print_on(
    args: &PrintArgs,
    machine: &Machine,
    mcus: &Mcus,
    gcode: File,
    run: &LiveRun<'_>,
) -> Result<Summary, String> {
    let LiveRun {
        started,
        scale,
        rt,
        hists,
        log,
    } = *run;
    let instance = format!("p{}", std::process::id());
    // (MCU index, step channel) of each MCU with steppers, the main one first.
    let streams: Vec<(usize, String)> = mcus
        .stream_params(machine)
        .iter()
        .map(|m| (m.mcu_index, steps_service_name(&instance, m.name)))
        .collect();
    let done_flag = AtomicBool::new(false);
    let done = &done_flag;
    let consumed_counts: Vec<AtomicU64> = streams.iter().map(|_| AtomicU64::new(0)).collect();
    let consumed = consumed_counts.as_slice();
    let instance = instance.as_str();

    std::thread::scope(|scope| {
        let mut ios = Vec::with_capacity(streams.len());
        for (k, (mcu_index, service)) in streams.iter().enumerate() {
            let conn = &mcus.list[*mcu_index];
            let (link, clock_freq) = (&conn.link, conn.clock_freq);
            let (ready_tx, ready_rx) = mpsc::channel();
            let io_spec = rt.io_spec(&conn.name);
            let counter = &consumed[k];
            let io = std::thread::Builder::new()
                .name(io_spec.name.clone())
                .spawn_scoped(scope, move || {
                    apply_rt(&io_spec);
                    let log = log.with_tag("io");
                    io_stage(link, service, ready_tx, done, counter, hists, clock_freq, &log)
                })
                .map_err(|e| format!("cannot start the IO stage thread of mcu '{}': {e}", conn.name))?;
            let ready = match ready_rx.recv_timeout(Duration::from_secs(10)) {
                Ok(Ok(())) => Ok(()),
                Ok(Err(e)) => Err(format!("io stage of mcu '{}': {e}", conn.name)),
                Err(_) => Err(format!(
                    "io stage of mcu '{}' did not start within 10 s",
                    conn.name
                )),
            };
            ios.push(io);
            if let Err(e) = ready {
                done.store(true, Ordering::Release);
                return Err(e);
            }
        }
        let planner_spec = rt.planner_spec();
        let planner = std::thread::Builder::new()
            .name("planner".to_string())
            .spawn_scoped(scope, move || {
                apply_rt(&planner_spec);
                let log = log.with_tag("planner");
                let side = McuSide::Local(mcus);
                let r = planner_stage(
                    args, machine, side, gcode, scale, instance, consumed, hists, &log, rt,
                );
                done.store(true, Ordering::Release);
                r
            })
            .map_err(|e| format!("cannot start the planner thread: {e}"));
        let planner = match planner {
            Ok(p) => p,
            Err(e) => {
                done.store(true, Ordering::Release);
                return Err(e);
            }
        };
        let telemetry = std::thread::Builder::new()
            .name("telemetry".to_string())
            .spawn_scoped(scope, move || {
                telemetry_thread(instance, hists, started, ALL_SOURCES, done)
            })
            .map_err(|e| format!("cannot start the telemetry thread: {e}"))?;
        let planned = planner
            .join()
            .map_err(|_| "the planner thread panicked".to_string())?;
        done.store(true, Ordering::Release);
        if let Ok(Err(e)) = telemetry.join() {
            log.log(Level::Warn, "telemetry failed (see stderr)", []);
            eprintln!("cadence: telemetry: {e}");
        }
        let mut io_total = IoReport::default();
        let mut io_allocs = Some(0u64);
        let mut io_error = None;
        for io in ios {
            let r = io
                .join()
                .map_err(|_| "an IO stage thread panicked".to_string())
                .and_then(|r| r);
            match r {
                Ok(r) => {
                    io_total.batches += r.batches;
                    io_total.batches_after_warmup += r.batches_after_warmup;
                    io_allocs = match (io_allocs, r.allocations_after_warmup) {
                        (Some(a), Some(b)) => Some(a + b),
                        // A stage that never warmed up (few batches) counts nothing.
                        (a, None) if r.batches < WARMUP_BATCHES => a,
                        _ => None,
                    };
                }
                Err(e) => io_error = io_error.or(Some(e)),
            }
        }
        // A failed IO stage is the root cause of a planner hand-off error: report it first.
        if let Some(e) = io_error {
            return Err(e);
        }
        let (mut summary, pipeline, streams, planner_allocs, _) = planned?;
        finish_print(mcus, machine, &pipeline, &streams, &mut summary, scale)?;
        summary.extra.extend(hists.report(summary.clock_freq));
        summary.extra.push(format!(
            "allocations after warm-up: planner {}, io stage{} {}; {} batches in all",
            planner_allocs.map_or("n/a".to_string(), |n| n.to_string()),
            if streams.mcus.len() > 1 { "s" } else { "" },
            io_allocs
                .filter(|_| io_total.batches >= WARMUP_BATCHES)
                .map_or("n/a".to_string(), |n| {
                    AfterWarmup {
                        allocations: n,
                        batches: io_total.batches_after_warmup,
                        ..AfterWarmup::default()
                    }
                    .to_string()
                }),
            io_total.batches
        ));
        Ok(summary)
    })
}

/// The telemetry thread: publishes the histogram summaries of `sources` on
/// `cadence/<instance>/telemetry` about once a second until `stop`, then once more. A thread of
/// its own (not real-time): summarising histograms is no work for the planner's loop.
pub(crate) fn telemetry_thread(
    instance: &str,
    hists: &Hists,
    started: Instant,
    sources: u32,
    stop: &AtomicBool,
) -> Result<(), String> {
    let (node, _) =
        open_node::<Ipc>(&format!("cadence-telemetry-{}", std::process::id())).map_err(|e| e.to_string())?;
    let mut publisher = ShmPublisher::<Ipc, Telemetry>::open(
        &node,
        &telemetry_service_name(instance),
        &ChannelConfig::telemetry(),
    )
    .map_err(|e| e.to_string())?;
    let mut last = Instant::now();
    // Acquire pairs with the Release store of whoever stops the print.
    while !stop.load(Ordering::Acquire) {
        std::thread::sleep(Duration::from_millis(50));
        if last.elapsed() >= Duration::from_secs(1) {
            last = Instant::now();
            hists.publish(&mut publisher, started.elapsed().as_nanos() as u64, sources);
        }
    }
    hists.publish(&mut publisher, started.elapsed().as_nanos() as u64, sources);
    Ok(())
}

/// What the planner thread hands back: the summary so far, the pipeline and step streams
/// (final positions, last step clocks), its allocations after warm-up and the number of step
/// batches published per stream.
pub(crate) type Planned = (Summary, Pipeline, StepStreams, Option<AfterWarmup>, Vec<u64>);

/// The planner thread: G-code → pipeline → step messages into shared memory (one channel per
/// MCU with steppers: `cadence/<instance>/mcu/<mcu>/steps`), paced. `consumed[k]` counts the
/// batches stream k's IO stage took.
#[allow(clippy::too_many_arguments)]
pub(crate) fn planner_stage(
    args: &PrintArgs,
    machine: &Machine,
    side: McuSide<'_>,
    gcode: File,
    scale: f64,
    instance: &str,
    consumed: &[AtomicU64],
    hists: &Hists,
    log: &LoggerHandle,
    rt: &RtConfig,
) -> Result<Planned, String> {
    let params = side.stream_params(machine)?;
    let Some(main) = params.first().copied() else {
        return Err("the printer has no MCU".to_string());
    };
    if consumed.len() != params.len() {
        return Err(format!(
            "internal error: {} IO stages for {} step streams",
            consumed.len(),
            params.len()
        ));
    }
    let clock_freq = main.clock_freq;
    let (node, _) =
        open_node::<Ipc>(&format!("cadence-planner-{}", std::process::id())).map_err(|e| e.to_string())?;
    let mut sinks = Vec::with_capacity(params.len());
    for m in &params {
        let service = steps_service_name(instance, m.name);
        let publisher = ShmPublisher::<Ipc, StepBatch>::open(&node, &service, &ChannelConfig::steps())
            .map_err(|e| format!("planner → io hand-off of mcu '{}': {e}", m.name))?;
        let deadline = Instant::now() + Duration::from_secs(5);
        while publisher.connect().map_err(|e| e.to_string())? < 1 {
            if Instant::now() > deadline {
                return Err(format!(
                    "planner → io hand-off: the IO stage of mcu '{}' never subscribed",
                    m.name
                ));
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        sinks.push(ShmSink {
            publisher,
            batch: StepBatch::default(),
        });
    }
    let sinks = RefCell::new(sinks);
    let published = |sinks: &[ShmSink]| -> u64 { sinks.iter().map(|s| s.publisher.next_seq()).sum() };

    let print_now = || side.clock(main.mcu_index).clock_at(McuLink::system_now()) / clock_freq;
    // Start far enough ahead that the first batch is planned long before it is due.
    let start = print_now() + (0.5f64).max(0.25 * scale);
    // Buffering window in print time: 2 s, or 1 s of wall time when the clock runs faster.
    let high_water = (2.0f64).max(1.0 * scale);
    let low_water = high_water / 2.0;
    let pace = Duration::from_millis(5);

    let streams = StepStreams::new(machine, &params)?;
    let maps = streams.clock_maps(|i| side.clock(i))?;
    let mut pipeline = Pipeline::with_clocks(
        machine.pipeline_config(clock_freq, args.max_error_us * 1e-6),
        start,
        machine.options,
        &maps,
    )
    .map_err(|e| e.to_string())?;
    let streams = RefCell::new(streams);
    // Each stream's MCU clock now (reused: no allocation per batch).
    let mut now_clocks = vec![0.0f64; params.len()];
    // Allocation counter and batches published when the pipeline first reached high water
    // (warm-up: every buffer has seen a full window), and the allocations of homing/probing
    // commands after that (not the streaming loop: counted apart).
    let warm: Cell<Option<(AllocCounter, u64)>> = Cell::new(None);
    let motions = Cell::new((0u64, 0u64));
    let homing_reports = RefCell::new(Vec::new());
    log.log(
        Level::Info,
        "planner started: start print time s, high water s, step streams",
        [Arg::F(start), Arg::F(high_water), Arg::U(params.len() as u64)],
    );
    let mut accessories = Accessories::new(machine.real_board);
    let lines = plan_file(
        args,
        &mut pipeline,
        gcode,
        &mut accessories,
        |cmds| {
            let mut streams = streams.borrow_mut();
            let mut sinks = sinks.borrow_mut();
            let now = McuLink::system_now();
            for (c, m) in now_clocks.iter_mut().zip(&streams.mcus) {
                *c = side.clock(m.mcu_index).clock_at(now);
            }
            for &(idx, cmd) in cmds.iter() {
                if let StepCmd::QueueStep { first_clock, .. } = cmd {
                    let k = streams.stream_of(idx).unwrap_or(0);
                    let freq = streams.mcus[k].clock_freq;
                    let now_clock = now_clocks[k];
                    if (first_clock as f64) < now_clock + MIN_LEAD_S * freq {
                        let ahead_ms = (first_clock as f64 - now_clock) / freq * 1e3;
                        log.log(
                            Level::Error,
                            "planner fell behind: stepper index, ms before due",
                            [Arg::U(idx as u64), Arg::F(ahead_ms)],
                        );
                        return Err(format!(
                            "the planner fell behind: a step for {} on mcu '{}' at its clock {first_clock} was \
                             ready only {ahead_ms:.1} ms before it is due (at least {:.0} ms required); print \
                             stopped before sending it",
                            machine.steppers[idx].name,
                            streams.mcus[k].name,
                            MIN_LEAD_S * 1e3
                        ));
                    }
                }
                streams.push(idx, cmd, &mut sinks[..])?;
            }
            sinks.iter_mut().try_for_each(ShmSink::flush)
        },
        |p| {
            // The next batch is planned with the MCUs' latest clock fits.
            streams.borrow().refresh_clocks(p, |i| side.clock(i))?;
            // Flow control: keep between the low and high water marks of buffered print time.
            if p.planned_until() - print_now() > high_water {
                if warm.get().is_none() {
                    warm.set(Some((AllocCounter::snapshot(), published(&sinks.borrow()[..]))));
                    crate::allocsites::start_if_requested();
                }
                log.log(
                    Level::Debug,
                    "flow control: buffered print time s, waiting down to s",
                    [Arg::F(p.planned_until() - print_now()), Arg::F(low_water)],
                );
                while p.planned_until() - print_now() > low_water {
                    side.check()?;
                    let t = Instant::now();
                    std::thread::sleep(pace);
                    if let Ok(mut h) = hists.wake_planner.try_lock() {
                        h.record(t.elapsed().saturating_sub(pace).as_nanos() as u64);
                    }
                }
            }
            side.check()
        },
        |pipeline, cmd| {
            if machine.endstops.is_empty() && machine.probe.is_none() {
                return Ok(false);
            }
            let McuSide::Local(mcus) = side else {
                let what = match cmd {
                    MotionCmd::Home(_) => "homing needs",
                    MotionCmd::Probe { .. } => "probing needs",
                };
                return Err(format!(
                    "{what} the in-process IO stage (triggers are relayed through the MCU link): \
                     print without --io-process/--io-attach"
                ));
            };
            let motion_start = AllocCounter::snapshot();
            // Drain the shared-memory hand-offs: everything planned so far must be in the links
            // before homing talks to the MCUs directly.
            let targets: Vec<u64> = {
                let mut sinks = sinks.borrow_mut();
                sinks.iter_mut().try_for_each(ShmSink::flush)?;
                sinks.iter().map(|s| s.publisher.next_seq()).collect()
            };
            let deadline = Instant::now() + Duration::from_secs(10);
            while consumed
                .iter()
                .zip(&targets)
                .any(|(c, &t)| c.load(Ordering::Acquire) < t)
            {
                if Instant::now() > deadline {
                    return Err("the IO stages did not take the planned steps before homing".to_string());
                }
                mcus.check()?;
                std::thread::sleep(Duration::from_millis(1));
            }
            let mut streams = streams.borrow_mut();
            let mut direct = crate::homing::direct_sinks(&streams, mcus);
            let mut ctx = HomingCtx::new(mcus, machine, pipeline, &mut streams, &mut direct, scale, rt);
            if let MotionCmd::Home(axes) = cmd {
                log.log(
                    Level::Info,
                    "homing axes x, y, z",
                    [
                        Arg::U(axes[0] as u64),
                        Arg::U(axes[1] as u64),
                        Arg::U(axes[2] as u64),
                    ],
                );
            }
            // Formatted text is printed by the main thread with the summary.
            let mut out = Vec::new();
            let result = run_motion(&mut ctx, cmd, &mut out);
            if let (Err(_), Some(detail)) = (&result, ctx.comm_timeout_detail.take()) {
                out.push(format!("homing: communication timeout: {detail}"));
            }
            homing_reports.borrow_mut().extend(out);
            result?;
            log.log(Level::Info, "homing done", []);
            if warm.get().is_some() {
                let (allocs, n) = motions.get();
                let more = AllocCounter::snapshot().since(motion_start).allocations();
                motions.set((allocs + more, n + 1));
            }
            Ok(true)
        },
    )?;
    let mut sinks = sinks.into_inner();
    let streams = streams.into_inner();
    sinks.iter_mut().try_for_each(ShmSink::flush)?;
    let total = published(&sinks);
    // Counted before anything below allocates (the report's own vectors).
    let (motion_allocations, motion_count) = motions.get();
    let allocs = warm.get().map(|(w, seq)| AfterWarmup {
        allocations: AllocCounter::snapshot()
            .since(w)
            .allocations()
            .saturating_sub(motion_allocations),
        batches: total - seq,
        motion_allocations,
        motions: motion_count,
    });
    crate::allocsites::finish_if_requested("planner");
    let batches: Vec<u64> = sinks.iter().map(|s| s.publisher.next_seq()).collect();
    let stats = pipeline.stats();
    let summary = Summary {
        file: args.file.clone(),
        lines,
        moves: stats.moves,
        print_time: pipeline.planned_until() - start,
        wall: 0.0,
        queue_steps: streams.queue_steps(),
        rows: Vec::new(),
        clock_freq,
        mcu_freqs: params
            .iter()
            .map(|m| (m.name.to_string(), m.clock_freq))
            .collect(),
        extra: accessories
            .lines()
            .into_iter()
            .chain(homing_reports.into_inner())
            .collect(),
    };
    log.log(
        Level::Info,
        "planner done: lines, moves, queue_steps, batches",
        [
            Arg::U(lines),
            Arg::U(stats.moves),
            Arg::U(summary.queue_steps),
            Arg::U(total),
        ],
    );
    Ok((summary, pipeline, streams, allocs, batches))
}

/// Waits for every MCU to execute its last step, reads the positions back and checks them,
/// and checks every MCU's lead.
fn finish_print(
    mcus: &Mcus,
    machine: &Machine,
    pipeline: &Pipeline,
    streams: &StepStreams,
    summary: &mut Summary,
    scale: f64,
) -> Result<(), String> {
    let mcu_positions = read_final_positions(mcus, machine, &streams.end_clocks(), scale)?;
    check_positions(machine, pipeline, &streams.steps_sent(), &mcu_positions, summary)?;
    for m in &mcus.list {
        check_min_lead(&m.name, m.link.stats().min_lead_margin_ticks, m.clock_freq)?;
    }
    Ok(())
}

/// Waits (bounded) until each MCU of `ends` (MCU index, last step clock in its own clock)
/// executed everything, then reads each stepper's position back from its MCU, in machine
/// order, in the host's sign convention (dir pin inversion undone).
pub(crate) fn read_final_positions(
    mcus: &Mcus,
    machine: &Machine,
    ends: &[(usize, u64)],
    scale: f64,
) -> Result<Vec<i64>, String> {
    for &(i, end_clock) in ends {
        let Some(m) = mcus.list.get(i) else {
            continue;
        };
        let link = &m.link;
        let clock_freq = m.clock_freq;
        let now_s = || link.clock().clock_at(McuLink::system_now()) / clock_freq;
        let wait_s = (end_clock as f64 / clock_freq - now_s()).max(0.0) / scale + 5.0;
        let deadline = Instant::now() + Duration::from_secs_f64(wait_s);
        link.wait_idle(Duration::from_secs_f64(wait_s))
            .map_err(|e| format!("mcu '{}': {e}", m.name))?;
        while now_s() * clock_freq < end_clock as f64 + 0.01 * clock_freq {
            mcus.check()?;
            if Instant::now() > deadline {
                return Err(format!(
                    "mcu '{}': its clock did not reach the end of the print in time",
                    m.name
                ));
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }
    mcus.check()?;
    let mut out = Vec::with_capacity(machine.steppers.len());
    for s in &machine.steppers {
        let m = mcus
            .get(&s.mcu)
            .ok_or_else(|| format!("[{}]: mcu '{}' is not connected", s.name, s.mcu))?;
        let link = &m.link;
        let q = link
            .dictionary()
            .encode("stepper_get_position", &[s.oid as i64])
            .map_err(|e| format!("mcu '{}': {e}", m.name))?;
        // Retried: an answer lost on a noisy line is not retransmitted (the query is idempotent).
        let ask = || {
            link.query(
                q,
                "stepper_position",
                Some(("oid", s.oid as i64)),
                Duration::from_secs(1),
            )
        };
        let mut reply = ask();
        for _ in 0..3 {
            if reply.is_ok() || link.error().is_some() {
                break;
            }
            reply = ask();
        }
        let reply = reply.map_err(|e| format!("mcu '{}': [{}] position: {e}", m.name, s.name))?;
        let raw = reply.get("pos").unwrap_or(0);
        out.push(if s.dir_pin.invert { -raw } else { raw });
    }
    Ok(out)
}

/// Fills the summary's rows and fails if an MCU position differs from the host's.
/// `steps_sent` is per stepper in machine order.
pub(crate) fn check_positions(
    machine: &Machine,
    pipeline: &Pipeline,
    steps_sent: &[u64],
    mcu_positions: &[i64],
    summary: &mut Summary,
) -> Result<(), String> {
    let host_positions = pipeline.stepper_positions();
    let commanded = pipeline.position();
    for (i, s) in machine.steppers.iter().enumerate() {
        let Some(&mcu_pos) = mcu_positions.get(i) else {
            return Err(format!("{}: no position read back from the MCU", s.name));
        };
        let host_pos = host_positions.get(i).copied().unwrap_or(0);
        summary.rows.push((
            s.name.clone(),
            steps_sent.get(i).copied().unwrap_or(0),
            mcu_pos,
            host_pos,
            commanded.get(s.axis).copied().unwrap_or(0.0),
        ));
    }
    if let Some((name, _, m, h, _)) = summary.rows.iter().find(|r| r.2 != r.3) {
        let mcu = machine
            .steppers
            .iter()
            .find(|s| &s.name == name)
            .map_or("?", |s| s.mcu.as_str());
        return Err(format!(
            "{name}: mcu '{mcu}' reports position {m} steps but the host sent {h}"
        ));
    }
    Ok(())
}

/// Fails if a step command reached MCU `mcu` (clock `clock_freq`) with less than the
/// required lead.
pub(crate) fn check_min_lead(
    mcu: &str,
    min_margin_ticks: Option<i64>,
    clock_freq: f64,
) -> Result<(), String> {
    if let Some(margin) = min_margin_ticks {
        if (margin as f64) < MIN_LEAD_S * clock_freq {
            return Err(format!(
                "a step command reached mcu '{mcu}' with only {:.1} ms lead (at least {:.0} ms required)",
                margin as f64 / clock_freq * 1e3,
                MIN_LEAD_S * 1e3
            ));
        }
    }
    Ok(())
}
