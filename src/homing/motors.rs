//! G28 of an axis whose further motors have their own endstops (`[stepper_z1] endstop_pin`):
//! each motor ends on its own switch, the axis at the rail's `position_endstop`.
//!
//! Klipper arms one trsync per endstop for one move and waits for all of them: each endstop
//! stops its own motors (`[stepper_z]`'s stops stepper_z and the further motors without an
//! `endstop_pin`), both passes alike, and the axis is then where `[stepper_z]` halted
//! (`position_endstop` plus its overshoot). Cadence has one trsync per MCU, so it reaches the
//! same end in steps of ordinary homing passes (each with the 25 ms stop budget, the overshoot
//! accounted for and `Communication timeout during homing`):
//! 1. with `homing_retract_dist` > 0: the first pass at `homing_speed` moves every motor of
//!    the axis together, every endstop of the axis armed, and stops them all on the first
//!    switch to trigger (no motor runs alone over the whole travel, so a gantry stays as level
//!    as it was, and none passes its own switch), then they all retract together; without a
//!    retract (no second pass) each group makes its single pass alone instead;
//! 2. each endstop's group in turn (the rail's first, then `[stepper_z1]`'s…) makes its pass
//!    (`second_homing_speed` after the retract) alone, the axis' other motors held still
//!    ([`planner::pipeline::Pipeline::freeze_lanes`]): its trigger is the rail's
//!    `position_endstop` for those motors (the pass may run the whole travel: a group whose
//!    switch did not trigger in step 1 is further from it than the retract);
//! 3. the axis is where the rail's group halted, and every motor is resynced to that
//!    position from its MCU step count: what the switches differ by stays between the motors
//!    (the gantry comes out as the switches sit).
//!
//! Every switch must be clear after the retract (else `Endstop z1 still triggered after
//! retract`, Klipper's wording and endstop name).

use super::*;

/// One endstop's motors: the endstop and the steppers (indices into `machine.steppers`) it
/// stops.
struct MotorGroup {
    endstop: EndstopOut,
    steppers: Vec<usize>,
    /// Klipper's endstop name in messages: the axis (`z`) for the rail's, `z1` for
    /// `[stepper_z1]`'s.
    name: String,
}

/// Homes axis `rail.axis` on the rail's endstop `rail` and the further motors' own `own`.
pub(super) fn home_motors(
    ctx: &mut HomingCtx<'_>,
    rail: &EndstopOut,
    own: &[EndstopOut],
) -> Result<AxisReport, HomingError> {
    let axis = rail.axis;
    let groups = motor_groups(ctx.machine, rail, own)?;
    let all = axis_steppers(ctx.machine, axis);
    let dir = if rail.homing_positive_dir { 1.0 } else { -1.0 };
    let retract = rail.homing_retract_dist;
    let mut passes = Vec::new();
    let mut mcus: Vec<String> = Vec::new();
    let start = rail.position_endstop - dir * TRAVEL_FACTOR * (rail.position_max - rail.position_min);
    let speed = if retract > 0.0 {
        // Step 1: all motors together onto the first switch, then back together.
        let plan = PassPlan {
            also_endstops: own,
            ..PassPlan::default()
        };
        let (first, names) = homing_pass(ctx, rail, PassKind::Home { start }, rail.homing_speed, plan)?;
        passes.push(first);
        mcus = names;
        let mut pos = ctx.pipeline.position();
        pos[axis] = rail.position_endstop - dir * retract;
        plain_move(ctx, pos, rail.homing_speed)?;
        wait_motion_done(ctx)?;
        for g in &groups {
            if endstop_state(ctx, &g.endstop)?.1 {
                return Err(still_triggered(g));
            }
        }
        rail.second_homing_speed
    } else {
        rail.homing_speed
    };
    // Step 2: each group alone; step 3: the axis where the rail's group halted.
    let mut homed = ctx.pipeline.position();
    for (k, g) in groups.iter().enumerate() {
        let (report, names) = group_pass(ctx, g, &all, start, speed)?;
        for n in names {
            if !mcus.contains(&n) {
                mcus.push(n);
            }
        }
        passes.push(report);
        if k == 0 {
            homed = ctx.pipeline.position();
        }
    }
    resync_motors(ctx, &all, homed)?;
    Ok(AxisReport {
        axis,
        mcus,
        passes,
        position: homed[axis],
    })
}

/// The rail's endstop with its motors that have none of their own, then each further motor's
/// own endstop with that motor.
fn motor_groups(
    machine: &Machine,
    rail: &EndstopOut,
    own: &[EndstopOut],
) -> Result<Vec<MotorGroup>, HomingError> {
    let axis = rail.axis;
    let axis_name = AXIS_NAMES[axis.min(2)];
    let all = axis_steppers(machine, axis);
    let kin = &machine.options.kinematics;
    for &i in &all {
        let s = &machine.steppers[i];
        let coeffs = kin
            .stepper(s.axis, s.step_dist)
            .ok()
            .and_then(|k| k.linear_coeffs().copied());
        let alone = coeffs.is_some_and(|c| (0..3).all(|a| (c[a] != 0.0) == (a == axis)));
        if !alone {
            return Err(HomingError::OwnEndstopKinematics {
                axis: axis_name,
                stepper: own.first().map_or_else(String::new, |e| e.stepper.clone()),
                kinematics: kinematics_name(kin),
            });
        }
    }
    let mut groups = vec![MotorGroup {
        endstop: rail.clone(),
        steppers: all
            .iter()
            .copied()
            .filter(|i| !own.iter().any(|e| e.motor == Some(*i)))
            .collect(),
        name: axis_name.to_string(),
    }];
    for e in own {
        let Some(i) = e.motor.filter(|i| all.contains(i)) else {
            continue;
        };
        groups.push(MotorGroup {
            endstop: e.clone(),
            steppers: vec![i],
            name: e.stepper.trim_start_matches("stepper_").to_string(),
        });
    }
    Ok(groups)
}

/// The kinematics' name in [`HomingError::OwnEndstopKinematics`].
fn kinematics_name(kin: &Kinematics) -> &'static str {
    match kin {
        Kinematics::Cartesian => "cartesian",
        Kinematics::CoreXY => "corexy",
        Kinematics::CoreXZ => "corexz",
        Kinematics::Delta(_) => "delta",
    }
}

/// Group `g`'s pass alone (the axis' other motors `all` held still) from the pretended
/// `start` at `speed`; afterwards every motor follows the toolhead again.
fn group_pass(
    ctx: &mut HomingCtx<'_>,
    g: &MotorGroup,
    all: &[usize],
    start: f64,
    speed: f64,
) -> Result<(PassReport, Vec<String>), HomingError> {
    wait_motion_done(ctx)?;
    let others: Vec<usize> = all.iter().copied().filter(|i| !g.steppers.contains(i)).collect();
    ctx.pipeline.freeze_lanes(&others)?;
    let plan = PassPlan {
        motors: Some(&g.steppers),
        ..PassPlan::default()
    };
    let result = homing_pass(ctx, &g.endstop, PassKind::Home { start }, speed, plan);
    ctx.pipeline.thaw_lanes();
    let pos = ctx.pipeline.position();
    // Resync even after a failed pass (best effort): the held lanes follow the toolhead again.
    let resynced = resync_motors(ctx, all, pos);
    let out = result.map_err(|err| match err {
        HomingError::NoTrigger { .. } => HomingError::NoTrigger { what: g.name.clone() },
        other => other,
    })?;
    resynced?;
    Ok(out)
}

/// Every motor of `motors` continues from toolhead position `pos`, each from its step count
/// (after some moved alone: their lanes follow the toolhead again).
pub(super) fn resync_motors(
    ctx: &mut HomingCtx<'_>,
    motors: &[usize],
    pos: [f64; 4],
) -> Result<(), HomingError> {
    let stopped: Vec<(usize, i64)> = motors
        .iter()
        .filter_map(|&i| Some((i, ctx.pipeline.stepper_position(i)?)))
        .collect();
    let t = ctx.pipeline.toolhead_print_time();
    Ok(ctx.pipeline.resync_after_stop(t, pos, &stopped)?)
}

fn still_triggered(g: &MotorGroup) -> HomingError {
    match g.endstop.motor {
        Some(_) => HomingError::MotorStillTriggered {
            endstop: g.name.clone(),
        },
        None => HomingError::StillTriggered {
            axis: AXIS_NAMES[g.endstop.axis.min(2)],
        },
    }
}
