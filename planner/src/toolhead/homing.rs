//! Homing support: after an endstop stopped the steppers part-way through the last move, the
//! toolhead's clock and commanded position are set to what really happened, so the next move
//! starts from the halt position at a print time the caller chose (not at the end of the move
//! that was cut short).

use super::{Toolhead, LOOKAHEAD_FLUSH_TIME};

impl Toolhead {
    /// Redefines the commanded position as `pos` and the start of the next move as
    /// `print_time` (which may be earlier than [`Toolhead::print_time`]: the rest of the last
    /// move never happened). Queued moves are finalized first; non-finite values are ignored.
    pub fn reset_after_stop(&mut self, print_time: f64, pos: [f64; 4]) {
        self.flush();
        if print_time.is_finite() && print_time >= 0.0 {
            self.print_time = print_time;
        }
        for (c, p) in self.commanded.iter_mut().zip(pos) {
            if p.is_finite() {
                *c = p;
            }
        }
        self.queued_time = 0.0;
        self.flush_countdown = LOOKAHEAD_FLUSH_TIME;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::toolhead::ToolheadConfig;

    fn cfg() -> ToolheadConfig {
        ToolheadConfig {
            max_velocity: 100.0,
            max_accel: 1000.0,
            minimum_cruise_ratio: 0.5,
            square_corner_velocity: 5.0,
            max_z_velocity: 10.0,
            max_z_accel: 100.0,
            max_extrude_only_velocity: 50.0,
            max_extrude_only_accel: 1000.0,
            max_extrude_only_distance: 50.0,
            axis_limits: [(0.0, 200.0); 3],
        }
    }

    #[test]
    fn next_move_starts_at_the_given_time_and_position() {
        let mut th = Toolhead::new(cfg(), 1.0);
        th.move_to([100.0, 0.0, 0.0, 0.0], 10.0).unwrap();
        th.flush();
        assert!(th.print_time() > 10.0);
        th.reset_after_stop(2.5, [42.0, f64::NAN, 0.0, 0.0]);
        assert_eq!(th.position(), [42.0, 0.0, 0.0, 0.0]);
        assert_eq!(th.print_time(), 2.5);
        let mut out = Vec::new();
        th.take_moves(&mut out);
        th.move_to([50.0, 0.0, 0.0, 0.0], 10.0).unwrap();
        th.flush();
        out.clear();
        th.take_moves(&mut out);
        assert_eq!(out.len(), 1);
        assert_eq!(out[0].print_time, 2.5);
        assert_eq!(out[0].start_pos[0], 42.0);
    }
}
