//! One homing or probing pass with the MCUs in the loop: the trsync group armed on every
//! involved MCU, the endstop armed, the homing move sent, the trigger awaited and relayed,
//! every member stopped, the trigger clock and the stepper positions read back, and the
//! planner resynced to where the steppers halted (see the homing module docs, steps 1–6).

use std::time::{Duration, Instant};

use links::mcu::McuLink;
use links::trsync::{
    TriggerGroup, TrsyncError, REASON_ENDSTOP_HIT, REASON_HOST_REQUEST, REASON_PAST_END_TIME,
};
use planner::kinematics::{Kinematics, StepperKin};
use planner::toolhead::Move;

use super::halt::{halt_position, stop_bounds, GroupStepper, Halt};
use super::*;
use crate::hardware::{EndstopOut, Machine};
use crate::mcus::{McuConn, Mcus};

/// What one pass moves and arms beyond its endstop's axis: the pass's own description, handed
/// in by its caller, so nothing of it outlives the pass. The default (no further endstops, every
/// stepper of the axis) is an ordinary homing or probing pass.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct PassPlan<'p> {
    /// With several endstops on one axis (`[stepper_z1] endstop_pin`), while one of them homes
    /// its own motors, the axis' others held still: those motors (indices into
    /// `machine.steppers`); `None`: every stepper that moves the axis.
    pub motors: Option<&'p [usize]>,
    /// Endstops armed beside the pass's own, the first of all to trigger stopping it (the
    /// further motors' own, while all the axis' motors approach together).
    pub also_endstops: &'p [EndstopOut],
    /// While a delta tower is homed (its carriage alone moving with Z, `homing::delta`): which.
    pub tower: Option<usize>,
}

/// One homing move of endstop `e`'s axis (see [`PassKind`]), its motors and further endstops
/// as `plan` says. Returns the pass report and the group's MCU names.
pub(crate) fn homing_pass(
    ctx: &mut HomingCtx<'_>,
    e: &EndstopOut,
    kind: PassKind,
    speed: f64,
    plan: PassPlan<'_>,
) -> Result<(PassReport, Vec<String>), HomingError> {
    let axis = e.axis;
    let axis_name = AXIS_NAMES[axis];
    check_kinematics(ctx, axis_name, plan.tower)?;
    // From before the move is queued until the stop is read back: no CPU halts meanwhile.
    let _idle_poll = ctx.rt.start_idle_poll();
    wait_motion_done(ctx)?;
    let mut g = PassGroup::new(ctx.mcus, ctx.machine, e, plan.tower, plan.motors)?;
    // Further endstops armed beside `e` (the first of all to trigger stops the pass).
    g.add_endstop_mcus(ctx.mcus, plan.also_endstops)?;
    let armed: Vec<&EndstopOut> = std::iter::once(e).chain(plan.also_endstops).collect();
    let before: Vec<i64> = g
        .idxs
        .iter()
        .map(|&i| stepper_position(ctx, i))
        .collect::<Result<_, _>>()?;
    let target = pass_target(ctx, e, kind);
    let steps = g.steps_between(ctx.machine, ctx.pipeline.position(), target);

    let allowance = ctx.generation_allowance(steps);
    let (group, t0, rest_ticks) = arm_pass(ctx, &g, &armed, speed, allowance)?;
    let sent = send_homing_move(ctx, target, speed, axis_name, steps);
    let outcome = await_trigger(ctx, &group, &sent);
    let received_at = outcome.as_ref().map_or(0.0, |o| o.received_at);
    let cancel = stop_pass(ctx, &g, &armed, &group, &outcome);
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
            trigger_clock(ctx, &armed, &o.mcu, t0, &rest_ticks).map(Some)
        }
        _ => Ok(None),
    };
    let after: Result<Vec<i64>, HomingError> = g.idxs.iter().map(|&i| stepper_position(ctx, i)).collect();
    let relay_written_at = relay_written_at(ctx, &g, e, &group);
    group.close();
    quiet(&g.conns);
    let primary_error = pass_error(ctx, outcome, axis_name, kind);
    let after = match after {
        Ok(a) => a,
        Err(err) => return Err(primary_error.unwrap_or(err)),
    };
    let stopped = Stopped::new(ctx, &g, &before, &after);
    let (trigger_mcu, trigger_clock) = match (primary_error, trig) {
        (None, Ok(Some(t))) => t,
        (Some(err), _) | (None, Err(err)) => return Err(stopped.give_up(ctx, &mv, axis_name, err)),
        (None, Ok(None)) => {
            let err = HomingError::NoTriggerClock { axis: axis_name };
            return Err(stopped.give_up(ctx, &mv, axis_name, err));
        }
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

/// Refuses a pass on kinematics whose axes do not home one at a time (delta), but for a
/// delta tower's own pass (`tower`).
fn check_kinematics(ctx: &HomingCtx<'_>, axis: char, tower: Option<usize>) -> Result<(), HomingError> {
    // A delta's towers are homed one at a time (homing::delta), each pass a carriage's own.
    match unsupported_kinematics(&ctx.machine.options.kinematics).filter(|_| tower.is_none()) {
        Some(kinematics) => Err(HomingError::UnsupportedKinematics { axis, kinematics }),
        None => Ok(()),
    }
}

/// When the host wrote the trigger's relay to the axis steppers' MCU (written by now:
/// `restop` waited for its link); `None` with the endstop on that MCU.
fn relay_written_at(
    ctx: &HomingCtx<'_>,
    g: &PassGroup<'_>,
    e: &EndstopOut,
    group: &TriggerGroup,
) -> Option<f64> {
    let stepper_mcu = &ctx.machine.steppers[g.idxs[0]].mcu;
    g.names
        .iter()
        .position(|n| n == stepper_mcu && *n != e.pin.mcu)
        .and_then(|i| group.trigger_written_at(i))
}

/// Where the pass's move heads: G28 pretends the toolhead starts at `start` (and sets it
/// there) and heads for `position_endstop`; PROBE heads for its target from where it is.
fn pass_target(ctx: &mut HomingCtx<'_>, e: &EndstopOut, kind: PassKind) -> [f64; 4] {
    let mut pos = ctx.pipeline.position();
    let mut target = pos;
    match kind {
        PassKind::Home { start } => {
            pos[e.axis] = start;
            ctx.pipeline.set_toolhead_position(pos);
            target = pos;
            target[e.axis] = e.position_endstop;
        }
        PassKind::Probe { target: to } => target[e.axis] = to,
    }
    target
}

/// Waits for the trigger until the move's end (plus a grace); a move that was not sent never
/// triggers.
fn await_trigger(
    ctx: &HomingCtx<'_>,
    group: &TriggerGroup,
    sent: &Result<Move, HomingError>,
) -> Result<links::trsync::TriggerOutcome, TrsyncError> {
    match sent {
        Ok(mv) => {
            let main = ctx.mcus.main();
            let end_sys = main.link.clock().system_time_at(mv.end_time() * main.clock_freq);
            let wait = (end_sys - McuLink::system_now()).clamp(0.0, 1e6);
            group.wait(Instant::now() + Duration::from_secs_f64(wait) + END_GRACE)
        }
        Err(_) => Err(TrsyncError::NotTriggered),
    }
}

/// Whatever happened: every member stops, the armed endstops stop sampling. Returns the
/// result of cancelling them (an error there matters only after a good trigger).
fn stop_pass(
    ctx: &HomingCtx<'_>,
    g: &PassGroup<'_>,
    armed: &[&EndstopOut],
    group: &TriggerGroup,
    outcome: &Result<links::trsync::TriggerOutcome, TrsyncError>,
) -> Result<(), HomingError> {
    let reason = match outcome {
        Err(TrsyncError::NotTriggered) => REASON_PAST_END_TIME,
        _ => REASON_HOST_REQUEST,
    };
    group.trigger_all(reason);
    restop(ctx, &g.conns, &g.idxs);
    let mut cancelled = Ok(());
    for e in armed {
        let conn = mcu(ctx.mcus, &e.pin.mcu)?;
        let cancel = conn.link.dictionary().encode(
            "endstop_home",
            &[e.oid as i64, 0, 0, 0, 0, 0, conn.trsync_oid as i64, 0],
        )?;
        cancelled = cancelled.and(conn.link.send(cancel).map_err(HomingError::from));
    }
    cancelled
}

/// The steppers and MCUs of one pass: every stepper that moves the axis stops on the trigger
/// (corexy X: A and B); the trsync group is the endstop's MCU first, then the steppers'.
pub(super) struct PassGroup<'m> {
    /// The axis steppers (machine order) and their kinematics.
    idxs: Vec<usize>,
    kins: Vec<StepperKin>,
    /// MCU names, the endstop's first.
    names: Vec<String>,
    conns: Vec<&'m McuConn>,
    /// mm the first stepper moves per mm of the axis (1 on cartesian and core* rails): the
    /// endstop samples about once per step of it.
    axis_coeff: f64,
    /// The kinematics the halt is computed in, and each stepper's rail in it: the printer's;
    /// for a delta tower's pass (its carriage alone moving with Z), cartesian Z.
    kinematics: Kinematics,
    rails: Vec<usize>,
}

impl<'m> PassGroup<'m> {
    /// Steps the group's steppers take in all on a move from `from` to `to`.
    pub(super) fn steps_between(&self, machine: &Machine, from: [f64; 4], to: [f64; 4]) -> f64 {
        self.idxs
            .iter()
            .zip(&self.kins)
            .map(|(&i, kin)| {
                let travel = match kin.linear_coeffs() {
                    Some(c) => (0..4).map(|a| c[a] * (to[a] - from[a])).sum::<f64>(),
                    None => (0..3).map(|a| (to[a] - from[a]).powi(2)).sum::<f64>().sqrt(),
                };
                travel.abs() / machine.steppers[i].step_dist.max(1e-12)
            })
            .sum()
    }

    /// Makes the MCUs of endstops `also` (armed beside the pass's own) members too, after the
    /// pass endstop's.
    fn add_endstop_mcus(&mut self, mcus: &'m Mcus, also: &[EndstopOut]) -> Result<(), HomingError> {
        for e in also {
            if !self.names.contains(&e.pin.mcu) {
                self.names.insert(1, e.pin.mcu.clone());
                self.conns.insert(1, mcu(mcus, &e.pin.mcu)?);
            }
        }
        Ok(())
    }

    /// The group of endstop `e`'s pass; with `tower`, the pass of that delta tower's steppers
    /// (the other towers held still), whose carriage follows a Z move at the centre one to one;
    /// with `motors`, of those motors alone (one endstop's of an axis with several).
    fn new(
        mcus: &'m Mcus,
        machine: &Machine,
        e: &EndstopOut,
        tower: Option<usize>,
        motors: Option<&[usize]>,
    ) -> Result<PassGroup<'m>, HomingError> {
        let axis_name = AXIS_NAMES[e.axis];
        let idxs = match (tower, motors) {
            (Some(t), _) => (0..machine.steppers.len())
                .filter(|&i| machine.steppers[i].axis == t)
                .collect(),
            (None, Some(m)) => m.to_vec(),
            (None, None) => axis_steppers(machine, e.axis),
        };
        if idxs.is_empty() {
            return Err(HomingError::NoStepper { axis: axis_name });
        }
        let mut kins = Vec::with_capacity(idxs.len());
        for &i in &idxs {
            let s = &machine.steppers[i];
            if tower.is_some() {
                kins.push(StepperKin::axis(e.axis, s.step_dist));
                continue;
            }
            kins.push(
                machine
                    .options
                    .kinematics
                    .stepper(s.axis, s.step_dist)
                    .map_err(|source| HomingError::StepperKinematics {
                        axis: axis_name,
                        stepper: s.name.clone(),
                        source,
                    })?,
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
        let (kinematics, rails) = match tower {
            Some(_) => (Kinematics::Cartesian, vec![e.axis; idxs.len()]),
            None => (
                machine.options.kinematics,
                idxs.iter().map(|&i| machine.steppers[i].axis).collect(),
            ),
        };
        Ok(PassGroup {
            idxs,
            kins,
            names,
            conns,
            axis_coeff,
            kinematics,
            rails,
        })
    }
}

/// Arms the pass: the trsyncs (then a round trip per member: every `trsync_state` still in
/// flight from the previous pass, as a triggered trsync keeps reporting, has arrived before the
/// group listens), the trigger group, and the endstop only after that, so no trigger can be
/// missed. The move starts `allowance` (print seconds, for computing its steps) after the
/// earliest start. Returns the group, the move's start print time and the endstop's rest ticks.
pub(super) fn arm_pass(
    ctx: &mut HomingCtx<'_>,
    g: &PassGroup<'_>,
    armed: &[&EndstopOut],
    speed: f64,
    allowance: f64,
) -> Result<(TriggerGroup, f64, Vec<u64>), HomingError> {
    let timeout = TriggerGroup::default_timeout(g.conns.len());
    let members: Vec<(&McuLink, u8)> = g.conns.iter().map(|c| (&c.link, c.trsync_oid)).collect();
    let t_arm = ctx.earliest_start();
    if let Err(err) = arm(ctx, &g.conns, &g.idxs, t_arm, timeout).and_then(|()| barrier(&g.conns)) {
        quiet(&g.conns);
        return Err(err);
    }
    let group = TriggerGroup::new(&members, timeout)?;
    let t0 = (ctx.earliest_start() + allowance).max(ctx.pipeline.toolhead_print_time());
    let sample_dist = ctx.machine.steppers[g.idxs[0]].step_dist / g.axis_coeff;
    let setup = ctx
        .pipeline
        .raise_print_time(t0)
        .map_err(HomingError::from)
        .and_then(|()| {
            armed
                .iter()
                .map(|e| arm_endstop(ctx, e, mcu(ctx.mcus, &e.pin.mcu)?, sample_dist, t0, speed))
                .collect::<Result<Vec<u64>, _>>()
        });
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

/// Plans the homing move to `target` and sends all its steps (about `steps` of them: how
/// long they took to compute is learned for the next move's start).
pub(super) fn send_homing_move(
    ctx: &mut HomingCtx<'_>,
    target: [f64; 4],
    speed: f64,
    axis_name: char,
    steps: f64,
) -> Result<Move, HomingError> {
    let began = Instant::now();
    let Some(mv) = ctx.pipeline.home_move(target, speed)? else {
        return Err(HomingError::NoMoveLength { axis: axis_name });
    };
    let mut out = Vec::new();
    generate(ctx, &mut out)?;
    ctx.learn_generation(steps, began.elapsed().as_secs_f64());
    push_cmds(ctx, &out)?;
    Ok(mv)
}

/// The trigger clock the endstop MCU reports (after a trigger it reports the matching read's
/// clock + its rest ticks, `rest_ticks[k]` for `armed[k]`), checked to be after the move's
/// start `t0`. With several endstops armed, the one that triggered still reads pressed (its
/// motors stopped past it) and, among those that do, its reported read came first: the others
/// kept sampling until they were cancelled, after the trigger.
pub(super) fn trigger_clock(
    ctx: &HomingCtx<'_>,
    armed: &[&EndstopOut],
    reporter: &str,
    t0: f64,
    rest_ticks: &[u64],
) -> Result<(String, u64), HomingError> {
    // (pressed, print time of the read, endstop, its MCU, clock, still homing), best first.
    let mut first: Option<(bool, f64, &EndstopOut, &McuConn, u64, bool)> = None;
    for (e, &rest) in armed.iter().zip(rest_ticks) {
        let conn = mcu(ctx.mcus, &e.pin.mcu)?;
        let (next, pressed, homing) = endstop_state(ctx, e)?;
        let c = next.saturating_sub(rest);
        let at = print_time_of_clock(ctx.mcus, conn, c);
        let better = first
            .as_ref()
            .is_none_or(|f| (pressed && !f.0) || (pressed == f.0 && at < f.1));
        if better {
            first = Some((pressed, at, e, conn, c, homing));
        }
    }
    let Some((_, _, e, conn, c, homing)) = first else {
        return Err(HomingError::NoTriggerClock {
            axis: AXIS_NAMES[armed.first().map_or(2, |e| e.axis.min(2))],
        });
    };
    if homing || c < clock_at_print_time(ctx.mcus, conn, t0) {
        return Err(HomingError::FalseTrigger {
            axis: AXIS_NAMES[e.axis],
            reporter: reporter.to_string(),
        });
    }
    Ok((e.pin.mcu.clone(), c))
}

/// The error a pass ends with, if any, from the trigger group's outcome.
pub(super) fn pass_error(
    ctx: &mut HomingCtx<'_>,
    outcome: Result<links::trsync::TriggerOutcome, TrsyncError>,
    axis_name: char,
    kind: PassKind,
) -> Option<HomingError> {
    match outcome {
        Ok(o) if o.reason == REASON_ENDSTOP_HIT => None,
        Ok(o) => Some(HomingError::StoppedWithReason {
            axis: axis_name,
            reason: o.reason,
        }),
        Err(TrsyncError::CommTimeout { detail, .. }) => {
            ctx.comm_timeout_detail = Some(detail);
            Some(HomingError::CommTimeout)
        }
        Err(TrsyncError::NotTriggered) => {
            let what = match kind {
                PassKind::Home { .. } => axis_name.to_string(),
                PassKind::Probe { .. } => "probe".to_string(),
            };
            Some(HomingError::NoTrigger { what })
        }
        Err(other) => Some(other.into()),
    }
}

/// Where the pass's steppers stopped, to compute the halt position and resync the planner.
pub(super) struct Stopped {
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
            .rails
            .iter()
            .zip(&g.kins)
            .zip(after.iter().zip(before))
            .map(|((&rail, &kin), (a, b))| GroupStepper {
                rail,
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
            kinematics: g.kinematics,
            group,
            positions: g.idxs.iter().copied().zip(after.iter().copied()).collect(),
            now_clocks,
            resume: ctx.earliest_start(),
        }
    }

    /// Where the steppers halted and where the trigger at `t_trig` found them.
    fn halt_at(&self, mv: &Move, t_trig: f64, axis_name: char) -> Result<Halt, HomingError> {
        halt_position(&self.kinematics, mv, &self.group, t_trig)
            .ok_or(HomingError::NotLinear { axis: axis_name })
    }

    /// After a failed pass: keeps host and MCU in agreement (positions in the pretended frame;
    /// axis not homed) and hands `err` back.
    fn give_up(&self, ctx: &mut HomingCtx<'_>, mv: &Move, axis_name: char, err: HomingError) -> HomingError {
        if let Ok(halt) = self.halt_at(mv, mv.print_time, axis_name) {
            let _ = self.resync(ctx, halt.halted_at(ctx.pipeline.position()));
        }
        err
    }

    /// The planner and the step streams continue from `p`, where the steppers stopped.
    fn resync(&self, ctx: &mut HomingCtx<'_>, p: [f64; 4]) -> Result<(), HomingError> {
        ctx.pipeline.resync_after_stop(self.resume, p, &self.positions)?;
        for (&(i, _), &now_clock) in self.positions.iter().zip(&self.now_clocks) {
            ctx.streams.note_stopped(i, now_clock);
        }
        Ok(())
    }
}

/// Stops the axis steppers a second time once every step command queued before the trigger
/// has reached its MCU: the trigger overtakes queued messages, and a `queue_step` arriving
/// after the stop would start the stepper again (the firmware accepts steps after a stop).
/// Per stepper MCU: wait until its link is idle, re-arm its trsync (no reports), attach the
/// axis steppers, trigger it. Best effort (a dead link stops nothing anyway).
pub(super) fn restop(ctx: &HomingCtx<'_>, conns: &[&McuConn], idxs: &[usize]) {
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
pub(super) fn barrier(conns: &[&McuConn]) -> Result<(), HomingError> {
    for c in conns {
        let cmd = c
            .link
            .dictionary()
            .encode("get_clock", &[])
            .map_err(|source| HomingError::Encode {
                mcu: c.name.clone(),
                source,
            })?;
        let mut result = Ok(());
        for _ in 0..QUERY_TRIES {
            result = c.link.query(cmd, "clock", None, QUERY_TIMEOUT).map(|_| ());
            if !matches!(result, Err(links::mcu::LinkError::Timeout { .. })) {
                break;
            }
        }
        result?;
    }
    Ok(())
}

/// Stops the periodic reports of the group's trsyncs (re-armed without reports or expiry,
/// no stepper attached) until the next homing move. Best effort.
pub(super) fn quiet(conns: &[&McuConn]) {
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
pub(super) fn arm(
    ctx: &HomingCtx<'_>,
    conns: &[&McuConn],
    idxs: &[usize],
    t_arm: f64,
    timeout: f64,
) -> Result<(), HomingError> {
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
            dict.encode(name, args).map_err(|source| HomingError::Encode {
                mcu: c.name.clone(),
                source,
            })
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
            c.link.send(cmd)?;
        }
    }
    Ok(())
}

/// Arms endstop `e` on its MCU `c` to sample from print time `t0` at a rest time of about one
/// step at `speed` (clamped to [`MIN_REST_TIME`, `MAX_REST_TIME`]); returns the rest time in
/// ticks (the trigger clock is `endstop_state`'s `next_clock` minus it).
pub(super) fn arm_endstop(
    ctx: &HomingCtx<'_>,
    e: &EndstopOut,
    c: &McuConn,
    step_dist: f64,
    t0: f64,
    speed: f64,
) -> Result<u64, HomingError> {
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
        .map_err(|source| HomingError::Encode {
            mcu: c.name.clone(),
            source,
        })?;
    c.link.send(cmd)?;
    Ok(rest_ticks)
}
