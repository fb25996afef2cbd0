//! G28 with motion, across MCUs: Klipper's endstop + trsync protocol (`links::trsync`: trigger
//! relay, 25 ms status timeout), the halt position computed on the host.
//!
//! The axis steppers are every stepper that moves the homed axis ([`axis_steppers`]): X's own
//! on a cartesian printer, both motors A (x + y) and B (x − y) for corexy X or Y, A (x + z) and
//! B (x − z) for corexz X or Z, each rail with its further motors (`stepper_z1`…, on the rail
//! motor's MCU), all stopped by the one trigger. Further motors with their own endstops
//! (`[stepper_z1] endstop_pin`) each end on their own switch (module `motors`). A delta homes
//! its three towers, one after the other with the other two held still, then computes the
//! toolhead from the three carriage heights (module `delta`).
//!
//! Per axis, per pass (the second at `second_homing_speed` after retracting
//! `homing_retract_dist`, skipped when that is 0):
//! 1. every step already planned is sent and executed (the MCUs are idle);
//! 2. the toolhead pretends to be 1.5 × travel (second pass: 2 × retract) away from the endstop
//!    on the far side;
//! 3. one trsync per involved MCU (the endstop's and the axis steppers') gets `trsync_start`
//!    (reports every 0.3 × timeout from ~2 ms on) and `trsync_set_timeout`; the stepper MCUs get
//!    `stepper_stop_on_trigger`; after a `get_clock` round trip per MCU (stale reports of the
//!    previous pass are in) a [`TriggerGroup`] registers them, then the endstop MCU gets
//!    `endstop_home` (15 µs samples, 4 of them, a read every ≤ 1 ms) from the move's start `t0`
//!    (≥ now + lead + a margin);
//! 4. the move to `position_endstop` at the homing speed is planned and all its steps are sent;
//!    the IO threads relay the trigger and extend the timeouts while we wait;
//! 5. whatever happened, every member is told to stop (`trsync_trigger`, host request) and the
//!    endstop stops sampling; once the stepper links are idle the axis steppers are stopped a
//!    second time (a step command the trigger overtook would restart them); then the endstop's trigger clock (`endstop_query_state`) and each
//!    axis stepper's position (`stepper_get_position`) are read;
//! 6. the position ([`halt_position`]): with `n(x) = ⌊x / step_dist + ½⌋` the step index of
//!    stepper position x, each axis stepper was at index `n_start = n(start)` and the MCU says
//!    it took `k` net steps, so it halted at `n_halt = n_start + k`; at the trigger print time
//!    `t` its commanded position was `x(t)` on the move's profile, index `n_trig = n(x(t))`.
//!    Forward kinematics of the rails at `n_halt · step_dist` and at `n_trig · step_dist` give
//!    the halted and the triggered toolhead positions (cartesian: the rail itself; corexy:
//!    x = (a + b) / 2, y = (a − b) / 2). The trigger defines `position_endstop`, so the homed
//!    axis is now at `position_endstop + (halted − triggered)` (the overshoot is accounted
//!    for; cartesian: `position_endstop + (n_halt − n_trig) · step_dist`), and any other axis
//!    the steppers move at its halted coordinate (unchanged up to a step's rounding); the
//!    planner and the step streamer are resynced to that, the next move starting at now + lead
//!    + margin.
//!
//! Errors: a trsync that expired or a member silent past the timeout →
//! exactly `Communication timeout during homing`; no trigger by the end of the move →
//! `No trigger on <axis> after full movement`; the endstop still triggered after the retract →
//! `Endstop <axis> still triggered after retract`. In every case all involved steppers have been
//! told to stop first, and the planner is resynced to where they stopped when the MCUs still
//! answer.
//!
//! Probing (`PROBE`, module `probe`) runs the same pass in probe mode ([`PassKind::Probe`]):
//! no pretended start, the move heads for the probe's `z_position`, the triggered Z is the
//! measurement and the toolhead keeps its coordinates (resynced to the halted position; on
//! corexz both motors of Z stop). With `probe:z_virtual_endstop` the probe's pin is Z's endstop.
//!
//! Latency figures per pass (host's view, print-time seconds): the executed steps' times are
//! known from the move profile, so the last executed step and the first cancelled one bound
//! the moment the stepper MCU stopped, relative to the endstop's trigger.

pub mod bed_mesh;
pub mod bltouch;
mod delta;
mod error;
mod halt;
mod motors;
mod pass;
pub mod probe;
pub mod procedure;
pub mod screws;
pub mod smart_effector;
pub mod z_tilt;

pub use error::{HomingError, LevelingError, ParamProblem, WiringError};
pub(crate) use pass::{homing_pass, PassPlan};

use std::fmt;
use std::time::{Duration, Instant};

use links::mcu::McuLink;
use planner::kinematics::{Kinematics, StepperKin};
use planner::pipeline::Pipeline;
use planner::stepgen::StepCmd;

use crate::gcode_feed::MotionCmd;
use crate::hardware::{EndstopOut, Machine};
use crate::mcus::{McuConn, Mcus};
use crate::step_stream::sink::{LinkSink, Sink};
use crate::step_stream::StepStreams;
use crate::MIN_LEAD_S;

/// Endstop confirmation sample spacing (s of MCU time).
pub const SAMPLE_TIME: f64 = 15e-6;
/// Matching samples needed for a trigger.
pub const SAMPLE_COUNT: u8 = 4;
/// Longest time between endstop reads while waiting for a match (s).
pub const MAX_REST_TIME: f64 = 1e-3;
/// Shortest time between endstop reads (s).
pub const MIN_REST_TIME: f64 = 100e-6;
/// Margin on top of the lead between "now" and the start of a homing move, in seconds of wall
/// time (× the simulator's time scale in print time): the set-up messages go out in it.
pub const START_MARGIN: f64 = 0.030;
/// The first homing move pretends to start this many axis travels away from the endstop.
pub const TRAVEL_FACTOR: f64 = 1.5;
/// Wall seconds per step a homing move's steps take to generate, assumed until a pass has
/// measured it (a debug build on a loaded 2-core machine: ~5 µs; a release build learns its
/// own, far lower, figure at its first pass). The whole move is generated at once.
pub const GEN_WALL_PER_STEP: f64 = 5e-6;
/// [`GEN_WALL_PER_STEP`] of a delta tower, whose step times are solved numerically (~13 µs
/// measured in that debug build).
pub const GEN_WALL_PER_STEP_DELTA: f64 = 20e-6;
/// A homing move starts this many times its expected generation time after "now" (on top of
/// the lead): room for host pauses while a long move's steps are computed.
const GEN_ALLOWANCE_FACTOR: f64 = 2.0;
/// The share of an MCU's 32-bit clock range a homing move may start ahead of now at most.
const ALLOWANCE_CLOCK_SHARE: f64 = 0.25;
/// Passes with fewer steps than this teach nothing about the generation rate (timer noise).
const GEN_LEARN_MIN_STEPS: f64 = 1000.0;
/// Tries of a position / endstop-state query (a reply can be lost on a noisy line).
const QUERY_TRIES: u32 = 5;
/// Wait for one query reply (wall time).
const QUERY_TIMEOUT: Duration = Duration::from_millis(300);
/// First trsync report this long after the set-up is sent (wall time, s): room for a slow line
/// (the command must arrive before it), well inside the 25 ms multi-MCU timeout.
const FIRST_REPORT_DELAY: f64 = 0.010;
/// Extra wall time after the homing move's end before "no trigger" is concluded.
const END_GRACE: Duration = Duration::from_millis(50);

pub const AXIS_NAMES: [char; 3] = ['x', 'y', 'z'];

/// What homing borrows from the live print.
pub struct HomingCtx<'a> {
    pub mcus: &'a Mcus,
    pub machine: &'a Machine,
    pub pipeline: &'a mut Pipeline,
    /// The step streams of the MCUs with steppers (the main MCU's first).
    pub streams: &'a mut StepStreams,
    /// Where each stream's step commands go (its MCU's live link), in stream order.
    pub sinks: &'a mut [LinkSink<'a>],
    /// MCU seconds per wall second (simulator `time_scale`; 1 for real MCUs): bounds waits.
    pub time_scale: f64,
    /// The real-time settings: each homing or probing pass keeps the idle CPUs polling when
    /// they ask for it ([`crate::realtime::RtConfig::start_idle_poll`]).
    pub rt: &'a crate::realtime::RtConfig,
    /// What the last communication timeout was, beyond its exact message (which MCU, MCU
    /// expiry or host-side silence): for logs and `cadence home`.
    pub comm_timeout_detail: Option<String>,
    /// Lines for the user produced on the way (a BLTouch's retries), drained into the
    /// command's output.
    pub messages: Vec<String>,
    /// The passes of every probe sample taken so far (their stop latencies), for reports.
    pub probe_passes: Vec<PassReport>,
    /// Wall seconds per step the last long homing move's steps took to generate (starts at
    /// [`GEN_WALL_PER_STEP`], [`GEN_WALL_PER_STEP_DELTA`] on a delta): the next move's start
    /// leaves room for its own.
    pub gen_wall_per_step: f64,
}

impl<'a> HomingCtx<'a> {
    /// Homing on the live links: step commands go to `sinks` (see [`direct_sinks`]) with the
    /// print's lead ([`MIN_LEAD_S`]).
    pub fn new(
        mcus: &'a Mcus,
        machine: &'a Machine,
        pipeline: &'a mut Pipeline,
        streams: &'a mut StepStreams,
        sinks: &'a mut [LinkSink<'a>],
        time_scale: f64,
        rt: &'a crate::realtime::RtConfig,
    ) -> HomingCtx<'a> {
        HomingCtx {
            mcus,
            machine,
            pipeline,
            streams,
            sinks,
            time_scale,
            rt,
            comm_timeout_detail: None,
            messages: Vec::new(),
            probe_passes: Vec::new(),
            gen_wall_per_step: match machine.options.kinematics {
                Kinematics::Delta(_) => GEN_WALL_PER_STEP_DELTA,
                _ => GEN_WALL_PER_STEP,
            },
        }
    }
}

impl HomingCtx<'_> {
    /// The earliest print time a command sent now may act at: the lead every step command must
    /// have at the MCU, plus [`START_MARGIN`] (scaled with a fast simulated clock).
    fn earliest_start(&self) -> f64 {
        print_now(self.mcus) + MIN_LEAD_S + START_MARGIN * self.time_scale.max(1.0)
    }

    /// Print time to leave before a homing move of `steps` steps starts, for computing them:
    /// all of a move's steps are generated before the first is sent, so a long move (a fine Z
    /// screw: 300 mm at 400 steps/mm is 120,000 steps) would otherwise have its first steps
    /// late. The expected wall time ([`Self::gen_wall_per_step`] per step) times
    /// [`GEN_ALLOWANCE_FACTOR`], in MCU time.
    /// At most a quarter of the fastest MCU's 32-bit clock range ([`ALLOWANCE_CLOCK_SHARE`]):
    /// the move's start and the endstop's first read go out as 32-bit clocks, and one more
    /// than 2³¹ ticks ahead reads as in the past (a 900,000-step probe pass on a 50 MHz MCU at
    /// time scale 10 asked for up to 89 s at the assumed rate, and its endstop reported a
    /// trigger before the move).
    fn generation_allowance(&self, steps: f64) -> f64 {
        let want = steps * self.gen_wall_per_step * GEN_ALLOWANCE_FACTOR * self.time_scale.max(1.0);
        let fastest = self.mcus.list.iter().map(|m| m.clock_freq).fold(1.0, f64::max);
        want.min(ALLOWANCE_CLOCK_SHARE * 4_294_967_296.0 / fastest)
    }

    /// Learns from a move of `steps` steps whose generation took `wall_s`: a slower rate is
    /// taken at once, a faster one at most halves the figure per pass (one quiet pass does not
    /// make the next allowance short).
    fn learn_generation(&mut self, steps: f64, wall_s: f64) {
        if steps >= GEN_LEARN_MIN_STEPS && wall_s.is_finite() {
            self.gen_wall_per_step = (wall_s / steps).max(0.5 * self.gen_wall_per_step);
        }
    }
}

/// One sink per step stream, straight to that stream's MCU link (stream order).
pub fn direct_sinks<'a>(streams: &StepStreams, mcus: &'a Mcus) -> Vec<LinkSink<'a>> {
    streams
        .mcus
        .iter()
        .map(|m| LinkSink {
            link: &mcus.list[m.mcu_index].link,
        })
        .collect()
}

impl fmt::Debug for HomingCtx<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("HomingCtx")
            .field("time_scale", &self.time_scale)
            .finish_non_exhaustive()
    }
}

/// One homing move of one axis.
#[derive(Debug, Clone, PartialEq)]
pub struct PassReport {
    /// Homing speed (mm/s).
    pub speed: f64,
    /// The MCU whose endstop triggered.
    pub trigger_mcu: String,
    /// Its trigger clock (64-bit, its own clock).
    pub trigger_clock: u64,
    /// The trigger on the main MCU's print time.
    pub trigger_print_time: f64,
    /// Position past the trigger point at which the axis halted (mm, ≥ 0 normally).
    pub overshoot_mm: f64,
    /// Axis coordinate of the trigger: `position_endstop` when homing (the trigger defines
    /// it), the measured position when probing.
    pub trigger_position: f64,
    /// Net steps the first axis stepper took during the move.
    pub steps: i64,
    /// Last executed step − trigger (s of print time): a lower bound of the stop latency
    /// (negative when no step fell between the trigger and the stop).
    pub last_step_after_s: f64,
    /// First cancelled step − trigger (s): an upper bound of the stop latency.
    pub next_step_after_s: f64,
    /// System time (`CLOCK_MONOTONIC` s) at which the host read the trigger's report.
    pub trigger_received_at: f64,
    /// System time at which the host's first `trsync_trigger` to the axis steppers' MCU was
    /// written to its link (`None` when the steppers are on the triggering MCU).
    pub relay_written_at: Option<f64>,
}

/// One homed axis.
#[derive(Debug, Clone, PartialEq)]
pub struct AxisReport {
    /// 0 = X, 1 = Y, 2 = Z.
    pub axis: usize,
    /// The MCUs of its trigger group.
    pub mcus: Vec<String>,
    pub passes: Vec<PassReport>,
    /// Toolhead position of the axis after homing (position_endstop + last overshoot).
    pub position: f64,
}

/// `s` seconds after the trigger in words: `208 us after the trigger`, `42 us before it`.
fn relative_to_trigger(s: f64) -> String {
    let us = (s * 1e6).round();
    if us < 0.0 {
        format!("{:.0} us before the trigger", -us)
    } else {
        format!("{us:.0} us after the trigger")
    }
}

/// What [`home_axes`] did.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct HomingReport {
    pub axes: Vec<AxisReport>,
}

impl fmt::Display for HomingReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for a in &self.axes {
            let name = AXIS_NAMES[a.axis.min(2)];
            write!(f, "homing {name}: mcus {}", a.mcus.join("+"))?;
            for (i, p) in a.passes.iter().enumerate() {
                write!(
                    f,
                    "; pass {} at {} mm/s: trigger on '{}', overshoot {:.4} mm, last step {}, first cancelled {}",
                    i + 1,
                    p.speed,
                    p.trigger_mcu,
                    p.overshoot_mm,
                    relative_to_trigger(p.last_step_after_s),
                    relative_to_trigger(p.next_step_after_s)
                )?;
            }
            writeln!(f, "; position {:.6}", a.position)?;
        }
        Ok(())
    }
}

/// Checks the homing wiring: the steppers of one axis may sit on several MCUs only if the
/// endstop is on one of them... and Klipper refuses even that; Cadence refuses the case the
/// trigger relay cannot serve: steppers of one axis on different MCUs while the endstop is on
/// yet another.
pub fn check_config(machine: &Machine) -> Result<(), HomingError> {
    let probe = machine.probe.as_ref().map(|p| &p.endstop);
    for e in machine.endstops.iter().chain(probe) {
        let mut mcus: Vec<&str> = Vec::new();
        for s in axis_steppers(machine, e.axis)
            .into_iter()
            .map(|i| &machine.steppers[i])
        {
            if !mcus.contains(&s.mcu.as_str()) {
                mcus.push(&s.mcu);
            }
        }
        if mcus.len() > 1 && !mcus.contains(&e.pin.mcu.as_str()) {
            return Err(HomingError::Wiring(Box::new(WiringError {
                section: e.stepper.clone(),
                option: if e.stepper == "probe" {
                    "pin"
                } else {
                    "endstop_pin"
                },
                pin: e.pin.to_string(),
                axis: AXIS_NAMES[e.axis.min(2)],
                mcus: mcus.iter().map(|m| m.to_string()).collect(),
                endstop_mcu: e.pin.mcu.clone(),
            })));
        }
    }
    Ok(())
}

/// Runs a G-code command that needs the MCUs in the loop (G28 with motion, the probe
/// commands) on a live print; its report lines go to `out` (also those before an error), and
/// a G28's report comes back.
pub(crate) fn run_motion(
    ctx: &mut HomingCtx<'_>,
    cmd: &MotionCmd<'_>,
    out: &mut Vec<String>,
) -> Result<Option<HomingReport>, HomingError> {
    let r = match cmd {
        MotionCmd::Home(axes) => home_axes(ctx, *axes).map(|report| {
            out.append(&mut ctx.messages);
            out.extend(report.to_string().lines().map(str::to_string));
            Some(report)
        }),
        MotionCmd::Probe { name, raw } => probe::run(ctx, name, raw, out).map(|()| None),
        // After the moves before it, as Klipper's print-time ordered register writes.
        MotionCmd::Tmc { name, raw } => wait_motion_done(ctx)
            .and_then(|()| {
                Ok(crate::tmc::gcode::run(
                    ctx.mcus,
                    &ctx.machine.tmc,
                    name,
                    raw,
                    out,
                )?)
            })
            .and_then(|()| resume_after_io(ctx))
            .map(|()| None),
    };
    out.append(&mut ctx.messages);
    r
}

/// Homes the named axes (X, Y, Z order) on a live print: `G28` with motion. On success the
/// axes are homed in the G-code state and the planner continues from the homed position.
pub fn home_axes(ctx: &mut HomingCtx<'_>, axes: [bool; 3]) -> Result<HomingReport, HomingError> {
    if !ctx.pipeline.supports_homing() {
        return Err(HomingError::NeedsInlinePlanner);
    }
    check_config(ctx.machine)?;
    let mut report = HomingReport::default();
    if let Some((geometry, endstops)) = delta_endstops(ctx.machine).filter(|_| axes.contains(&true)) {
        // A delta homes its three towers together, whichever axes G28 names (as Klipper).
        ctx.pipeline.set_homed([false; 3]);
        report.axes = delta::home_towers(ctx, &geometry, &endstops)?;
        ctx.pipeline.set_homed([true; 3]);
        return Ok(report);
    }
    for axis in (0..3).filter(|&a| axes[a]) {
        let mut homed = ctx.pipeline.gcode_state().homed();
        homed[axis] = false;
        ctx.pipeline.set_homed(homed);
        let own: Vec<EndstopOut> = (ctx.machine.endstops.iter())
            .filter(|e| e.axis == axis && e.motor.is_some())
            .cloned()
            .collect();
        match (ctx.machine.endstops.iter())
            .find(|e| e.axis == axis && e.motor.is_none())
            .cloned()
        {
            // On the probe (`probe:z_virtual_endstop`), a BLTouch is deployed for the passes.
            Some(e) if e.probe => report.axes.push(bltouch::session(ctx, |ctx| {
                home_axis(ctx, &e, PassPlan::default())
            })?),
            // On a driver's virtual endstop: the driver reports stalls for the passes.
            Some(e) if e.sensorless.is_some() => report.axes.push(sensorless_session(ctx, &e)?),
            // Further motors on their own endstops (`[stepper_z1] endstop_pin`).
            Some(e) if !own.is_empty() => report.axes.push(motors::home_motors(ctx, &e, &own)?),
            Some(e) => report.axes.push(home_axis(ctx, &e, PassPlan::default())?),
            None => {
                // No endstop: the old behaviour, the position is declared.
                let mut pos = ctx.pipeline.position();
                pos[axis] = ctx.machine.home_position[axis];
                ctx.pipeline.set_toolhead_position(pos);
            }
        }
        let mut homed = ctx.pipeline.gcode_state().homed();
        homed[axis] = true;
        ctx.pipeline.set_homed(homed);
    }
    Ok(report)
}

/// Both passes of one axis, each as `plan` says (a delta tower's: its `tower`).
fn home_axis(ctx: &mut HomingCtx<'_>, e: &EndstopOut, plan: PassPlan<'_>) -> Result<AxisReport, HomingError> {
    let axis = e.axis;
    let travel = e.position_max - e.position_min;
    let dir = if e.homing_positive_dir { 1.0 } else { -1.0 };
    let mut passes = Vec::new();
    let start = e.position_endstop - dir * TRAVEL_FACTOR * travel;
    let (first, mcus) = probe_pass(ctx, e, PassKind::Home { start }, e.homing_speed, plan)?;
    passes.push(first);
    let retract = e.homing_retract_dist;
    if retract > 0.0 {
        let mut pos = ctx.pipeline.position();
        pos[axis] = e.position_endstop - dir * retract;
        plain_move(ctx, pos, e.homing_speed)?;
        wait_motion_done(ctx)?;
        if endstop_state(ctx, e)?.1 {
            return Err(HomingError::StillTriggered {
                axis: AXIS_NAMES[axis],
            });
        }
        let start = e.position_endstop - dir * 2.0 * retract;
        let (second, _) = probe_pass(ctx, e, PassKind::Home { start }, e.second_homing_speed, plan)?;
        passes.push(second);
    }
    Ok(AxisReport {
        axis,
        mcus,
        passes,
        position: ctx.pipeline.position()[axis],
    })
}

/// A homing pass; on the probe, between deploying and stowing a BLTouch.
fn probe_pass(
    ctx: &mut HomingCtx<'_>,
    e: &EndstopOut,
    kind: PassKind,
    speed: f64,
    plan: PassPlan<'_>,
) -> Result<(PassReport, Vec<String>), HomingError> {
    match e.probe {
        true => bltouch::sample(ctx, |ctx| homing_pass(ctx, e, kind, speed, plan)),
        false => homing_pass(ctx, e, kind, speed, plan),
    }
}

/// A plain move of the toolhead to `pos` (retract, bench moves), sent at once.
pub fn plain_move(ctx: &mut HomingCtx<'_>, pos: [f64; 4], speed: f64) -> Result<(), HomingError> {
    let t0 = ctx.earliest_start();
    ctx.pipeline.raise_print_time(t0)?;
    ctx.pipeline.home_move(pos, speed)?;
    let mut out = Vec::new();
    generate(ctx, &mut out)?;
    push_cmds(ctx, &out)
}

/// Releases the planned step commands, each stepper's in its MCU's clock as the clock fits
/// stand now.
fn generate(ctx: &mut HomingCtx<'_>, out: &mut Vec<(usize, StepCmd)>) -> Result<(), HomingError> {
    let mcus = ctx.mcus;
    ctx.streams.refresh_clocks(ctx.pipeline, |i| {
        mcus.list
            .get(i)
            .map_or(links::clocksync::ClockEstimate::INVALID, |m| m.link.clock())
    })?;
    ctx.pipeline.generate(out);
    Ok(())
}

/// MCU `mcu_index`'s clock now (its fit; 0 for an unknown MCU).
fn mcu_clock_now(mcus: &Mcus, mcu_index: usize) -> f64 {
    mcus.list
        .get(mcu_index)
        .map_or(0.0, |m| m.link.clock().clock_at(McuLink::system_now()))
}

/// The main MCU's print time now (its estimated clock / nominal CLOCK_FREQ).
pub fn print_now(mcus: &Mcus) -> f64 {
    let main = mcus.main();
    main.link.clock().clock_at(McuLink::system_now()) / main.clock_freq
}

/// MCU `m`'s clock at main print time `t`.
fn clock_at_print_time(mcus: &Mcus, m: &McuConn, t: f64) -> u64 {
    let main = mcus.main();
    if std::ptr::eq(main, m) {
        return (t * main.clock_freq).max(0.0) as u64;
    }
    let sys = main.link.clock().system_time_at(t * main.clock_freq);
    m.link.clock().clock_at(sys).max(0.0) as u64
}

/// Main print time at MCU `m`'s clock `clock`.
fn print_time_of_clock(mcus: &Mcus, m: &McuConn, clock: u64) -> f64 {
    let main = mcus.main();
    if std::ptr::eq(main, m) {
        return clock as f64 / main.clock_freq;
    }
    let sys = m.link.clock().system_time_at(clock as f64);
    main.link.clock().clock_at(sys) / main.clock_freq
}

/// Hands released step commands to their MCUs' sinks, refusing any that would reach its MCU
/// late.
fn push_cmds(ctx: &mut HomingCtx<'_>, out: &[(usize, StepCmd)]) -> Result<(), HomingError> {
    let now: Vec<f64> = ctx
        .streams
        .mcus
        .iter()
        .map(|m| mcu_clock_now(ctx.mcus, m.mcu_index))
        .collect();
    for &(idx, cmd) in out {
        if let StepCmd::QueueStep { first_clock, .. } = cmd {
            let k = ctx.streams.stream_of(idx).unwrap_or(0);
            let m = &ctx.streams.mcus[k];
            if (first_clock as f64) < now[k] + MIN_LEAD_S * m.clock_freq {
                return Err(HomingError::LateStep {
                    stepper: ctx
                        .machine
                        .steppers
                        .get(idx)
                        .map_or("?", |s| s.name.as_str())
                        .to_string(),
                    mcu: m.name.clone(),
                    ready_ms: (first_clock as f64 - now[k]) / m.clock_freq * 1e3,
                    min_ms: MIN_LEAD_S * 1e3,
                });
            }
        }
        ctx.streams.push(idx, cmd, ctx.sinks)?;
    }
    Ok(ctx.sinks.iter_mut().try_for_each(|s| s.flush())?)
}

/// Sends everything planned so far and waits (bounded) until every MCU executed it.
pub fn wait_motion_done(ctx: &mut HomingCtx<'_>) -> Result<(), HomingError> {
    ctx.pipeline.flush_lookahead();
    let mut out = Vec::new();
    generate(ctx, &mut out)?;
    push_cmds(ctx, &out)?;
    for m in &ctx.streams.mcus {
        let Some(conn) = ctx.mcus.list.get(m.mcu_index) else {
            continue;
        };
        let end = m.streamer.last_step_clock as f64 + 0.001 * m.clock_freq;
        let now = || mcu_clock_now(ctx.mcus, m.mcu_index);
        let remaining = ((end - now()) / m.clock_freq).max(0.0);
        let deadline = Instant::now() + Duration::from_secs_f64(remaining / ctx.time_scale.max(1e-3) + 5.0);
        while now() < end {
            ctx.mcus.check()?;
            if let Some(e) = conn.link.error() {
                return Err(HomingError::McuLink {
                    mcu: conn.name.clone(),
                    source: e,
                });
            }
            if Instant::now() > deadline {
                return Err(HomingError::ClockStalled {
                    mcu: conn.name.clone(),
                });
            }
            std::thread::sleep(Duration::from_millis(1));
        }
    }
    Ok(ctx.mcus.check()?)
}

/// Homes on a TMC driver's virtual endstop: stall reporting on before the passes, the
/// driver's settings back after them (also when homing failed).
fn sensorless_session(ctx: &mut HomingCtx<'_>, e: &EndstopOut) -> Result<AxisReport, HomingError> {
    let tmc = &ctx.machine.tmc;
    let drv = e
        .sensorless
        .and_then(|i| tmc.get(i))
        .ok_or(HomingError::NoSensorlessDriver)?;
    let io = crate::tmc::gcode::io_for(ctx.mcus, tmc, &drv.cfg.stepper)?;
    let saved = crate::tmc::sensorless::begin(&io)?;
    let result = home_axis(ctx, e, PassPlan::default());
    let io = crate::tmc::gcode::io_for(ctx.mcus, &ctx.machine.tmc, &drv.cfg.stepper)?;
    let restored = crate::tmc::sensorless::end(&io, saved);
    let report = result?;
    restored?;
    resume_after_io(ctx)?;
    Ok(report)
}

/// After register traffic that took wall time: the toolhead's next move starts no earlier than
/// a move planned now can (else its first steps would be late).
fn resume_after_io(ctx: &mut HomingCtx<'_>) -> Result<(), HomingError> {
    let start = ctx.earliest_start();
    Ok(ctx.pipeline.raise_print_time(start)?)
}

/// `query` with retries (the reply of an idempotent query can be lost on a noisy line).
fn query<'m>(
    mcus: &'m Mcus,
    mcu_name: &str,
    name: &str,
    oid: u8,
    response: &str,
) -> Result<(&'m McuConn, links::dict::Message), HomingError> {
    let conn = mcu(mcus, mcu_name)?;
    let cmd = conn
        .link
        .dictionary()
        .encode(name, &[oid as i64])
        .map_err(|source| HomingError::Encode {
            mcu: conn.name.clone(),
            source,
        })?;
    let mut tries = 1;
    loop {
        match conn
            .link
            .query(cmd, response, Some(("oid", oid as i64)), QUERY_TIMEOUT)
        {
            Ok(m) => return Ok((conn, m)),
            Err(links::mcu::LinkError::Timeout { .. }) if tries < QUERY_TRIES => tries += 1,
            Err(e) => return Err(e.into()),
        }
    }
}

fn mcu<'m>(mcus: &'m Mcus, name: &str) -> Result<&'m McuConn, HomingError> {
    mcus.get(name).ok_or_else(|| HomingError::NoMcu {
        name: name.to_string(),
    })
}

/// Net steps of stepper `idx` as the host counts them (the MCU's count, sign-corrected for an
/// inverted dir pin).
pub fn stepper_position(ctx: &HomingCtx<'_>, idx: usize) -> Result<i64, HomingError> {
    let s = &ctx.machine.steppers[idx];
    let (_, reply) = query(
        ctx.mcus,
        &s.mcu,
        "stepper_get_position",
        s.oid,
        "stepper_position",
    )?;
    let raw = reply.get("pos").ok_or(HomingError::MissingField {
        response: "stepper_position",
        field: "pos",
    })?;
    Ok(if s.dir_pin.invert { -raw } else { raw })
}

/// (`next_clock` extended to 64 bits, the pin reads triggered, still homing) of endstop `e`.
pub(crate) fn endstop_state(ctx: &HomingCtx<'_>, e: &EndstopOut) -> Result<(u64, bool, bool), HomingError> {
    let (conn, reply) = query(
        ctx.mcus,
        &e.pin.mcu,
        "endstop_query_state",
        e.oid,
        "endstop_state",
    )?;
    let wire = reply.get("next_clock").unwrap_or(0) as u32;
    let clock = conn.link.clock().extend(wire, McuLink::system_now());
    let pin = reply.get("pin_value").unwrap_or(0) != 0;
    let homing = reply.get("homing").unwrap_or(0) != 0;
    Ok((clock, pin != e.pin.invert, homing))
}

/// What a homing move is for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum PassKind {
    /// G28: the axis position is unknown; the move pretends to start at `start` and heads for
    /// `position_endstop`, which the trigger defines.
    Home { start: f64 },
    /// PROBE: from the current (homed) position toward `target`; the trigger's position is
    /// measured and the axis keeps its coordinates.
    Probe { target: f64 },
}

/// A delta printer's geometry and its towers' endstops (tower A's first), when every tower
/// has a plain endstop.
fn delta_endstops(machine: &Machine) -> Option<(planner::kinematics::DeltaGeometry, [EndstopOut; 3])> {
    let Kinematics::Delta(g) = machine.options.kinematics else {
        return None;
    };
    let tower = |t: usize| {
        machine
            .endstops
            .iter()
            .find(|e| e.axis == t && !e.probe && e.sensorless.is_none())
            .cloned()
    };
    Some((g, [tower(0)?, tower(1)?, tower(2)?]))
}

/// The kinematics' name when homing is not supported: delta (its towers home together, all
/// three carriages to their endstops: a different sequence). Corexy and corexz axes are homed
/// with all the steppers that move them.
pub(crate) fn unsupported_kinematics(kin: &Kinematics) -> Option<&'static str> {
    match kin {
        Kinematics::Cartesian | Kinematics::CoreXY | Kinematics::CoreXZ => None,
        Kinematics::Delta(_) => Some("delta"),
    }
}

/// The steppers (indices into `machine.steppers`) that move toolhead axis `axis`: every one
/// whose kinematics has a non-zero coefficient for it (corexy X: stepper_x = A and stepper_y =
/// B). A delta tower counts for the axis of its index (delta homing is refused anyway).
pub fn axis_steppers(machine: &Machine, axis: usize) -> Vec<usize> {
    let kin = &machine.options.kinematics;
    (0..machine.steppers.len())
        .filter(|&i| {
            let s = &machine.steppers[i];
            match kin
                .stepper(s.axis, s.step_dist)
                .ok()
                .as_ref()
                .and_then(StepperKin::linear_coeffs)
            {
                Some(c) => c.get(axis).is_some_and(|&v| v != 0.0),
                None => s.axis == axis,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests;
