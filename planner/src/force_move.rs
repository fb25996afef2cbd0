//! FORCE_MOVE and STEPPER_BUZZ (Klipper's `[force_move]`): one stepper moved on its own, outside
//! the kinematics, while the toolhead stands still.
//!
//! The move is Klipper's `calc_move_time`: a distance `d` at speed `v` with acceleration `a`;
//! with `a = 0` it runs at `v` from the first step (no ramp), otherwise it ramps up and down at
//! `a`, capped at `v' = √(d·a)` when `d` is too short to reach `v` (then there is no cruise).
//! It is written as a [`Move`] along one axis from the stepper's own position, so the step
//! generator emits its steps as for any move; the stepper's commanded position is not changed
//! by it (the next toolhead move re-anchors the generator, as Klipper's `set_position` after a
//! forced move), so the motor ends `d` away from where the kinematics put it.

use crate::toolhead::Move;

/// STEPPER_BUZZ: each of the 10 cycles moves 1 mm at 4 mm/s, waits 50 ms, moves back and
/// waits 450 ms (Klipper's constants).
pub const BUZZ_DISTANCE: f64 = 1.0;
pub const BUZZ_VELOCITY: f64 = BUZZ_DISTANCE / 0.250;
pub const BUZZ_CYCLES: usize = 10;
pub const BUZZ_DWELLS: (f64, f64) = (0.050, 0.450);

/// A forced move of `distance` mm (signed) at `velocity` mm/s (> 0) with `accel` mm/s² (0: no
/// ramp) starting at `print_time` from stepper position `from` (axis X of the move).
pub fn forced_move(print_time: f64, from: f64, distance: f64, velocity: f64, accel: f64) -> Move {
    let r = if distance < 0.0 { -1.0 } else { 1.0 };
    let d = distance.abs();
    let (accel_t, cruise_t, v, start_v) = if accel <= 0.0 || d == 0.0 {
        (0.0, d / velocity, velocity, velocity)
    } else {
        let v = velocity.min((d * accel).sqrt());
        let accel_t = v / accel;
        (accel_t, ((d - accel_t * v) / v).max(0.0), v, 0.0)
    };
    Move {
        print_time,
        start_pos: [from, 0.0, 0.0, 0.0],
        end_pos: [from + distance, 0.0, 0.0, 0.0],
        axes_r: [r, 0.0, 0.0, 0.0],
        move_d: d,
        start_v,
        cruise_v: v,
        end_v: start_v,
        accel: if accel_t > 0.0 { accel } else { 0.0 },
        accel_t,
        cruise_t,
        decel_t: accel_t,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn profiles() {
        // No acceleration: the whole distance at the velocity.
        let m = forced_move(1.0, 5.0, -10.0, 20.0, 0.0);
        assert_eq!((m.accel_t, m.cruise_t, m.decel_t), (0.0, 0.5, 0.0));
        assert_eq!(m.position_at(0.25)[0], 0.0);
        assert_eq!(m.end_pos[0], -5.0);
        // Ramps: 10 mm at 20 mm/s, 100 mm/s²: 0.2 s up, 0.2 s down, 6 mm cruise (0.3 s).
        let m = forced_move(0.0, 0.0, 10.0, 20.0, 100.0);
        assert!((m.accel_t - 0.2).abs() < 1e-12 && (m.cruise_t - 0.3).abs() < 1e-12);
        assert!((m.position_at(m.duration())[0] - 10.0).abs() < 1e-9);
        // Too short to reach the velocity: v = √(d·a), no cruise.
        let m = forced_move(0.0, 0.0, 1.0, 20.0, 100.0);
        assert!((m.cruise_v - 10.0).abs() < 1e-12 && m.cruise_t.abs() < 1e-12);
        assert!((m.position_at(m.duration())[0] - 1.0).abs() < 1e-9);
    }
}
