//! G28 with motion, across MCUs: Klipper's endstop + trsync protocol (`links::trsync`: trigger
//! relay, 25 ms status timeout), the halt position computed on the host.
//!
//! The axis steppers are every stepper that moves the homed axis ([`axis_steppers`]): X's own
//! on a cartesian printer, both motors A (x + y) and B (x − y) for corexy X or Y, A (x + z) and
//! B (x − z) for corexz X or Z. Delta homing is refused (its towers home together).
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

pub mod probe;

use std::fmt;
use std::time::{Duration, Instant};

use links::mcu::McuLink;
use links::trsync::{
    TriggerGroup, TrsyncError, COMM_TIMEOUT_MSG, REASON_ENDSTOP_HIT, REASON_HOST_REQUEST,
    REASON_PAST_END_TIME,
};
use planner::kinematics::{Kinematics, StepperKin};
use planner::pipeline::Pipeline;
use planner::stepgen::StepCmd;
use planner::toolhead::Move;

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
        }
    }
}

impl HomingCtx<'_> {
    /// The earliest print time a command sent now may act at: the lead every step command must
    /// have at the MCU, plus [`START_MARGIN`] (scaled with a fast simulated clock).
    fn earliest_start(&self) -> f64 {
        print_now(self.mcus) + MIN_LEAD_S + START_MARGIN * self.time_scale.max(1.0)
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
                    "; pass {} at {} mm/s: trigger on '{}', overshoot {:.4} mm, stop {:.0}..{:.0} us after trigger",
                    i + 1,
                    p.speed,
                    p.trigger_mcu,
                    p.overshoot_mm,
                    p.last_step_after_s * 1e6,
                    p.next_step_after_s * 1e6
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
pub fn check_config(machine: &Machine) -> Result<(), String> {
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
            return Err(format!(
                "[{}] {} '{}': the steppers of axis {} are on MCUs '{}' while its endstop is on \
                 yet another MCU '{}': put the endstop on one of the steppers' MCUs or all steppers of the \
                 axis on one MCU",
                e.stepper,
                if e.stepper == "probe" {
                    "pin"
                } else {
                    "endstop_pin"
                },
                e.pin,
                AXIS_NAMES[e.axis.min(2)],
                mcus.join("', '"),
                e.pin.mcu
            ));
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
) -> Result<Option<HomingReport>, String> {
    match cmd {
        MotionCmd::Home(axes) => {
            let report = home_axes(ctx, *axes)?;
            out.extend(report.to_string().lines().map(str::to_string));
            Ok(Some(report))
        }
        MotionCmd::Probe { name, raw } => probe::run(ctx, name, raw, out).map(|()| None),
    }
}

/// Homes the named axes (X, Y, Z order) on a live print: `G28` with motion. On success the
/// axes are homed in the G-code state and the planner continues from the homed position.
pub fn home_axes(ctx: &mut HomingCtx<'_>, axes: [bool; 3]) -> Result<HomingReport, String> {
    if !ctx.pipeline.supports_homing() {
        return Err("G28: homing needs the inline planner without pressure advance".to_string());
    }
    check_config(ctx.machine)?;
    let mut report = HomingReport::default();
    for axis in (0..3).filter(|&a| axes[a]) {
        let mut homed = ctx.pipeline.gcode_state().homed();
        homed[axis] = false;
        ctx.pipeline.set_homed(homed);
        match ctx.machine.endstops.iter().find(|e| e.axis == axis).cloned() {
            Some(e) => report.axes.push(home_axis(ctx, &e)?),
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

/// Both passes of one axis.
fn home_axis(ctx: &mut HomingCtx<'_>, e: &EndstopOut) -> Result<AxisReport, String> {
    let axis = e.axis;
    let travel = e.position_max - e.position_min;
    let dir = if e.homing_positive_dir { 1.0 } else { -1.0 };
    let mut passes = Vec::new();
    let start = e.position_endstop - dir * TRAVEL_FACTOR * travel;
    let (first, mcus) = homing_pass(ctx, e, PassKind::Home { start }, e.homing_speed)?;
    passes.push(first);
    let retract = e.homing_retract_dist;
    if retract > 0.0 {
        let mut pos = ctx.pipeline.position();
        pos[axis] = e.position_endstop - dir * retract;
        plain_move(ctx, pos, e.homing_speed)?;
        wait_motion_done(ctx)?;
        if endstop_state(ctx, e)?.1 {
            return Err(format!(
                "Endstop {} still triggered after retract",
                AXIS_NAMES[axis]
            ));
        }
        let start = e.position_endstop - dir * 2.0 * retract;
        let (second, _) = homing_pass(ctx, e, PassKind::Home { start }, e.second_homing_speed)?;
        passes.push(second);
    }
    Ok(AxisReport {
        axis,
        mcus,
        passes,
        position: ctx.pipeline.position()[axis],
    })
}

/// A plain move of the toolhead to `pos` (retract, bench moves), sent at once.
pub fn plain_move(ctx: &mut HomingCtx<'_>, pos: [f64; 4], speed: f64) -> Result<(), String> {
    let t0 = ctx.earliest_start();
    ctx.pipeline.raise_print_time(t0).map_err(|e| e.to_string())?;
    ctx.pipeline.home_move(pos, speed).map_err(|e| e.to_string())?;
    let mut out = Vec::new();
    generate(ctx, &mut out)?;
    push_cmds(ctx, &out)
}

/// Releases the planned step commands, each stepper's in its MCU's clock as the clock fits
/// stand now.
fn generate(ctx: &mut HomingCtx<'_>, out: &mut Vec<(usize, StepCmd)>) -> Result<(), String> {
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
fn push_cmds(ctx: &mut HomingCtx<'_>, out: &[(usize, StepCmd)]) -> Result<(), String> {
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
                return Err(format!(
                    "homing: a step for {} on mcu '{}' was ready only {:.1} ms before it is due (at least {:.0} ms \
                     required)",
                    ctx.machine.steppers.get(idx).map_or("?", |s| s.name.as_str()),
                    m.name,
                    (first_clock as f64 - now[k]) / m.clock_freq * 1e3,
                    MIN_LEAD_S * 1e3
                ));
            }
        }
        ctx.streams.push(idx, cmd, ctx.sinks)?;
    }
    ctx.sinks.iter_mut().try_for_each(|s| s.flush())
}

/// Sends everything planned so far and waits (bounded) until every MCU executed it.
pub fn wait_motion_done(ctx: &mut HomingCtx<'_>) -> Result<(), String> {
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
                return Err(format!("mcu '{}': {e}", conn.name));
            }
            if Instant::now() > deadline {
                return Err(format!(
                    "homing: the clock of mcu '{}' did not reach the end of the planned moves in time",
                    conn.name
                ));
            }
            std::thread::sleep(Duration::from_millis(1));
        }
    }
    Ok(ctx.mcus.check()?)
}

/// `query` with retries (the reply of an idempotent query can be lost on a noisy line).
fn query<'m>(
    mcus: &'m Mcus,
    mcu_name: &str,
    name: &str,
    oid: u8,
    response: &str,
) -> Result<(&'m McuConn, links::dict::Message), String> {
    let conn = mcu(mcus, mcu_name)?;
    let cmd = conn
        .link
        .dictionary()
        .encode(name, &[oid as i64])
        .map_err(|e| format!("mcu '{}': {e}", conn.name))?;
    let mut last = String::new();
    for _ in 0..QUERY_TRIES {
        match conn
            .link
            .query(cmd, response, Some(("oid", oid as i64)), QUERY_TIMEOUT)
        {
            Ok(m) => return Ok((conn, m)),
            Err(e @ links::mcu::LinkError::Timeout { .. }) => last = e.to_string(),
            Err(e) => return Err(e.to_string()),
        }
    }
    Err(last)
}

fn mcu<'m>(mcus: &'m Mcus, name: &str) -> Result<&'m McuConn, String> {
    mcus.get(name)
        .ok_or_else(|| format!("homing: no MCU called '{name}'"))
}

/// Net steps of stepper `idx` as the host counts them (the MCU's count, sign-corrected for an
/// inverted dir pin).
pub fn stepper_position(ctx: &HomingCtx<'_>, idx: usize) -> Result<i64, String> {
    let s = &ctx.machine.steppers[idx];
    let (_, reply) = query(
        ctx.mcus,
        &s.mcu,
        "stepper_get_position",
        s.oid,
        "stepper_position",
    )?;
    let raw = reply.get("pos").ok_or("stepper_position without pos")?;
    Ok(if s.dir_pin.invert { -raw } else { raw })
}

/// (`next_clock` extended to 64 bits, the pin reads triggered, still homing) of endstop `e`.
pub(crate) fn endstop_state(ctx: &HomingCtx<'_>, e: &EndstopOut) -> Result<(u64, bool, bool), String> {
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

/// n(x) = ⌊x / step_dist + ½⌋.
fn step_index(x: f64, step_dist: f64) -> i64 {
    (x / step_dist + 0.5).floor() as i64
}

/// Print time at which stepper `kin` (linear) reaches position `x` (mm) in `mv` (clamped to
/// the move; its end when the stepper does not move).
fn time_at_stepper_pos(mv: &Move, kin: &StepperKin, x: f64) -> f64 {
    let r = kin
        .linear_coeffs()
        .map_or(0.0, |c| c.iter().zip(&mv.axes_r).map(|(k, r)| k * r).sum::<f64>());
    if r == 0.0 {
        return mv.end_time();
    }
    let s = ((x - kin.position(&mv.start_pos)) / r).clamp(0.0, mv.move_d);
    mv.print_time + mv.time_at_distance(s)
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

/// Where a homing or probing move cut short by the MCUs left the toolhead, from step indices
/// (module doc, step 6) and forward kinematics: what [`halt_position`] computes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Halt {
    /// Toolhead X, Y, Z of the rails where the group's steppers halted.
    pub halted: [f64; 3],
    /// Toolhead X, Y, Z of the rails at the step indices commanded at the trigger time.
    pub triggered: [f64; 3],
    /// The axes the group's steppers move: only these are recomputed, the others keep the
    /// move's coordinates.
    pub moved: [bool; 3],
}

impl Halt {
    /// The toolhead after a homing pass of `axis` whose trigger defines `position_endstop`:
    /// that plus the overshoot on `axis` (halted − triggered), the halted coordinates on the
    /// other moved axes, `pos` elsewhere.
    pub fn homed(&self, pos: [f64; 4], axis: usize, position_endstop: f64) -> [f64; 4] {
        let mut p = self.halted_at(pos);
        p[axis] = position_endstop + (self.halted[axis] - self.triggered[axis]);
        p
    }

    /// `pos` with the moved axes at their halted coordinates.
    pub fn halted_at(&self, pos: [f64; 4]) -> [f64; 4] {
        let mut p = pos;
        for a in (0..3).filter(|&a| self.moved[a]) {
            p[a] = self.halted[a];
        }
        p
    }
}

/// One stepper of a homing group for [`halt_position`]: its rail (0..=2), its kinematics and
/// the net steps the MCU says it took during the move.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct GroupStepper {
    pub rail: usize,
    pub kin: StepperKin,
    pub net_steps: i64,
}

/// The position computation of one pass on linear kinematics. Per rail (its first stepper in
/// `group`): `n_start = n(stepper position at the move's start)`, `n_halt = n_start +
/// net_steps`, `n_trig = n(stepper position commanded at print time t_trig)` with `n(x) = ⌊x /
/// step_dist + ½⌋`; the rails no stepper of the group drives keep their start positions.
/// Forward kinematics of `n_halt · step_dist` and `n_trig · step_dist` give the halted and the
/// triggered toolhead positions (corexy: x = (a + b) / 2, y = (a − b) / 2). `None` when a
/// stepper's kinematics is not linear (delta).
pub(crate) fn halt_position(
    kin: &Kinematics,
    mv: &Move,
    group: &[GroupStepper],
    t_trig: f64,
) -> Option<Halt> {
    let start = [mv.start_pos[0], mv.start_pos[1], mv.start_pos[2]];
    let mut halted = kin.inverse(start);
    let mut triggered = halted;
    let mut seen = [false; 3];
    let mut moved = [false; 3];
    let t_rel = (t_trig - mv.print_time).clamp(0.0, mv.duration());
    for g in group {
        let c = g.kin.linear_coeffs()?;
        for a in 0..3 {
            moved[a] |= c[a] != 0.0;
        }
        let Some(first) = seen.get_mut(g.rail).filter(|s| !**s) else {
            continue;
        };
        *first = true;
        let sd = g.kin.step_dist;
        let n_start = step_index(g.kin.position(&mv.start_pos), sd);
        halted[g.rail] = (n_start + g.net_steps) as f64 * sd;
        triggered[g.rail] = step_index(g.kin.position_at(mv, t_rel), sd) as f64 * sd;
    }
    Some(Halt {
        halted: kin.forward(halted),
        triggered: kin.forward(triggered),
        moved,
    })
}

/// One homing move of endstop `e`'s axis (see [`PassKind`]). Returns the pass report and the
/// group's MCU names.
pub(crate) fn homing_pass(
    ctx: &mut HomingCtx<'_>,
    e: &EndstopOut,
    kind: PassKind,
    speed: f64,
) -> Result<(PassReport, Vec<String>), String> {
    let axis = e.axis;
    let axis_name = AXIS_NAMES[axis];
    let kinematics = ctx.machine.options.kinematics;
    if let Some(kin) = unsupported_kinematics(&kinematics) {
        return Err(format!(
            "homing {axis_name}: {kin} kinematics is not supported: its towers home together, \
             which Cadence does not do yet (cartesian, corexy and corexz axes can be homed)"
        ));
    }
    // From before the move is queued until the stop is read back: no CPU halts meanwhile.
    let _idle_poll = ctx.rt.start_idle_poll();
    wait_motion_done(ctx)?;
    let g = PassGroup::new(ctx.mcus, ctx.machine, e)?;
    let endstop_conn = g.conns[0];
    let before: Vec<i64> = g
        .idxs
        .iter()
        .map(|&i| stepper_position(ctx, i))
        .collect::<Result<_, _>>()?;

    let mut pos = ctx.pipeline.position();
    let mut target = pos;
    match kind {
        PassKind::Home { start } => {
            pos[axis] = start;
            ctx.pipeline.set_toolhead_position(pos);
            target = pos;
            target[axis] = e.position_endstop;
        }
        PassKind::Probe { target: to } => target[axis] = to,
    }

    let (group, t0, rest_ticks) = arm_pass(ctx, &g, e, speed)?;
    let sent = send_homing_move(ctx, target, speed, axis_name);
    let outcome = match &sent {
        Ok(mv) => {
            let main = ctx.mcus.main();
            let end_sys = main.link.clock().system_time_at(mv.end_time() * main.clock_freq);
            let wait = (end_sys - McuLink::system_now()).clamp(0.0, 1e6);
            group.wait(Instant::now() + Duration::from_secs_f64(wait) + END_GRACE)
        }
        Err(_) => Err(TrsyncError::NotTriggered),
    };
    let received_at = outcome.as_ref().map_or(0.0, |o| o.received_at);
    // Whatever happened: every member stops, the endstop stops sampling.
    let reason = match &outcome {
        Err(TrsyncError::NotTriggered) => REASON_PAST_END_TIME,
        _ => REASON_HOST_REQUEST,
    };
    group.trigger_all(reason);
    restop(ctx, &g.conns, &g.idxs);
    let cancel = endstop_conn
        .link
        .dictionary()
        .encode(
            "endstop_home",
            &[e.oid as i64, 0, 0, 0, 0, 0, endstop_conn.trsync_oid as i64, 0],
        )
        .map_err(|x| x.to_string())
        .and_then(|c| endstop_conn.link.send(c).map_err(|x| x.to_string()));
    let mv = match sent {
        Ok(mv) => mv,
        Err(err) => {
            group.close();
            quiet(&g.conns);
            return Err(err);
        }
    };
    // The trigger clock, and where the steppers halted.
    let trig = match &outcome {
        Ok(o) if o.reason == REASON_ENDSTOP_HIT => {
            trigger_clock(ctx, e, endstop_conn, &o.mcu, t0, rest_ticks).map(Some)
        }
        _ => Ok(None),
    };
    let after: Result<Vec<i64>, String> = g.idxs.iter().map(|&i| stepper_position(ctx, i)).collect();
    // The relay to the axis steppers' MCU (written by now: `restop` waited for its link).
    let stepper_mcu = &ctx.machine.steppers[g.idxs[0]].mcu;
    let relay_written_at = g
        .names
        .iter()
        .position(|n| n == stepper_mcu && *n != e.pin.mcu)
        .and_then(|i| group.trigger_written_at(i));
    group.close();
    quiet(&g.conns);
    let primary_error = pass_error(ctx, outcome, axis_name, kind);
    let after = match after {
        Ok(a) => a,
        Err(err) => return Err(primary_error.unwrap_or(err)),
    };
    let stopped = Stopped::new(ctx, &g, &before, &after);
    let (trig, error) = match (primary_error, trig) {
        (Some(err), _) => (None, Some(err)),
        (None, Ok(Some(t))) => (Some(t), None),
        (None, Ok(None)) => (None, Some(format!("homing {axis_name}: no trigger clock"))),
        (None, Err(err)) => (None, Some(err)),
    };
    let (Some((trigger_mcu, trigger_clock)), None) = (trig, error.clone()) else {
        // Keep host and MCU in agreement (positions in the pretended frame; axis not homed).
        if let Ok(halt) = stopped.halt_at(&mv, mv.print_time, axis_name) {
            let _ = stopped.resync(ctx, halt.halted_at(ctx.pipeline.position()));
        }
        return Err(error.unwrap_or_else(|| format!("homing {axis_name}: failed")));
    };
    cancel?;
    let trig_conn = mcu(ctx.mcus, &trigger_mcu)?;
    let t_trig = print_time_of_clock(ctx.mcus, trig_conn, trigger_clock);
    let halt = stopped.halt_at(&mv, t_trig, axis_name)?;
    let dir = if mv.axes_r[axis] >= 0.0 { 1.0 } else { -1.0 };
    let overshoot_mm = (halt.halted[axis] - halt.triggered[axis]) * dir + 0.0;
    let (position, trigger_position) = match kind {
        PassKind::Home { .. } => (
            halt.homed(ctx.pipeline.position(), axis, e.position_endstop),
            e.position_endstop,
        ),
        PassKind::Probe { .. } => (halt.halted_at(ctx.pipeline.position()), halt.triggered[axis]),
    };
    let (last_step, next_step) = stop_bounds(&mv, &g.kins[0], stopped.group[0].net_steps);
    stopped.resync(ctx, position)?;
    Ok((
        PassReport {
            speed,
            trigger_mcu,
            trigger_clock,
            trigger_print_time: t_trig,
            overshoot_mm,
            trigger_position,
            steps: after[0] - before[0],
            last_step_after_s: last_step - t_trig,
            next_step_after_s: next_step - t_trig,
            trigger_received_at: received_at,
            relay_written_at,
        },
        g.names,
    ))
}

/// The steppers and MCUs of one pass: every stepper that moves the axis stops on the trigger
/// (corexy X: A and B); the trsync group is the endstop's MCU first, then the steppers'.
struct PassGroup<'m> {
    /// The axis steppers (machine order) and their kinematics.
    idxs: Vec<usize>,
    kins: Vec<StepperKin>,
    /// MCU names, the endstop's first.
    names: Vec<String>,
    conns: Vec<&'m McuConn>,
    /// mm the first stepper moves per mm of the axis (1 on cartesian and core* rails): the
    /// endstop samples about once per step of it.
    axis_coeff: f64,
}

impl<'m> PassGroup<'m> {
    fn new(mcus: &'m Mcus, machine: &Machine, e: &EndstopOut) -> Result<PassGroup<'m>, String> {
        let axis_name = AXIS_NAMES[e.axis];
        let idxs = axis_steppers(machine, e.axis);
        if idxs.is_empty() {
            return Err(format!("homing {axis_name}: the axis has no stepper"));
        }
        let mut kins = Vec::with_capacity(idxs.len());
        for &i in &idxs {
            let s = &machine.steppers[i];
            kins.push(
                machine
                    .options
                    .kinematics
                    .stepper(s.axis, s.step_dist)
                    .map_err(|err| format!("homing {axis_name}: {}: {err}", s.name))?,
            );
        }
        let axis_coeff = kins[0].linear_coeffs().map_or(1.0, |c| c[e.axis].abs()).max(1e-9);
        let mut names = vec![e.pin.mcu.clone()];
        for &i in &idxs {
            let m = &machine.steppers[i].mcu;
            if !names.contains(m) {
                names.push(m.clone());
            }
        }
        let conns = names
            .iter()
            .map(|n| mcu(mcus, n))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(PassGroup {
            idxs,
            kins,
            names,
            conns,
            axis_coeff,
        })
    }
}

/// Arms the pass: the trsyncs (then a round trip per member: every `trsync_state` still in
/// flight from the previous pass, as a triggered trsync keeps reporting, has arrived before the
/// group listens), the trigger group, and the endstop only after that, so no trigger can be
/// missed. Returns the group, the move's start print time and the endstop's rest ticks.
fn arm_pass(
    ctx: &mut HomingCtx<'_>,
    g: &PassGroup<'_>,
    e: &EndstopOut,
    speed: f64,
) -> Result<(TriggerGroup, f64, u64), String> {
    let timeout = TriggerGroup::default_timeout(g.conns.len());
    let members: Vec<(&McuLink, u8)> = g.conns.iter().map(|c| (&c.link, c.trsync_oid)).collect();
    let t_arm = ctx.earliest_start();
    if let Err(err) = arm(ctx, &g.conns, &g.idxs, t_arm, timeout).and_then(|()| barrier(&g.conns)) {
        quiet(&g.conns);
        return Err(err);
    }
    let group = TriggerGroup::new(&members, timeout).map_err(|e| e.to_string())?;
    let t0 = ctx.earliest_start().max(ctx.pipeline.toolhead_print_time());
    let sample_dist = ctx.machine.steppers[g.idxs[0]].step_dist / g.axis_coeff;
    let setup = ctx
        .pipeline
        .raise_print_time(t0)
        .map_err(|e| e.to_string())
        .and_then(|()| arm_endstop(ctx, e, g.conns[0], sample_dist, t0, speed));
    match setup {
        Ok(rest_ticks) => Ok((group, t0, rest_ticks)),
        Err(err) => {
            group.trigger_all(REASON_HOST_REQUEST);
            group.close();
            quiet(&g.conns);
            Err(err)
        }
    }
}

/// Plans the homing move to `target` and sends all its steps.
fn send_homing_move(
    ctx: &mut HomingCtx<'_>,
    target: [f64; 4],
    speed: f64,
    axis_name: char,
) -> Result<Move, String> {
    let Some(mv) = ctx.pipeline.home_move(target, speed).map_err(|e| e.to_string())? else {
        return Err(format!("homing {axis_name}: the homing move has no length"));
    };
    let mut out = Vec::new();
    generate(ctx, &mut out)?;
    push_cmds(ctx, &out)?;
    Ok(mv)
}

/// The trigger clock the endstop MCU reports (after a trigger it reports the matching read's
/// clock + `rest_ticks`), checked to be after the move's start `t0`.
fn trigger_clock(
    ctx: &HomingCtx<'_>,
    e: &EndstopOut,
    endstop_conn: &McuConn,
    reporter: &str,
    t0: f64,
    rest_ticks: u64,
) -> Result<(String, u64), String> {
    let (next, _, homing) = endstop_state(ctx, e)?;
    let c = next.saturating_sub(rest_ticks);
    if homing || c < clock_at_print_time(ctx.mcus, endstop_conn, t0) {
        return Err(format!(
            "homing {}: '{reporter}' reported a trigger but the endstop did not trigger",
            AXIS_NAMES[e.axis]
        ));
    }
    Ok((e.pin.mcu.clone(), c))
}

/// The error a pass ends with, if any, from the trigger group's outcome.
fn pass_error(
    ctx: &mut HomingCtx<'_>,
    outcome: Result<links::trsync::TriggerOutcome, TrsyncError>,
    axis_name: char,
    kind: PassKind,
) -> Option<String> {
    match outcome {
        Ok(o) if o.reason == REASON_ENDSTOP_HIT => None,
        Ok(o) => Some(format!(
            "homing {axis_name}: the move stopped with trigger reason {}",
            o.reason
        )),
        Err(TrsyncError::CommTimeout { detail, .. }) => {
            ctx.comm_timeout_detail = Some(detail);
            Some(COMM_TIMEOUT_MSG.to_string())
        }
        Err(TrsyncError::NotTriggered) => {
            let trigger_name = match kind {
                PassKind::Home { .. } => axis_name.to_string(),
                PassKind::Probe { .. } => "probe".to_string(),
            };
            Some(format!("No trigger on {trigger_name} after full movement"))
        }
        Err(other) => Some(other.to_string()),
    }
}

/// Where the pass's steppers stopped, to compute the halt position and resync the planner.
struct Stopped {
    kinematics: Kinematics,
    group: Vec<GroupStepper>,
    /// (stepper, MCU position) of each.
    positions: Vec<(usize, i64)>,
    /// Each stopped stepper's MCU clock when read (they are idle from here on).
    now_clocks: Vec<u64>,
    /// The print time the next move may start at.
    resume: f64,
}

impl Stopped {
    fn new(ctx: &HomingCtx<'_>, g: &PassGroup<'_>, before: &[i64], after: &[i64]) -> Stopped {
        let group = g
            .idxs
            .iter()
            .zip(&g.kins)
            .zip(after.iter().zip(before))
            .map(|((&i, &kin), (a, b))| GroupStepper {
                rail: ctx.machine.steppers[i].axis,
                kin,
                net_steps: a - b,
            })
            .collect();
        let now_clocks = g
            .idxs
            .iter()
            .map(|&i| {
                let conn = ctx.mcus.get(&ctx.machine.steppers[i].mcu);
                conn.map_or(0.0, |c| c.link.clock().clock_at(McuLink::system_now()))
                    .max(0.0) as u64
            })
            .collect();
        Stopped {
            kinematics: ctx.machine.options.kinematics,
            group,
            positions: g.idxs.iter().copied().zip(after.iter().copied()).collect(),
            now_clocks,
            resume: ctx.earliest_start(),
        }
    }

    /// Where the steppers halted and where the trigger at `t_trig` found them.
    fn halt_at(&self, mv: &Move, t_trig: f64, axis_name: char) -> Result<Halt, String> {
        halt_position(&self.kinematics, mv, &self.group, t_trig)
            .ok_or_else(|| format!("homing {axis_name}: the kinematics is not linear"))
    }

    /// The planner and the step streams continue from `p`, where the steppers stopped.
    fn resync(&self, ctx: &mut HomingCtx<'_>, p: [f64; 4]) -> Result<(), String> {
        ctx.pipeline
            .resync_after_stop(self.resume, p, &self.positions)
            .map_err(|e| e.to_string())?;
        for (&(i, _), &now_clock) in self.positions.iter().zip(&self.now_clocks) {
            ctx.streams.note_stopped(i, now_clock);
        }
        Ok(())
    }
}

/// When the first stepper's last executed step and its first cancelled one were due: its
/// last step reached index n_halt at boundary (n_halt − sdir·½)·sd, sdir its direction.
fn stop_bounds(mv: &Move, kin0: &StepperKin, net_steps: i64) -> (f64, f64) {
    let sd = kin0.step_dist;
    let n_halt = step_index(kin0.position(&mv.start_pos), sd) + net_steps;
    let sdir = if kin0.position_at(mv, mv.duration()) >= kin0.position(&mv.start_pos) {
        1.0
    } else {
        -1.0
    };
    let last_b = (n_halt as f64 - 0.5 * sdir) * sd;
    (
        time_at_stepper_pos(mv, kin0, last_b),
        time_at_stepper_pos(mv, kin0, last_b + sdir * sd),
    )
}

/// Stops the axis steppers a second time once every step command queued before the trigger
/// has reached its MCU: the trigger overtakes queued messages, and a `queue_step` arriving
/// after the stop would start the stepper again (the firmware accepts steps after a stop).
/// Per stepper MCU: wait until its link is idle, re-arm its trsync (no reports), attach the
/// axis steppers, trigger it. Best effort (a dead link stops nothing anyway).
fn restop(ctx: &HomingCtx<'_>, conns: &[&McuConn], idxs: &[usize]) {
    for c in conns {
        let attached: Vec<i64> = idxs
            .iter()
            .map(|&i| &ctx.machine.steppers[i])
            .filter(|s| s.mcu == c.name)
            .map(|s| s.oid as i64)
            .collect();
        if attached.is_empty() || c.link.wait_idle(Duration::from_secs(2)).is_err() {
            continue;
        }
        let dict = c.link.dictionary();
        let oid = c.trsync_oid as i64;
        let mut cmds = vec![dict.encode("trsync_start", &[oid, 0, 0, 0])];
        for s in &attached {
            cmds.push(dict.encode("stepper_stop_on_trigger", &[*s, oid]));
        }
        cmds.push(dict.encode("trsync_trigger", &[oid, REASON_HOST_REQUEST as i64]));
        for cmd in cmds.into_iter().flatten() {
            let _ = c.link.send(cmd);
        }
    }
}

/// One `get_clock` round trip per MCU: everything each sent before it has been received.
fn barrier(conns: &[&McuConn]) -> Result<(), String> {
    for c in conns {
        let cmd = c
            .link
            .dictionary()
            .encode("get_clock", &[])
            .map_err(|x| format!("mcu '{}': {x}", c.name))?;
        let mut result = Ok(());
        for _ in 0..QUERY_TRIES {
            result = c.link.query(cmd, "clock", None, QUERY_TIMEOUT).map(|_| ());
            if !matches!(result, Err(links::mcu::LinkError::Timeout { .. })) {
                break;
            }
        }
        result.map_err(|x| x.to_string())?;
    }
    Ok(())
}

/// Stops the periodic reports of the group's trsyncs (re-armed without reports or expiry,
/// no stepper attached) until the next homing move. Best effort.
fn quiet(conns: &[&McuConn]) {
    for c in conns {
        if let Ok(cmd) = c
            .link
            .dictionary()
            .encode("trsync_start", &[c.trsync_oid as i64, 0, 0, 0])
        {
            let _ = c.link.send(cmd);
        }
    }
}

/// Starts the trsyncs of the group (reports from ~10 ms on, expiry at `t_arm` + timeout until
/// the host extends it) and attaches the axis steppers.
fn arm(
    ctx: &HomingCtx<'_>,
    conns: &[&McuConn],
    idxs: &[usize],
    t_arm: f64,
    timeout: f64,
) -> Result<(), String> {
    let now = McuLink::system_now();
    for c in conns {
        let dict = c.link.dictionary();
        let est = c.link.clock();
        let freq = if est.is_valid() { est.freq() } else { c.clock_freq };
        // The first report must come well inside the group's timeout (the host watches for
        // silence from the moment the group is made), yet its clock must not have passed when
        // `trsync_start` arrives: Klipper's firmware shuts down ("Timer too close") if it has.
        let report_clock = est.clock_at(now + FIRST_REPORT_DELAY).max(0.0) as u64;
        let report_ticks = (0.3 * timeout * freq) as u64;
        let expire = clock_at_print_time(ctx.mcus, c, t_arm).max(report_clock) + (timeout * freq) as u64;
        let oid = c.trsync_oid as i64;
        let enc = |name: &str, args: &[i64]| {
            dict.encode(name, args)
                .map_err(|x| format!("mcu '{}': {x}", c.name))
        };
        let mut cmds = vec![
            enc(
                "trsync_start",
                &[
                    oid,
                    report_clock as u32 as i64,
                    report_ticks as i64,
                    links::trsync::REASON_COMMS_TIMEOUT as i64,
                ],
            )?,
            enc("trsync_set_timeout", &[oid, expire as u32 as i64])?,
        ];
        for &i in idxs {
            let s = &ctx.machine.steppers[i];
            if s.mcu == c.name {
                cmds.push(enc("stepper_stop_on_trigger", &[s.oid as i64, oid])?);
            }
        }
        for cmd in cmds {
            c.link.send(cmd).map_err(|x| x.to_string())?;
        }
    }
    Ok(())
}

/// Arms endstop `e` on its MCU `c` to sample from print time `t0` at a rest time of about one
/// step at `speed` (clamped to [`MIN_REST_TIME`, `MAX_REST_TIME`]); returns the rest time in
/// ticks (the trigger clock is `endstop_state`'s `next_clock` minus it).
fn arm_endstop(
    ctx: &HomingCtx<'_>,
    e: &EndstopOut,
    c: &McuConn,
    step_dist: f64,
    t0: f64,
    speed: f64,
) -> Result<u64, String> {
    let rest_time = (step_dist / speed.max(1e-6)).clamp(MIN_REST_TIME, MAX_REST_TIME);
    let rest_ticks = (rest_time * c.clock_freq).round().max(1.0) as u64;
    let clock = clock_at_print_time(ctx.mcus, c, t0);
    let cmd = c
        .link
        .dictionary()
        .encode(
            "endstop_home",
            &[
                e.oid as i64,
                clock as u32 as i64,
                (SAMPLE_TIME * c.clock_freq).round().max(1.0) as i64,
                SAMPLE_COUNT as i64,
                rest_ticks as i64,
                !e.pin.invert as i64,
                c.trsync_oid as i64,
                REASON_ENDSTOP_HIT as i64,
            ],
        )
        .map_err(|x| format!("mcu '{}': {x}", c.name))?;
    c.link.send(cmd).map_err(|x| x.to_string())?;
    Ok(rest_ticks)
}

#[cfg(test)]
mod tests;
