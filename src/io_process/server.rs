//! `cadence serve --role io`: the IO stage in its own process.
//!
//! It owns the MCU connections (serial ports, or simulated MCUs it starts), configures the MCUs
//! from the same printer.cfg the planner loads, and then serves one print: it subscribes to the
//! step channel `cadence/<instance>/mcu/<mcu>/steps` exactly as the in-process IO stage thread
//! does and feeds the link. What the planner needs from the MCU side crosses over the services
//! of [`super::payloads`] (MCU info with the data dictionary, clock snapshots, status, control);
//! see that module for the handshake and the payload layouts.
//!
//! Threads: the IO stage (pinned, SCHED_FIFO where allowed, like in-process), the MCU links' IO
//! threads, the logger, and this process's main thread, which publishes clock snapshots every
//! [`CLOCK_PERIOD`], watches the MCUs, the planner and the IO stage, and finishes the print.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

use links::mcu::McuLink;
use rt_core::logger::{Arg, Level, LoggerHandle};
use rt_core::os::{apply_rt, RtSpec};
use rt_core::shm::{
    open_node, steps_service_name, telemetry_service_name, ChannelConfig, ShmError, ShmPublisher,
    ShmSubscriber, Telemetry,
};

use super::payloads::{
    clock_service_name, control_kind, control_service_name, info_service_name, io_state, status_service_name,
    ClockSnapshot, IoControl, IoStatus, McuInfo, STATUS_POSITIONS,
};
use super::IoProcessError;
use crate::hardware::Machine;
use crate::io_stage;
use crate::latency::{self, Hists};
use crate::logging::Logging;
use crate::mcus::Mcus;
use crate::realtime::RtConfig;

type Ipc = iceoryx2::prelude::ipc::Service;

/// How often the main thread publishes clock snapshots and checks on everything.
pub const CLOCK_PERIOD: Duration = Duration::from_millis(20);

/// How `serve` runs the IO stage.
#[derive(Debug, Clone)]
pub struct ServeOptions {
    /// Klipper-format printer.cfg (default: the built-in simulated cartesian printer); the
    /// planner must load the same one (checked through the configuration CRC).
    pub config: Option<PathBuf>,
    /// Service instance: services are named `cadence/<instance>/...` (default `p<pid>`).
    pub instance: Option<String>,
    /// Simulated MCU clock runs this many times faster than the wall clock.
    pub time_scale: Option<f64>,
    /// Write the simulated MCU's step trace to this file.
    pub trace: Option<PathBuf>,
    /// Don't pin threads, use SCHED_FIFO or lock memory.
    pub no_realtime: bool,
    /// Also write the log to this file (appended).
    pub log_file: Option<PathBuf>,
    /// Most verbose log level recorded: error, warn, info, debug or trace.
    pub log_level: Level,
    /// Stop (and fail) when the process with this pid (the planner that started us) is gone.
    pub parent_pid: Option<u32>,
    /// Fail when neither a step batch nor a command arrived for this many seconds (0: wait
    /// forever; the CLI's default is 120).
    pub idle_timeout: f64,
}

/// What `serve` reports: its lines (histograms, link statistics, allocations, log), which
/// real-time guarantees were off, and how the served print ended.
#[derive(Debug)]
pub struct ServeOutcome {
    pub report: Vec<String>,
    pub rt_report: Vec<String>,
    pub result: Result<(), IoProcessError>,
}

/// Serves one print: connects and configures the MCUs, runs the IO stage until the planner's
/// FINISH, publishes DONE. `warn` gets the printer.cfg's warnings. Errors before the MCUs are
/// connected come back as `Err`; later ones in [`ServeOutcome::result`] after the report.
pub fn run(args: &ServeOptions, warn: &mut dyn FnMut(&str)) -> Result<ServeOutcome, IoProcessError> {
    let mut cfg = crate::hardware::load_config(args.config.as_deref())?;
    for w in &cfg.warnings {
        warn(w);
    }
    let simulated = cfg.mcus.iter().any(|m| m.is_simulated());
    if args.time_scale.is_some() && !simulated {
        return Err(IoProcessError::TimeScaleNotSimulated);
    }
    let time_scale = args.time_scale.unwrap_or(cfg.simulator.time_scale);
    if !(time_scale > 0.0 && time_scale <= 50.0) {
        return Err(IoProcessError::TimeScale(time_scale));
    }
    // The run's time scale is the simulated printer's (heater safety windows follow it).
    cfg.simulator.time_scale = time_scale;
    let machine = Machine::from_config(&cfg)?;
    super::planner_side::check_single_mcu(&machine)?;
    let instance = args
        .instance
        .clone()
        .unwrap_or_else(|| format!("p{}", std::process::id()));
    let logging = Logging::start(args.log_level, args.log_file.clone())?;
    let log = logging.handle("serve");
    let (node, _) = open_node::<Ipc>(&format!("cadence-serve-{}", std::process::id()))?;
    let mut status = ShmPublisher::<Ipc, IoStatus>::open(
        &node,
        &status_service_name(&instance),
        &ChannelConfig::latest(),
    )?;
    let mut report = StatusReport {
        base: IoStatus {
            pid: std::process::id(),
            ..IoStatus::default()
        },
    };
    report.send(&mut status, io_state::STARTING, "")?;

    let rt = RtConfig::from_section(&cfg.realtime, args.no_realtime);
    let _idle_hold = rt.hold_idle_latency();
    let connected = crate::live::connect_mcus(&cfg, &machine, time_scale, args.trace.clone(), &rt, &logging);
    let (hists, mut mcus) = match connected {
        Ok(c) => c,
        Err(e) => {
            let _ = report.send(&mut status, io_state::FAILED, &e.to_string());
            return Err(e.into());
        }
    };
    let ctx = ServeCtx {
        args,
        machine: &machine,
        mcus: &mcus,
        instance: &instance,
        rt: &rt,
        hists: &hists,
        log: &log,
        scale: time_scale,
    };
    let result = serve_print(&ctx, &node, &mut status, &mut report);
    if let Err(e) = &result {
        log.log(Level::Error, "serve: the print failed", []);
        let _ = report.send(&mut status, io_state::FAILED, &e.to_string());
    }
    let stats = mcus.close();
    // The report: this process's histograms and link statistics.
    let clock_freq = machine_clock_freq(&result);
    let mut lines: Vec<String> = hists
        .report(clock_freq)
        .into_iter()
        .map(|l| format!("  io: {l}"))
        .collect();
    for (name, s) in &stats {
        lines.push(format!("  io: mcu '{name}': {s}"));
    }
    if let Ok(io) = &result {
        lines.push(format!(
            "  io: stage took {} batches; allocations after warm-up: {}",
            io.batches,
            io.allocations_after_warmup
                .map_or("n/a".to_string(), |n| n.to_string())
        ));
    }
    lines.push(format!("  io: {}", logging.finish()));
    Ok(ServeOutcome {
        report: lines,
        rt_report: rt_core::os::rt_report(),
        result: result.map(|_| ()),
    })
}

/// The clock frequency the served print used (for the report's ms figures).
fn machine_clock_freq(result: &Result<ServedReport, IoProcessError>) -> f64 {
    match result {
        Ok(r) => r.clock_freq,
        Err(_) => 50e6,
    }
}

/// What `serve_print` reports.
#[derive(Debug)]
struct ServedReport {
    batches: u64,
    allocations_after_warmup: Option<u64>,
    clock_freq: f64,
}

/// Publishes status changes on top of a base record.
#[derive(Debug)]
struct StatusReport {
    base: IoStatus,
}

impl StatusReport {
    fn send(
        &mut self,
        publisher: &mut ShmPublisher<Ipc, IoStatus>,
        state: u32,
        msg: &str,
    ) -> Result<(), IoProcessError> {
        self.base.state = state;
        self.base.set_msg(msg);
        let s = self.base;
        publisher
            .send_with(|p| {
                let seq = p.seq;
                *p = s;
                p.seq = seq;
            })
            .map(|_| ())
            .map_err(IoProcessError::Status)
    }
}

struct ServeCtx<'a> {
    args: &'a ServeOptions,
    machine: &'a Machine,
    mcus: &'a Mcus,
    instance: &'a str,
    rt: &'a RtConfig,
    hists: &'a Arc<Hists>,
    log: &'a LoggerHandle,
    scale: f64,
}

/// Publishes each MCU's info (kept as history) and opens its clock publisher.
fn open_info_and_clocks(
    ctx: &ServeCtx<'_>,
    node: &iceoryx2::node::Node<Ipc>,
) -> Result<Publishers, IoProcessError> {
    let mut infos = Vec::new();
    let mut clocks = Vec::new();
    for (i, m) in ctx.mcus.list.iter().enumerate() {
        let dict = m.link.dictionary();
        let crc = super::planner_side::config_crc(dict, ctx.machine, &m.name)?;
        let mut p = ShmPublisher::<Ipc, McuInfo>::open(
            node,
            &info_service_name(ctx.instance, &m.name),
            &ChannelConfig::info(),
        )?;
        let compressed = dict.compressed();
        let mut fits = true;
        p.send_with(|info| {
            info.clock_freq = m.clock_freq;
            info.move_count = m.move_count as u32;
            info.config_crc = crc;
            info.mcu_index = i as u32;
            fits = info.set_dict(compressed);
        })?;
        if !fits {
            return Err(IoProcessError::DictionaryTooLarge {
                mcu: m.name.clone(),
                bytes: compressed.len(),
            });
        }
        infos.push(p);
        let c = ShmPublisher::<Ipc, ClockSnapshot>::open(
            node,
            &clock_service_name(ctx.instance, &m.name),
            &ChannelConfig::latest(),
        )?;
        clocks.push(c);
    }
    Ok((infos, clocks))
}

/// The info and clock publishers, one each per MCU.
type Publishers = (
    Vec<ShmPublisher<Ipc, McuInfo>>,
    Vec<ShmPublisher<Ipc, ClockSnapshot>>,
);

/// Publishes every MCU's clock fit now.
fn publish_clocks(mcus: &Mcus, clocks: &mut [ShmPublisher<Ipc, ClockSnapshot>]) -> Result<(), ShmError> {
    let now = McuLink::system_now();
    for (m, p) in mcus.list.iter().zip(clocks.iter_mut()) {
        let est = m.link.clock();
        p.send_with(|c| {
            c.ref_time = now;
            c.ref_clock = est.clock_at(now);
            c.freq = est.freq();
            c.residual_us = est.residual_us();
            c.valid = est.is_valid() as u32;
        })?;
    }
    Ok(())
}

/// Waits until the main MCU executed the last step, reads the stepper positions back and
/// fills the `DONE` status with them and the link's lead figures.
fn fill_done(
    ctx: &ServeCtx<'_>,
    end_clock: u64,
    batches: u64,
    report: &mut StatusReport,
) -> Result<(), IoProcessError> {
    let positions = crate::live::read_final_positions(ctx.mcus, ctx.machine, &[(0, end_clock)], ctx.scale)?;
    if positions.len() > STATUS_POSITIONS {
        return Err(IoProcessError::TooManySteppers(positions.len()));
    }
    let stats = ctx.mcus.main().link.stats();
    report.base.batches = batches;
    report.base.clocked_msgs = stats.clocked_msgs;
    report.base.min_lead_margin_ticks = stats.min_lead_margin_ticks.unwrap_or(i64::MIN);
    report.base.npos = positions.len() as u32;
    report.base.positions[..positions.len()].copy_from_slice(&positions);
    Ok(())
}

/// Publishes the MCU info and clocks, runs the IO stage thread for the main MCU until the
/// planner's FINISH, then reads the final positions back and publishes DONE.
fn serve_print(
    ctx: &ServeCtx<'_>,
    node: &iceoryx2::node::Node<Ipc>,
    status: &mut ShmPublisher<Ipc, IoStatus>,
    report: &mut StatusReport,
) -> Result<ServedReport, IoProcessError> {
    let mcus = ctx.mcus;
    let main = mcus.main();
    let clock_freq = main.clock_freq;
    let mut chans = open_chans(ctx, node)?;
    let service = steps_service_name(ctx.instance, &main.name);
    let service = service.as_str();
    let done_flag = AtomicBool::new(false);
    let consumed_count = AtomicU64::new(0);
    let (done, consumed) = (&done_flag, &consumed_count);
    let link = &main.link;
    let hists = ctx.hists;
    let started = Instant::now();

    std::thread::scope(|scope| {
        let (ready_tx, ready_rx) = mpsc::channel();
        let io_spec: RtSpec = ctx.rt.io_spec(&main.name);
        let io_log = ctx.log.with_tag("io");
        let io = std::thread::Builder::new()
            .name(io_spec.name.clone())
            .spawn_scoped(scope, move || {
                apply_rt(&io_spec);
                io_stage::io_stage(
                    link, service, ready_tx, done, consumed, hists, clock_freq, &io_log,
                )
            })
            .map_err(|source| IoProcessError::Thread {
                what: "IO stage thread",
                source,
            })?;
        let stop_io =
            |io: std::thread::ScopedJoinHandle<'_, Result<io_stage::IoReport, io_stage::IoStageError>>| {
                done.store(true, Ordering::Release);
                match io.join() {
                    Ok(r) => r.map_err(IoProcessError::from),
                    Err(_) => Err(IoProcessError::Panicked {
                        what: "IO stage thread",
                    }),
                }
            };
        match ready_rx.recv_timeout(Duration::from_secs(10)) {
            Ok(Ok(())) => {}
            Ok(Err(e)) => return Err(IoProcessError::IoStageStart(e)),
            Err(_) => return Err(IoProcessError::IoStageTimeout),
        }
        report.send(status, io_state::READY, "")?;
        ctx.log.log(Level::Info, "serve: ready", []);

        let mut watch = Watch::new(ctx.args.idle_timeout, started);
        loop {
            std::thread::sleep(CLOCK_PERIOD);
            let turn = watch.turn(
                ctx,
                &mut chans,
                status,
                consumed.load(Ordering::Acquire),
                report,
                io.is_finished(),
            );
            match turn {
                Ok(Turn::Go) => {}
                Ok(Turn::Finish(f)) => {
                    let io_report = stop_io(io)?;
                    let end = Served {
                        status: &mut *status,
                        report: &mut *report,
                        chans: &mut chans,
                        started,
                    };
                    return end.finish(ctx, &f, &io_report, clock_freq);
                }
                Ok(Turn::IoEnded) => {
                    // The IO stage only ends on its own with an error (or after `done`).
                    return Err(match stop_io(io) {
                        Err(e) => e,
                        Ok(_) => IoProcessError::IoStageEnded,
                    });
                }
                // Every other end stops the IO stage first (the scope joins it).
                Ok(Turn::Stop(e)) | Err(e) => {
                    let _ = stop_io(io);
                    return Err(e);
                }
            }
        }
    })
}

/// The ends of a served print the planner reads its outcome from.
struct Served<'a> {
    status: &'a mut ShmPublisher<Ipc, IoStatus>,
    report: &'a mut StatusReport,
    chans: &'a mut Chans,
    started: Instant,
}

impl Served<'_> {
    /// The planner's FINISH (`f`) with every batch taken: waits for the MCU, publishes DONE
    /// with the final positions and the last telemetry, and keeps DONE until it was read.
    fn finish(
        self,
        ctx: &ServeCtx<'_>,
        f: &IoControl,
        io_report: &io_stage::IoReport,
        clock_freq: f64,
    ) -> Result<ServedReport, IoProcessError> {
        ctx.log.log(
            Level::Info,
            "serve: all batches taken, waiting for the MCU: batches, end clock",
            [Arg::U(f.batches), Arg::U(f.end_clock)],
        );
        fill_done(ctx, f.end_clock, io_report.batches, self.report)?;
        self.report.send(self.status, io_state::DONE, "")?;
        ctx.hists.publish(
            &mut self.chans.telemetry,
            self.started.elapsed().as_nanos() as u64,
            latency::LEAD_SOURCE,
        );
        ctx.log.log(Level::Info, "serve: print done", []);
        // Keep the DONE sample alive until the planner has read it.
        wait_for_ack(&mut self.chans.control, ctx.log);
        Ok(ServedReport {
            batches: io_report.batches,
            allocations_after_warmup: io_report.allocations_after_warmup,
            clock_freq,
        })
    }
}

/// Publishes the MCU info and the first clocks, opens the control and telemetry channels.
fn open_chans(ctx: &ServeCtx<'_>, node: &iceoryx2::node::Node<Ipc>) -> Result<Chans, IoProcessError> {
    let (infos, mut clocks) = open_info_and_clocks(ctx, node)?;
    publish_clocks(ctx.mcus, &mut clocks)?;
    let control = ShmSubscriber::<Ipc, IoControl>::open(
        node,
        &control_service_name(ctx.instance),
        &ChannelConfig::control(),
    )?;
    let telemetry = ShmPublisher::<Ipc, Telemetry>::open(
        node,
        &telemetry_service_name(ctx.instance),
        &ChannelConfig::telemetry(),
    )?;
    Ok(Chans {
        infos,
        clocks,
        control,
        telemetry,
    })
}

/// The channels the serve loop keeps up besides the status.
struct Chans {
    infos: Vec<ShmPublisher<Ipc, McuInfo>>,
    clocks: Vec<ShmPublisher<Ipc, ClockSnapshot>>,
    control: ShmSubscriber<Ipc, IoControl>,
    telemetry: ShmPublisher<Ipc, Telemetry>,
}

/// What one turn of the serve loop found.
enum Turn {
    /// Nothing ends the print yet.
    Go,
    /// The planner's FINISH, and the IO stage has taken all its batches.
    Finish(IoControl),
    /// The IO stage thread ended on its own.
    IoEnded,
    /// The print must end: the reason.
    Stop(IoProcessError),
}

/// The serve loop's memory between turns.
struct Watch {
    idle_limit: Option<Duration>,
    started: Instant,
    last_activity: Instant,
    last_consumed: u64,
    last_telemetry: Instant,
    finish: Option<IoControl>,
}

impl Watch {
    fn new(idle_timeout: f64, started: Instant) -> Watch {
        Watch {
            idle_limit: (idle_timeout > 0.0).then(|| Duration::from_secs_f64(idle_timeout)),
            started,
            last_activity: Instant::now(),
            last_consumed: 0,
            last_telemetry: Instant::now(),
            finish: None,
        }
    }

    /// One turn: publishes the clocks (and telemetry each second), lets new subscribers
    /// connect, then checks the MCUs, the IO stage, the planner's commands, its process and
    /// the idle limit. `consumed`: batches the IO stage has taken so far.
    fn turn(
        &mut self,
        ctx: &ServeCtx<'_>,
        chans: &mut Chans,
        status: &mut ShmPublisher<Ipc, IoStatus>,
        consumed: u64,
        report: &mut StatusReport,
        io_finished: bool,
    ) -> Result<Turn, IoProcessError> {
        publish_clocks(ctx.mcus, &mut chans.clocks)?;
        // New subscribers get the history (info, status) when the publisher connects.
        for p in &chans.infos {
            p.connect()?;
        }
        status.connect()?;
        if self.last_telemetry.elapsed() >= Duration::from_secs(1) {
            self.last_telemetry = Instant::now();
            ctx.hists.publish(
                &mut chans.telemetry,
                self.started.elapsed().as_nanos() as u64,
                latency::LEAD_SOURCE,
            );
        }
        if let Err(e) = ctx.mcus.check() {
            return Ok(Turn::Stop(e.into()));
        }
        if io_finished {
            return Ok(Turn::IoEnded);
        }
        while let Some(c) = chans.control.try_recv_with(|c| *c)? {
            self.last_activity = Instant::now();
            match c.kind {
                control_kind::FINISH => self.finish = Some(c),
                control_kind::ABORT => return Ok(stop("the planner aborted the print".to_string())),
                _ => {}
            }
        }
        if consumed != self.last_consumed {
            self.last_consumed = consumed;
            self.last_activity = Instant::now();
            report.base.batches = consumed;
        }
        if let Some(f) = self.finish.filter(|f| consumed >= f.batches) {
            return Ok(Turn::Finish(IoControl {
                batches: consumed,
                ..f
            }));
        }
        if let Some(pid) = ctx.args.parent_pid {
            if !std::path::Path::new(&format!("/proc/{pid}")).exists() {
                return Ok(stop(format!("the planner process {pid} is gone")));
            }
        }
        if let Some(limit) = self.idle_limit.filter(|l| self.last_activity.elapsed() > *l) {
            return Ok(stop(format!(
                "no step batch or command from a planner for {:.0} s",
                limit.as_secs_f64()
            )));
        }
        Ok(Turn::Go)
    }
}

/// The serve loop's end for `reason`.
fn stop(reason: String) -> Turn {
    Turn::Stop(IoProcessError::Stop { reason })
}

/// Waits (bounded) for the planner's `DONE_SEEN`, so the final status outlives this process's
/// publisher long enough to be read.
fn wait_for_ack(control: &mut ShmSubscriber<Ipc, IoControl>, log: &LoggerHandle) {
    let deadline = Instant::now() + ACK_TIMEOUT;
    while Instant::now() < deadline {
        match control.recv_timeout_with(CLOCK_PERIOD, |c| c.kind) {
            Ok(Some(control_kind::DONE_SEEN)) => return,
            Ok(_) => {}
            Err(_) => break,
        }
    }
    log.log(
        Level::Warn,
        "serve: the planner did not acknowledge the final status",
        [],
    );
}

/// Longest wait for the planner's acknowledgement of `DONE`.
const ACK_TIMEOUT: Duration = Duration::from_secs(10);
