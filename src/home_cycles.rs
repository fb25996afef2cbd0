//! Homing cycles with latency figures (`cadence home`): homes the printer (default: the built-in simulated one) with real motion,
//! once or `--cycles N` times (each cycle first moves the homed axes `--away` mm off their
//! endstops), and reports the homed position, the overshoot and trigger → stop latencies.
//!
//! Latencies, per homing pass:
//! - host view (always): the last executed step and the first cancelled step of the axis
//!   stepper, from the move profile and the MCU's step count, minus the endstop's trigger time;
//! - trace view (with `--trace`, for an axis whose endstop is on another MCU than its steppers):
//!   the stepper MCU's trsync trigger record (the moment its steppers stopped) and its last step
//!   record, minus the endstop MCU's trigger record, each converted to system time with the
//!   clock epoch the simulator wrote next to its trace (both count CLOCK_MONOTONIC: exact), or
//!   else with the host's clock estimate of that MCU (a fit: off by up to a millisecond over
//!   long runs). Pairing: each endstop
//!   trigger with the first unused stop on the stepper MCU at or after it (−5 ms tolerance).
//! - trace view, per hop of the relay (with `--trace`): endstop MCU trigger → the host read its
//!   `trsync_state` ([`links::trsync::TriggerOutcome::received_at`]) → the host wrote
//!   `trsync_trigger` to the stepper MCU's link ([`links::trsync::TriggerGroup::trigger_written_at`])
//!   → the stepper MCU's trsync trigger record. Each pass is paired with the latest endstop
//!   trigger at or before its read time (+5 ms tolerance); per pass the three hops add up to
//!   its trigger → stop latency exactly. The 5 slowest passes are listed with their hops.
//!
//! Figures are µs of system time (MCU time when the simulator's time scale is 1).
//!
//! Noise floor: a cyclictest-like sleeper ([`rt_core::wakeup`], 1 ms sleeps at the IO threads'
//! priority, any core) runs for the whole bench; its wake-up latency is printed with the
//! p99.9 trigger → stop latencies as multiples of its p99.9, the figure to compare between
//! runs on a machine whose own timing noise varies (a VM).
//!
//! Idle polling: with `[realtime] idle_poll_homing: True` every homing pass runs with the idle
//! CPUs polling ([`rt_core::os::IdlePoll`]), as in a print; the summary line says whether it
//! was on. The sleeper's figure covers the whole run, passes and the moves between them.
//!
//! Threads: like a live print, with printer.cfg's `[realtime]` (unless `--no-realtime`): the
//! links' IO threads (they relay the trigger) pinned to the IO core under SCHED_FIFO, this
//! thread (planning, waiting) as the planner, the simulated MCUs SCHED_FIFO below them.
//! `--cpu-load` adds one SCHED_OTHER busy-spinning thread per core for the whole run (started
//! before any real-time setting, so they inherit none), stopped at the end.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Instant;

use links::clocksync::ClockEstimate;
use planner::pipeline::{Pipeline, PipelineOptions};
use rt_core::hist::LatencyHist;
use rt_core::wakeup::{WakeupProbe, WakeupReport};

use crate::hardware::{HardwareError, Machine};
use crate::homing::{plain_move, print_now, HomingCtx, HomingError, HomingReport, AXIS_NAMES};
use crate::mcus::{trace_path, ConnectOptions, McuError, Mcus};
use crate::realtime::RtConfig;
use crate::step_stream::{StepStreams, StreamError};

/// Why `cadence home` stopped.
#[derive(Debug, thiserror::Error)]
pub enum HomeCyclesError {
    /// `--away` is not a positive distance.
    #[error("--away {0}: must be > 0")]
    Away(f64),
    /// `--time-scale` is out of range.
    #[error("--time-scale {0}: must be in (0, 50]")]
    TimeScale(f64),
    /// printer.cfg could not be read or describes no printer Cadence can home.
    #[error(transparent)]
    Config(#[from] HardwareError),
    /// A `--cpu-load` thread did not start.
    #[error("--cpu-load: cannot start a hog thread: {0}")]
    HogThread(#[source] std::io::Error),
    /// The wake-up latency probe did not start.
    #[error("cannot start the wake-up probe thread: {0}")]
    ProbeThread(#[source] std::io::Error),
    /// An MCU did not connect, configure or keep running.
    #[error(transparent)]
    Mcu(#[from] McuError),
    /// The step streams could not be set up.
    #[error(transparent)]
    Stream(#[from] StreamError),
    /// The planner could not be set up.
    #[error(transparent)]
    Plan(#[from] planner::machine::PlanError),
    /// A homing pass or move failed (the wiring check too).
    #[error(transparent)]
    Homing(Box<HomingError>),
    /// After the cycles the MCU and the host disagree on a stepper's position.
    #[error("{stepper}: the MCU reports position {mcu} steps but the host counts {host:?}")]
    Position {
        stepper: String,
        mcu: i64,
        host: Option<i64>,
    },
    /// A simulated MCU's trace could not be read.
    #[error("{}: {source}", .path.display())]
    Trace {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

from_boxed!(HomeCyclesError, Homing, HomingError);

/// The CLI's view (the message as shown).
impl From<HomeCyclesError> for String {
    fn from(e: HomeCyclesError) -> String {
        e.to_string()
    }
}

/// What `cadence home` runs.
#[derive(Debug, Clone)]
pub struct HomeOptions {
    /// Klipper-format printer.cfg (`None`: the built-in simulated cartesian printer).
    pub config: Option<PathBuf>,
    /// Axes to home (X, Y, Z).
    pub axes: [bool; 3],
    /// Homing cycles; before each one after the first, the axes move `away` mm off their
    /// endstops.
    pub cycles: u32,
    /// Distance (mm) the axes move off their endstops between cycles.
    pub away: f64,
    /// Load every core with a SCHED_OTHER busy-spinning thread while homing.
    pub cpu_load: bool,
    /// Simulated MCU clocks run this many times faster than the wall clock.
    pub time_scale: Option<f64>,
    /// Step traces of the simulated MCUs.
    pub trace: Option<PathBuf>,
    /// Maximum step time error of the compression (µs).
    pub max_error_us: f64,
    /// Don't pin threads, use SCHED_FIFO or lock memory.
    pub no_realtime: bool,
}

/// Where the report goes: `out` the report lines (stdout in the CLI), `err` the warnings and
/// notes (stderr).
pub trait HomeOutput {
    fn out(&mut self, line: String);
    fn err(&mut self, line: String);
}

/// One SCHED_OTHER busy-spinning thread per core; stopped and joined when dropped.
struct CpuHogs {
    stop: Arc<AtomicBool>,
    threads: Vec<JoinHandle<()>>,
}

impl CpuHogs {
    /// Must run before this thread gets any real-time setting: new threads inherit it.
    fn start(n: usize) -> Result<CpuHogs, HomeCyclesError> {
        let stop = Arc::new(AtomicBool::new(false));
        let mut hogs = CpuHogs {
            stop: stop.clone(),
            threads: Vec::with_capacity(n),
        };
        for i in 0..n {
            let stop = stop.clone();
            let t = std::thread::Builder::new()
                .name(format!("cpu-hog-{i}"))
                .spawn(move || {
                    while !stop.load(Ordering::Relaxed) {
                        std::hint::spin_loop();
                    }
                })
                .map_err(HomeCyclesError::HogThread)?;
            hogs.threads.push(t);
        }
        Ok(hogs)
    }
}

impl Drop for CpuHogs {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

/// The host's timestamps of one homing pass (system time, `CLOCK_MONOTONIC` seconds).
#[derive(Debug, Clone, Copy)]
struct PassTiming {
    /// 1-based.
    cycle: u32,
    /// 1-based, within the axis' homing.
    pass: usize,
    axis: usize,
    /// The host read the trigger's report.
    received: f64,
    /// The host wrote `trsync_trigger` to the steppers' MCU (`None`: same MCU as the trigger).
    written: Option<f64>,
}

/// Sleep period of the wake-up probe (the machine's noise floor during the run).
const WAKEUP_PERIOD: std::time::Duration = std::time::Duration::from_millis(1);

/// What a run of cycles measured, for a caller that reports it its own way (`cadence bench
/// homing`).
#[derive(Debug)]
pub struct CycleFigures {
    /// The report of every cycle that homed (a cycle with a communication timeout has none).
    pub reports: Vec<HomingReport>,
    /// Cycles that ended in a communication timeout.
    pub timeouts: u32,
    /// The machine's wake-up latency meanwhile (1 ms sleeps at the IO threads' priority).
    pub noise: WakeupReport,
    /// Simulated MCU clocks ran this many times faster than the wall clock (pass latencies
    /// are print time).
    pub time_scale: f64,
    /// Each homed axis's trigger → stop from the simulated MCUs' traces (with a trace).
    pub trace_stops: Vec<TraceStops>,
}

/// Homes `cycles` times and reports as it goes (see the module docs).
pub fn run(args: &HomeOptions, o: &mut dyn HomeOutput) -> Result<(), HomeCyclesError> {
    run_figures(args, o).map(|_| ())
}

/// The options clap cannot check: `--away` above 0, `--time-scale` in (0, 50].
fn check_options(args: &HomeOptions) -> Result<(), HomeCyclesError> {
    if !(args.away.is_finite() && args.away > 0.0) {
        return Err(HomeCyclesError::Away(args.away));
    }
    if let Some(scale) = args.time_scale {
        if !(scale > 0.0 && scale <= 50.0) {
            return Err(HomeCyclesError::TimeScale(scale));
        }
    }
    Ok(())
}

/// The report's line on the threads: real time, this thread's pinning and priority (`got`),
/// the links' IO threads' and the CPU load.
fn threads_line(
    rt: &RtConfig,
    got: &rt_core::os::RtApplied,
    link_spec: &rt_core::os::RtSpec,
    hogs: Option<&CpuHogs>,
) -> String {
    format!(
        "threads: real time {} (this thread pinned={} fifo={}, links' IO threads on core {} at \
         SCHED_FIFO {}); cpu load: {}",
        if rt.enabled { "on" } else { "off" },
        got.pinned,
        got.fifo,
        link_spec.core.map_or("any".to_string(), |c| c.to_string()),
        link_spec.fifo_priority.map_or("-".to_string(), |p| p.to_string()),
        match hogs {
            Some(h) => format!("on ({} SCHED_OTHER spinning threads)", h.threads.len()),
            None => "off".to_string(),
        }
    )
}

/// [`run`], returning what it measured.
pub fn run_figures(args: &HomeOptions, o: &mut dyn HomeOutput) -> Result<CycleFigures, HomeCyclesError> {
    let axes = args.axes;
    check_options(args)?;
    let cfg = crate::hardware::load_config(args.config.as_deref())?;
    for w in &cfg.warnings {
        o.err(format!("warning: {w}"));
    }
    let machine = Machine::from_config(&cfg)?;
    crate::homing::check_config(&machine)?;
    let time_scale = args.time_scale.unwrap_or(cfg.simulator.time_scale);
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let hogs = if args.cpu_load {
        Some(CpuHogs::start(cores)?)
    } else {
        None
    };
    let rt = RtConfig::from_section(&cfg.realtime, args.no_realtime);
    let _idle_hold = rt.hold_idle_latency();
    // Before this thread is pinned (the core count would then be 1).
    let link_spec = rt.link_spec();
    let opts = ConnectOptions {
        time_scale,
        trace: args.trace.clone(),
        lead_hooks: None,
        io_rt: Some(link_spec.clone()),
    };
    let mut mcus = Mcus::connect(&cfg, &machine, opts)?;
    // The machine's noise floor meanwhile, at the IO threads' priority; started before this
    // thread is pinned, so the sleeper may run on any core.
    let probe =
        WakeupProbe::start(WAKEUP_PERIOD, link_spec.fifo_priority).map_err(HomeCyclesError::ProbeThread)?;
    // After the simulated MCUs were spawned (they would inherit this thread's core).
    let got = rt_core::os::apply_rt(&rt.planner_spec());
    o.out(threads_line(&rt, &got, &link_spec, hogs.as_ref()));
    let clocks: Vec<(String, ClockEstimate)> = mcus
        .list
        .iter()
        .map(|m| (m.name.clone(), m.link.clock()))
        .collect();
    let result = cycles(args, o, &machine, &mcus, axes, time_scale, &rt);
    let noise = probe.finish();
    // Fresh estimates for the trace conversion (the fit keeps improving).
    let clocks: Vec<(String, ClockEstimate)> = mcus
        .list
        .iter()
        .map(|m| (m.name.clone(), m.link.clock()))
        .chain(clocks)
        .collect();
    let trsyncs: Vec<(String, u8)> = mcus.list.iter().map(|m| (m.name.clone(), m.trsync_oid)).collect();
    let main_name = mcus.main().name.clone();
    mcus.close();
    drop(hogs);
    for line in rt_core::os::rt_report() {
        o.err(line);
    }
    let (timings, host_p999, reports, timeouts) = result?;
    o.out(format!(
        "  machine wake-up latency meanwhile ({} ms sleeps, {}): {}",
        noise.period.as_secs_f64() * 1e3,
        if noise.fifo { "SCHED_FIFO" } else { "SCHED_OTHER" },
        noise.hist.summary().format_latency()
    ));
    if let Some(r) = noise.ratio_to_p999(host_p999) {
        o.out(format!(
            "  host view, last executed step after trigger p99.9 = {r:.1} x the wake-up p99.9"
        ));
    }
    let mut trace_stops = Vec::new();
    if let Some(base) = &args.trace {
        let trace_mcus = TraceMcus {
            main: main_name,
            trsyncs,
            clocks,
        };
        trace_stops = trace_latency(&machine, axes, base, &trace_mcus, &timings, &noise, o)?;
    }
    Ok(CycleFigures {
        reports,
        timeouts,
        noise,
        time_scale,
        trace_stops,
    })
}

/// Moves the homed axes `away` mm off their endstops (inside their travel).
fn move_away(
    ctx: &mut HomingCtx<'_>,
    machine: &Machine,
    axes: [bool; 3],
    away: f64,
) -> Result<(), HomingError> {
    let mut pos = ctx.pipeline.position();
    for e in (machine.endstops.iter()).filter(|e| axes[e.axis] && e.motor.is_none()) {
        let dir = if e.homing_positive_dir { 1.0 } else { -1.0 };
        pos[e.axis] = (e.position_endstop - dir * away).clamp(e.position_min, e.position_max);
    }
    let speed = machine.endstops.first().map_or(10.0, |e| e.homing_speed);
    plain_move(ctx, pos, speed)
}

/// Once everything executed, the host and the MCU agree on every stepper position.
fn check_positions(ctx: &mut HomingCtx<'_>, machine: &Machine) -> Result<(), HomeCyclesError> {
    crate::homing::wait_motion_done(ctx)?;
    let host = ctx.pipeline.stepper_positions();
    for (i, s) in machine.steppers.iter().enumerate() {
        let mcu_pos = crate::homing::stepper_position(ctx, i)?;
        if host.get(i) != Some(&mcu_pos) {
            return Err(HomeCyclesError::Position {
                stepper: s.name.clone(),
                mcu: mcu_pos,
                host: host.get(i).copied(),
            });
        }
    }
    Ok(())
}

/// Homes `cycles` times and prints the reports and the host-view histograms; returns the
/// host's timestamps of every successful pass, the host view's p99.9 (ns) of the last
/// executed step after the trigger, every successful cycle's report and the timeouts.
fn cycles(
    args: &HomeOptions,
    o: &mut dyn HomeOutput,
    machine: &Machine,
    mcus: &Mcus,
    axes: [bool; 3],
    scale: f64,
    rt: &RtConfig,
) -> Result<(Vec<PassTiming>, f64, Vec<HomingReport>, u32), HomeCyclesError> {
    let main = mcus.main();
    let start = print_now(mcus) + (0.5f64).max(0.25 * scale);
    let mut streams = StepStreams::new(machine, &mcus.stream_params(machine))?;
    let maps = streams.clock_maps(|i| {
        mcus.list
            .get(i)
            .map_or(ClockEstimate::INVALID, |m| m.link.clock())
    })?;
    let mut pipeline = Pipeline::with_clocks(
        machine.pipeline_config(main.clock_freq, args.max_error_us * 1e-6),
        start,
        // The printer's kinematics; no pressure advance and no worker threads (homing plans
        // inline, and nothing extrudes here).
        PipelineOptions {
            kinematics: machine.options.kinematics,
            ..PipelineOptions::default()
        },
        &maps,
    )?;
    let mut sinks = crate::homing::direct_sinks(&streams, mcus);
    let mut ctx = HomingCtx::new(mcus, machine, &mut pipeline, &mut streams, &mut sinks, scale, rt);
    let mut last_step = LatencyHist::new();
    let mut next_step = LatencyHist::new();
    let mut overshoot = LatencyHist::new();
    let mut timings = Vec::new();
    let started = Instant::now();
    let mut last_report = HomingReport::default();
    let mut timeouts = 0u32;
    let mut reports = Vec::new();
    let mut failed_last = false;
    for cycle in 0..args.cycles {
        // After a failed cycle the axis is not homed: its position is unknown, so no away move.
        if cycle > 0 && !failed_last {
            move_away(&mut ctx, machine, axes, args.away)?;
        }
        // A communication timeout is an outcome to count here, not the end of the bench (the
        // planner was resynced to where the steppers stopped; the next cycle homes again).
        let report = match crate::homing::home_axes(&mut ctx, axes) {
            Ok(r) => r,
            Err(e @ HomingError::CommTimeout) if args.cycles > 1 => {
                timeouts += 1;
                failed_last = true;
                let detail = ctx.comm_timeout_detail.take().unwrap_or_default();
                o.err(format!("cycle {}: {e} ({detail})", cycle + 1));
                continue;
            }
            Err(e) => return Err(e.into()),
        };
        failed_last = false;
        for a in &report.axes {
            for (i, p) in a.passes.iter().enumerate() {
                last_step.record_signed((p.last_step_after_s * 1e9) as i64);
                next_step.record_signed((p.next_step_after_s * 1e9) as i64);
                overshoot.record_signed((p.overshoot_mm * 1e6) as i64); // nm
                timings.push(PassTiming {
                    cycle: cycle + 1,
                    pass: i + 1,
                    axis: a.axis,
                    received: p.trigger_received_at,
                    written: p.relay_written_at,
                });
            }
        }
        if cycle == 0 {
            report.to_string().lines().for_each(|l| o.out(l.to_string()));
        }
        reports.push(report.clone());
        last_report = report;
    }
    if args.cycles > 1 {
        o.out("last cycle:".to_string());
        last_report.to_string().lines().for_each(|l| o.out(l.to_string()));
    }
    check_positions(&mut ctx, machine)?;
    let pos = ctx.pipeline.position();
    o.out(format!(
        "homed position: x={:.6} y={:.6} z={:.6}",
        pos[0], pos[1], pos[2]
    ));
    let passes = last_step.count();
    o.out(format!(
        "homing: {} cycles, {passes} passes, {timeouts} communication timeouts, wall {:.1} s \
         (real time {}, idle poll {}, cpu load {})",
        args.cycles,
        started.elapsed().as_secs_f64(),
        if rt.enabled { "on" } else { "off" },
        if rt.idle_poll_homing() { "on" } else { "off" },
        if args.cpu_load { "on" } else { "off" }
    ));
    o.out(format!(
        "  host view, last executed step after trigger:  {}",
        last_step.summary().format_latency()
    ));
    o.out(format!(
        "  host view, first cancelled step after trigger: {}",
        next_step.summary().format_latency()
    ));
    let ov = overshoot.summary();
    let mm = |nm: u64| nm as f64 * 1e-6;
    o.out(format!(
        "  overshoot: p50 {:.4} mm p99 {:.4} mm p99.9 {:.4} mm max {:.4} mm",
        mm(ov.p50),
        mm(ov.p99),
        mm(ov.p999),
        mm(ov.max)
    ));
    let p999 = last_step.summary().p999 as f64 * last_step.ns_per_unit();
    Ok((timings, p999, reports, timeouts))
}

/// MCU clock → system time (CLOCK_MONOTONIC seconds).
#[derive(Debug, Clone, Copy)]
enum TimeBase {
    /// The simulator's own record of when its clock was 0.
    Epoch { epoch: f64, ticks_per_s: f64 },
    /// The host's clock sync fit (its error grows with the distance from the last samples).
    Estimate(ClockEstimate),
}

impl TimeBase {
    fn system_time_at(&self, clock: f64) -> f64 {
        match self {
            TimeBase::Epoch { epoch, ticks_per_s } => epoch + clock / ticks_per_s,
            TimeBase::Estimate(e) => e.system_time_at(clock),
        }
    }
}

/// Tolerance of the pass ↔ trace trigger pairing (the epochs are exact to nanoseconds).
const PAIR_SLACK_S: f64 = 0.005;
/// A pass whose report came more than this after the latest trigger has none in the trace.
const PAIR_WINDOW_S: f64 = 1.0;
/// Slowest passes listed.
const SLOWEST: usize = 5;

/// One pass' relay, hop by hop (seconds).
#[derive(Debug, Clone, Copy)]
struct Hops {
    cycle: u32,
    pass: usize,
    /// Endstop MCU trigger → the host read its report.
    read: f64,
    /// Host read → `trsync_trigger` written to the stepper MCU's link.
    relay: f64,
    /// Written → the stepper MCU's trsync trigger record.
    stop: f64,
}

impl Hops {
    fn total(&self) -> f64 {
        self.read + self.relay + self.stop
    }
}

/// Pairs each pass of `timings` with the latest endstop trigger at or before its read time
/// (`triggers` chronological, `stops[i]` the stop paired with trigger `i`). Returns the hops
/// of the paired passes and the number left unpaired.
fn pair_hops(timings: &[PassTiming], triggers: &[f64], stops: &[Option<f64>]) -> (Vec<Hops>, usize) {
    let mut used = vec![false; triggers.len()];
    let mut hops = Vec::with_capacity(timings.len());
    let mut unpaired = 0;
    for p in timings {
        let k = triggers.partition_point(|&t| t <= p.received + PAIR_SLACK_S);
        let trigger = k
            .checked_sub(1)
            .filter(|&i| !used[i] && p.received - triggers[i] <= PAIR_WINDOW_S);
        let stop = trigger.and_then(|i| stops.get(i).copied().flatten());
        let (Some(i), Some(written), Some(stop)) = (trigger, p.written, stop) else {
            unpaired += 1;
            continue;
        };
        used[i] = true;
        hops.push(Hops {
            cycle: p.cycle,
            pass: p.pass,
            read: p.received - triggers[i],
            relay: written - p.received,
            stop: stop - written,
        });
    }
    (hops, unpaired)
}

/// What the trace conversion needs to know of the MCUs once they are closed.
#[derive(Debug)]
struct TraceMcus {
    /// The main MCU's name (its trace file has no `-NAME` inserted).
    main: String,
    /// Each MCU's trsync oid.
    trsyncs: Vec<(String, u8)>,
    /// Clock estimates, the freshest first.
    clocks: Vec<(String, ClockEstimate)>,
}

/// One axis's trigger → stop latencies read from the simulated MCUs' traces (exact: the
/// endstop MCU's trigger record and the steppers' MCU's trsync trigger record, the moment its
/// steppers stopped, both in system time).
#[derive(Debug)]
pub struct TraceStops {
    /// 0 = X, 1 = Y, 2 = Z.
    pub axis: usize,
    /// The MCU of the axis's endstop.
    pub endstop_mcu: String,
    /// The MCU of the axis's steppers (the same as `endstop_mcu` when the MCU stops itself).
    pub stepper_mcu: String,
    /// Endstop trigger → steppers stopped, per pass (ns).
    pub stop: LatencyHist,
    /// Endstop trigger → the last step executed before the stop, per pass (ns; negative when
    /// the last step came before the trigger).
    pub last_step: LatencyHist,
    /// Each endstop trigger's system time and its stop's (when one was paired).
    triggers: Vec<f64>,
    stop_of: Vec<Option<f64>>,
}

/// Trigger → stop latencies from the simulated MCUs' traces (see the module doc) for each homed
/// axis, reported through `o`; for an axis whose endstop is on another MCU than its steppers
/// (either way round) also the relay's hops from the host's timestamps in `timings`.
fn trace_latency(
    machine: &Machine,
    axes: [bool; 3],
    base: &Path,
    mcus: &TraceMcus,
    timings: &[PassTiming],
    noise: &WakeupReport,
    o: &mut dyn HomeOutput,
) -> Result<Vec<TraceStops>, HomeCyclesError> {
    let mut all = Vec::new();
    for e in (machine.endstops.iter()).filter(|e| axes[e.axis] && e.motor.is_none()) {
        let Some(t) = trace_stops(machine, e, base, mcus, o)? else {
            continue;
        };
        let name = AXIS_NAMES[e.axis.min(2)];
        let stepper_mcu = t.stepper_mcu.as_str();
        let line = |label: &str, h: &LatencyHist| {
            format!(
                "trace {name} ({} → {stepper_mcu}): {label:<33} {}",
                e.pin.mcu,
                h.summary().format_latency()
            )
        };
        if t.endstop_mcu == t.stepper_mcu {
            // The MCU stops itself: no relay, no hops; `cadence home` reports those axes from
            // the host's view, `cadence bench homing` takes the figures.
            all.push(t);
            continue;
        }
        o.out(line("trigger → stepper MCU stop:", &t.stop));
        let p999 = t.stop.summary().p999 as f64 * t.stop.ns_per_unit();
        if let Some(r) = noise.ratio_to_p999(p999) {
            o.out(format!(
                "  trigger → stepper MCU stop p99.9 = {r:.1} x the machine's wake-up p99.9 meanwhile"
            ));
        }
        o.out(line("trigger → last step before stop:", &t.last_step));
        let s = t.last_step.summary();
        if s.negative > 0 {
            o.out(format!(
                "  ({} passes had their last step before the trigger)",
                s.negative
            ));
        }
        let (triggers, stop_of) = (&t.triggers, &t.stop_of);
        let axis_timings: Vec<PassTiming> = timings.iter().filter(|p| p.axis == e.axis).copied().collect();
        let (hops, unpaired) = pair_hops(&axis_timings, triggers, stop_of);
        let mut hists = [LatencyHist::new(), LatencyHist::new(), LatencyHist::new()];
        for h in &hops {
            for (hist, v) in hists.iter_mut().zip([h.read, h.relay, h.stop]) {
                hist.record_signed((v * 1e9) as i64);
            }
        }
        o.out(line("hop 1, trigger → host read:", &hists[0]));
        o.out(line("hop 2, host read → relay written:", &hists[1]));
        o.out(line("hop 3, relay written → MCU stop:", &hists[2]));
        let negative: u64 = hists.iter().map(|h| h.summary().negative).sum();
        o.out(format!(
            "  hops of {} passes (per pass they add up to its trigger → stop exactly){}{}",
            hops.len(),
            if unpaired > 0 {
                format!("; {unpaired} passes without a trace trigger or relay time")
            } else {
                String::new()
            },
            if negative > 0 {
                format!("; {negative} negative hops counted as 0")
            } else {
                String::new()
            }
        ));
        let mut slowest = hops;
        slowest.sort_by(|a, b| b.total().total_cmp(&a.total()));
        slowest.truncate(SLOWEST);
        if !slowest.is_empty() {
            o.out(
                "  slowest passes, µs:  cycle pass  trigger→read  read→written  written→stop     total"
                    .to_string(),
            );
            for h in &slowest {
                o.out(format!(
                    "                      {:>5} {:>4}  {:>12.1}  {:>12.1}  {:>12.1}  {:>8.1}",
                    h.cycle,
                    h.pass,
                    h.read * 1e6,
                    h.relay * 1e6,
                    h.stop * 1e6,
                    h.total() * 1e6
                ));
            }
        }
        all.push(t);
    }
    Ok(all)
}

/// One endstop's passes from the traces: `None` when a trace or its time base is missing.
fn trace_stops(
    machine: &Machine,
    e: &crate::hardware::EndstopOut,
    base: &Path,
    mcus: &TraceMcus,
    o: &mut dyn HomeOutput,
) -> Result<Option<TraceStops>, HomeCyclesError> {
    let TraceMcus {
        main,
        trsyncs,
        clocks,
    } = mcus;
    let main = main.as_str();
    let est = |name: &str| clocks.iter().find(|(n, _)| n == name).map(|&(_, e)| e);
    let read = |name: &str| {
        let path = trace_path(base, name, name == main);
        firmware::trace::read_trace(&path).map_err(|source| HomeCyclesError::Trace { path, source })
    };
    // Exact when both simulators wrote their clock epoch (they count CLOCK_MONOTONIC).
    let to_sys = |name: &str, trace: &firmware::trace::TraceFile| -> Option<TimeBase> {
        let epoch = firmware::sim::read_epoch(&trace_path(base, name, name == main));
        match epoch {
            Some(epoch) if trace.clock_freq > 0 && trace.time_scale > 0.0 => Some(TimeBase::Epoch {
                epoch,
                ticks_per_s: trace.clock_freq as f64 * trace.time_scale,
            }),
            _ => est(name).map(TimeBase::Estimate),
        }
    };
    // The axis' steppers' MCU (one: `check_config` refuses split axes with a third-MCU endstop).
    let group = crate::homing::axis_steppers(machine, e.axis);
    let Some(stepper_mcu) = group.first().map(|&i| machine.steppers[i].mcu.as_str()) else {
        return Ok(None);
    };
    let Some(&(_, trsync_oid)) = trsyncs.iter().find(|(n, _)| n == stepper_mcu) else {
        return Ok(None);
    };
    let s_trace = read(stepper_mcu)?;
    let Some(s_est) = to_sys(stepper_mcu, &s_trace) else {
        return Ok(None);
    };
    let e_trace;
    let (e_trace, e_est) = if e.pin.mcu == stepper_mcu {
        (&s_trace, s_est)
    } else {
        e_trace = read(&e.pin.mcu)?;
        let Some(e_est) = to_sys(&e.pin.mcu, &e_trace) else {
            return Ok(None);
        };
        if matches!((&e_est, &s_est), (TimeBase::Epoch { .. }, TimeBase::Epoch { .. })) {
            o.out("trace: MCU clocks converted with the simulators' clock epochs (exact)".to_string());
        } else {
            o.out("trace: MCU clocks converted with the host's clock estimates".to_string());
        }
        (&e_trace, e_est)
    };
    let triggers: Vec<f64> = e_trace
        .triggers
        .iter()
        .filter(|t| t.endstop && t.oid == e.oid)
        .map(|t| e_est.system_time_at(t.clock as f64))
        .collect();
    let stops: Vec<(u64, f64)> = s_trace
        .triggers
        .iter()
        .filter(|t| !t.endstop && t.oid == trsync_oid)
        .map(|t| (t.clock, s_est.system_time_at(t.clock as f64)))
        .collect();
    let oids: Vec<u8> = group
        .iter()
        .map(|&i| &machine.steppers[i])
        .filter(|s| s.mcu == stepper_mcu)
        .map(|s| s.oid)
        .collect();
    let steps = step_clocks(&s_trace, &oids);
    let (stop_h, last_h, stop_of) = pair_stops(&triggers, &stops, &steps, &s_est);
    Ok(Some(TraceStops {
        axis: e.axis,
        endstop_mcu: e.pin.mcu.clone(),
        stepper_mcu: stepper_mcu.to_string(),
        stop: stop_h,
        last_step: last_h,
        triggers,
        stop_of,
    }))
}

/// The clocks of the steps of the steppers `oids` in `trace`, in order.
fn step_clocks(trace: &firmware::trace::TraceFile, oids: &[u8]) -> Vec<u64> {
    let mut steps: Vec<u64> = trace
        .records
        .iter()
        .filter_map(|r| match *r {
            firmware::trace::TraceRecord::Step { oid, clock, .. } if oids.contains(&oid) => Some(clock),
            _ => None,
        })
        .collect();
    steps.sort_unstable();
    steps
}

/// Pairs each trigger (system time) with the first trsync stop (stepper MCU clock, system
/// time) not before it (within [`PAIR_SLACK_S`]): the trigger → stop latencies, the trigger →
/// last step before the stop latencies (`steps`: the axis' step clocks, `est` their time
/// base), and each trigger's stop time.
fn pair_stops(
    triggers: &[f64],
    stops: &[(u64, f64)],
    steps: &[u64],
    est: &TimeBase,
) -> (LatencyHist, LatencyHist, Vec<Option<f64>>) {
    let mut stop_h = LatencyHist::new();
    let mut last_h = LatencyHist::new();
    let mut stop_of = vec![None; triggers.len()];
    let mut j = 0;
    for (&t, stop_of) in triggers.iter().zip(&mut stop_of) {
        while j < stops.len() && stops[j].1 < t - PAIR_SLACK_S {
            j += 1;
        }
        let Some(&(stop_clock, stop_sys)) = stops.get(j) else {
            break;
        };
        j += 1;
        *stop_of = Some(stop_sys);
        stop_h.record_signed(((stop_sys - t) * 1e9) as i64);
        let k = steps.partition_point(|&c| c <= stop_clock);
        if k > 0 {
            last_h.record_signed(((est.system_time_at(steps[k - 1] as f64) - t) * 1e9) as i64);
        }
    }
    (stop_h, last_h, stop_of)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn timing(cycle: u32, received: f64, written: Option<f64>) -> PassTiming {
        PassTiming {
            cycle,
            pass: 1,
            axis: 2,
            received,
            written,
        }
    }

    #[test]
    fn passes_pair_with_the_latest_trigger_before_their_report() {
        // Trigger 1 belongs to a failed pass the host reported nothing for.
        let triggers = [1.0, 2.0, 3.0, 5.0];
        let stops = [Some(1.01), Some(2.01), Some(3.004), None];
        let timings = [
            timing(1, 1.001, Some(1.002)),
            timing(2, 3.001, Some(3.003)),
            // No stop in the trace, no relay time, no trigger within the window.
            timing(3, 5.001, Some(5.002)),
            timing(4, 4.0, None),
            timing(5, 9.0, Some(9.001)),
        ];
        let (hops, unpaired) = pair_hops(&timings, &triggers, &stops);
        assert_eq!(unpaired, 3);
        assert_eq!(hops.len(), 2);
        assert_eq!((hops[0].cycle, hops[1].cycle), (1, 2));
        for (h, (t, stop)) in hops.iter().zip([(1.0, 1.01), (3.0, 3.004)]) {
            assert!((h.total() - (stop - t)).abs() < 1e-12, "{h:?}");
        }
        assert!((hops[1].read - 0.001).abs() < 1e-9);
        assert!((hops[1].relay - 0.002).abs() < 1e-9);
        assert!((hops[1].stop - 0.001).abs() < 1e-9);
    }
}
