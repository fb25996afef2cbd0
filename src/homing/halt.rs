//! Where a homing or probing pass halted, on the host: step indices, the move's profile and
//! forward kinematics give the halted and the triggered toolhead positions (see the homing
//! module docs, step 6). Pure maths, tested with virtual passes.

use planner::kinematics::{Kinematics, StepperKin};
use planner::toolhead::Move;

/// n(x) = ⌊x / step_dist + ½⌋.
pub(super) fn step_index(x: f64, step_dist: f64) -> i64 {
    (x / step_dist + 0.5).floor() as i64
}

/// Print time at which stepper `kin` (linear) reaches position `x` (mm) in `mv` (clamped to
/// the move; its end when the stepper does not move).
pub(super) fn time_at_stepper_pos(mv: &Move, kin: &StepperKin, x: f64) -> f64 {
    let r = kin
        .linear_coeffs()
        .map_or(0.0, |c| c.iter().zip(&mv.axes_r).map(|(k, r)| k * r).sum::<f64>());
    if r == 0.0 {
        return mv.end_time();
    }
    let s = ((x - kin.position(&mv.start_pos)) / r).clamp(0.0, mv.move_d);
    mv.print_time + mv.time_at_distance(s)
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

/// When the first stepper's last executed step and its first cancelled one were due: its
/// last step reached index n_halt at boundary (n_halt − sdir·½)·sd, sdir its direction.
pub(super) fn stop_bounds(mv: &Move, kin0: &StepperKin, net_steps: i64) -> (f64, f64) {
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
