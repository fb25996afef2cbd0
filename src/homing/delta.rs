//! G28 on a delta printer: every tower's carriage to its endstop at the top, then the toolhead
//! position from the three carriage heights (forward kinematics).
//!
//! Klipper moves the three carriages up together, each stopping on its own endstop. Cadence
//! has one trigger group per MCU, so it homes the towers one after the other with the same
//! result: with the toolhead declared at the centre (X = Y = 0) and the other two towers'
//! steppers held still ([`planner::pipeline::Pipeline::freeze_lanes`]), a Z move moves the
//! homed tower's carriage alone, one to one, so its pass is an ordinary homing pass of Z
//! (both passes, the retract between them, the overshoot accounted for) whose trigger defines
//! Z = the tower's `position_endstop` (the pass itself heads for the lowest tower's, the top of
//! the toolhead's range, and the difference is added back). That carriage is then at height `position_endstop +
//! overshoot + √(arm² − radius²)` (the carriage height of the centre at that Z, Klipper's
//! "absolute endstop"). Once the three are known, the toolhead is where forward kinematics
//! of the three heights puts it (the centre at `position_endstop` when the endstops agree),
//! and every tower's stepper is resynced to its MCU position there.

use planner::kinematics::DeltaGeometry;

use super::*;

/// Steps the move after homing may take to compute before its first is due.
const RESUME_STEPS: f64 = 5000.0;

/// Homes the three towers of a delta printer (G28 of any axis homes all, as on Klipper).
/// `endstops[t]` is tower `t`'s.
pub(super) fn home_towers(
    ctx: &mut HomingCtx<'_>,
    geometry: &DeltaGeometry,
    endstops: &[EndstopOut; 3],
) -> Result<Vec<AxisReport>, HomingError> {
    wait_motion_done(ctx)?;
    let mut pos = ctx.pipeline.position();
    pos[0] = 0.0;
    pos[1] = 0.0;
    ctx.pipeline.set_toolhead_position(pos);
    // Each pass heads for the lowest endstop's Z (the toolhead's top: a move above it is out of
    // range); a tower whose endstop is higher stops that much higher.
    let z_ref = endstops
        .iter()
        .map(|e| e.position_endstop)
        .fold(f64::INFINITY, f64::min);
    let mut reports = Vec::with_capacity(3);
    let mut heights = [0.0; 3];
    for (tower, e) in endstops.iter().enumerate() {
        let others: Vec<usize> = tower_steppers(ctx.machine, |t| t != tower);
        ctx.pipeline.freeze_lanes(&others)?;
        let as_z = EndstopOut {
            axis: 2,
            position_endstop: z_ref,
            ..e.clone()
        };
        let plan = PassPlan {
            tower: Some(tower),
            ..PassPlan::default()
        };
        let result = home_axis(ctx, &as_z, plan);
        ctx.pipeline.thaw_lanes();
        let mut report = result?;
        report.position += e.position_endstop - z_ref;
        heights[tower] = report.position + carriage_offset(geometry, tower);
        report.axis = tower;
        reports.push(report);
        // The next tower's pass starts from the centre again.
        let mut pos = ctx.pipeline.position();
        pos[0] = 0.0;
        pos[1] = 0.0;
        ctx.pipeline.set_toolhead_position(pos);
    }
    let top = ctx.machine.options.kinematics.forward(heights);
    let mut pos = ctx.pipeline.position();
    pos[..3].copy_from_slice(&top);
    let all = tower_steppers(ctx.machine, |_| true);
    let mut positions = Vec::with_capacity(all.len());
    for &i in &all {
        positions.push((i, stepper_position(ctx, i)?));
    }
    // The next move (a delta's steps are solved numerically: slow) starts with room to
    // compute a few thousand steps.
    let resume = ctx.earliest_start() + ctx.generation_allowance(RESUME_STEPS);
    ctx.pipeline.resync_after_stop(resume, pos, &positions)?;
    for &i in &all {
        let mcu_index = ctx
            .mcus
            .list
            .iter()
            .position(|m| m.name == ctx.machine.steppers[i].mcu);
        let now = mcu_index.map_or(0.0, |m| mcu_clock_now(ctx.mcus, m));
        ctx.streams.note_stopped(i, now.max(0.0) as u64);
    }
    Ok(reports)
}

/// Carriage height above the toolhead's Z when the toolhead is at the centre: √(arm² − radius²).
pub(super) fn carriage_offset(g: &DeltaGeometry, tower: usize) -> f64 {
    let arm = g.arm_length[tower.min(2)];
    (arm * arm - g.radius * g.radius).max(0.0).sqrt()
}

/// The steppers of the towers `which` accepts (machine order).
fn tower_steppers(machine: &Machine, which: impl Fn(usize) -> bool) -> Vec<usize> {
    (0..machine.steppers.len())
        .filter(|&i| machine.steppers[i].axis < 3 && which(machine.steppers[i].axis))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use planner::kinematics::Kinematics;

    #[test]
    fn carriages_at_their_offsets_put_the_toolhead_at_the_centre() {
        let g = DeltaGeometry {
            radius: 140.0,
            arm_length: [270.0, 271.0, 269.5],
            angles: [210.0, 330.0, 90.0],
        };
        let kin = Kinematics::Delta(g);
        // All three carriages stopped where the centre at Z 300 puts them: the toolhead is
        // there; one carriage 1 mm lower tilts it off the centre and lowers it.
        let heights = [0, 1, 2].map(|t| 300.0 + carriage_offset(&g, t));
        let p = kin.forward(heights);
        assert!(
            p[0].abs() < 1e-9 && p[1].abs() < 1e-9 && (p[2] - 300.0).abs() < 1e-9,
            "{p:?}"
        );
        let q = kin.forward([heights[0] - 1.0, heights[1], heights[2]]);
        assert!(q[2] < 300.0 && q[0].hypot(q[1]) > 0.1, "{q:?}");
        assert_eq!(
            kin.inverse(p).map(|h| (h * 1e6).round()),
            heights.map(|h| (h * 1e6).round())
        );
    }
}
