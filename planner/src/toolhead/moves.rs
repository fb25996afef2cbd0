//! A planned move: a straight line from `start_pos` to `end_pos` with a trapezoidal speed profile
//! (constant acceleration `accel` from `start_v` to `cruise_v`, cruise, constant deceleration
//! to `end_v`).
//!
//! Distance along the move at time t (seconds from `print_time`):
//! - accel phase: s = v0·t + ½·a·t²
//! - cruise phase: s = accel_d + vc·(t − accel_t)
//! - decel phase (τ = time into it): s = accel_d + cruise_d + vc·τ − ½·a·τ²
//!
//! and the inverses in closed form, written without cancellation: t = 2s / (v0 + √(v0² + 2as))
//! (= (−v0 + √(v0² + 2as)) / a) while accelerating, τ = 2s' / (vc + √(vc² − 2as')) while
//! decelerating.

/// One move as the lookahead finalized it. Positions are X, Y, Z, E in mm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Move {
    /// Print time (seconds) at which the move starts.
    pub print_time: f64,
    pub start_pos: [f64; 4],
    /// Exactly the next move's `start_pos` (no rounding drift between moves).
    pub end_pos: [f64; 4],
    /// Per-axis share of the move distance: Δaxis / move_d. For extrude-only moves the distance
    /// is |ΔE| and `axes_r` is `[0, 0, 0, ±1]`.
    pub axes_r: [f64; 4],
    /// Distance in mm (XYZ length, or |ΔE| for extrude-only moves).
    pub move_d: f64,
    pub start_v: f64,
    pub cruise_v: f64,
    pub end_v: f64,
    /// Acceleration (and deceleration) in mm/s².
    pub accel: f64,
    pub accel_t: f64,
    pub cruise_t: f64,
    pub decel_t: f64,
}

impl Move {
    /// Print time at which the move ends.
    #[inline]
    pub fn end_time(&self) -> f64 {
        self.print_time + self.duration()
    }

    /// Seconds the move lasts.
    #[inline]
    pub fn duration(&self) -> f64 {
        self.accel_t + self.cruise_t + self.decel_t
    }

    /// Distance covered while accelerating.
    #[inline]
    pub fn accel_d(&self) -> f64 {
        (self.start_v + self.cruise_v) * 0.5 * self.accel_t
    }

    /// Distance covered while cruising.
    #[inline]
    pub fn cruise_d(&self) -> f64 {
        self.cruise_v * self.cruise_t
    }

    /// True when X, Y or Z moves (false for extrude-only moves).
    pub fn is_kinematic(&self) -> bool {
        self.axes_r[..3].iter().any(|&r| r != 0.0)
    }

    /// Distance along the move at `t_rel` seconds after its start (clamped to the move).
    pub fn distance_at(&self, t_rel: f64) -> f64 {
        let t = t_rel.clamp(0.0, self.duration());
        let s = if t < self.accel_t {
            (self.start_v + 0.5 * self.accel * t) * t
        } else if t < self.accel_t + self.cruise_t {
            self.accel_d() + self.cruise_v * (t - self.accel_t)
        } else {
            let tau = (t - self.accel_t - self.cruise_t).min(self.decel_t);
            self.accel_d() + self.cruise_d() + (self.cruise_v - 0.5 * self.accel * tau) * tau
        };
        s.clamp(0.0, self.move_d)
    }

    /// Time (seconds after the start) at which the move has covered `s` mm; the inverse of
    /// [`Self::distance_at`], in closed form.
    pub fn time_at_distance(&self, s: f64) -> f64 {
        Phases::new(self).time_at(s)
    }

    /// X, Y, Z, E at `t_rel` seconds after the start.
    pub fn position_at(&self, t_rel: f64) -> [f64; 4] {
        let s = self.distance_at(t_rel);
        let mut p = self.start_pos;
        for (p, r) in p.iter_mut().zip(self.axes_r) {
            *p += r * s;
        }
        p
    }

    /// Speed (mm/s along the move) at `t_rel`.
    pub fn velocity_at(&self, t_rel: f64) -> f64 {
        let t = t_rel.clamp(0.0, self.duration());
        if t < self.accel_t {
            self.start_v + self.accel * t
        } else if t < self.accel_t + self.cruise_t {
            self.cruise_v
        } else {
            let tau = (t - self.accel_t - self.cruise_t).min(self.decel_t);
            (self.cruise_v - self.accel * tau).max(0.0)
        }
    }
}

/// The profile's constants, precomputed once per move for the many `time_at` calls of step
/// generation.
#[derive(Debug, Clone, Copy)]
pub struct Phases {
    v0: f64,
    v0_2: f64,
    vc: f64,
    vc_2: f64,
    /// 1 / cruise velocity (0 when the move has no cruise velocity).
    inv_vc: f64,
    two_a: f64,
    accel_d: f64,
    cruise_end_d: f64,
    accel_t: f64,
    cruise_end_t: f64,
    total_t: f64,
}

impl Phases {
    pub fn new(m: &Move) -> Phases {
        let accel_d = m.accel_d();
        Phases {
            v0: m.start_v,
            v0_2: m.start_v * m.start_v,
            vc: m.cruise_v,
            vc_2: m.cruise_v * m.cruise_v,
            inv_vc: if m.cruise_v > 0.0 { 1.0 / m.cruise_v } else { 0.0 },
            two_a: 2.0 * m.accel,
            accel_d,
            cruise_end_d: accel_d + m.cruise_d(),
            accel_t: m.accel_t,
            cruise_end_t: m.accel_t + m.cruise_t,
            total_t: m.duration(),
        }
    }

    /// The cruise phase as a line: (distance where it starts, distance where it ends, time at
    /// its start, 1 / cruise velocity); `None` without a cruise phase.
    #[inline]
    pub fn cruise(&self) -> Option<(f64, f64, f64, f64)> {
        (self.inv_vc > 0.0 && self.cruise_end_d > self.accel_d).then_some((
            self.accel_d,
            self.cruise_end_d,
            self.accel_t,
            self.inv_vc,
        ))
    }

    /// Time at which distance `s` is reached (clamped to the move's duration). Hot: called for
    /// every step of linear kinematics, so comparisons rather than `f64::min` (no NaN can
    /// reach here: s is clamped by the caller and the profile's numbers are finite).
    #[inline]
    pub fn time_at(&self, s: f64) -> f64 {
        let t = if s <= 0.0 {
            0.0
        } else if s < self.accel_d {
            let den = self.v0 + (self.v0_2 + self.two_a * s).sqrt();
            if den > 0.0 {
                let t = 2.0 * s / den;
                if t < self.accel_t {
                    t
                } else {
                    self.accel_t
                }
            } else {
                0.0
            }
        } else if s < self.cruise_end_d {
            self.accel_t + (s - self.accel_d) * self.inv_vc
        } else {
            let sd = s - self.cruise_end_d;
            let r = self.vc_2 - self.two_a * sd;
            let den = self.vc + if r > 0.0 { r.sqrt() } else { 0.0 };
            if den > 0.0 {
                self.cruise_end_t + 2.0 * sd / den
            } else {
                self.total_t
            }
        };
        if t < self.total_t {
            t
        } else {
            self.total_t
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn trapezoid() -> Move {
        // 0 → 10 mm/s at 100 mm/s² (0.1 s, 0.5 mm), cruise 1 mm (0.1 s), 10 → 4 mm/s (0.06 s, 0.42 mm).
        Move {
            print_time: 2.0,
            start_pos: [1.0, 2.0, 3.0, 4.0],
            end_pos: [1.0 + 1.92 * 0.6, 2.0 + 1.92 * 0.8, 3.0, 4.0 + 1.92 * 0.05],
            axes_r: [0.6, 0.8, 0.0, 0.05],
            move_d: 1.92,
            start_v: 0.0,
            cruise_v: 10.0,
            end_v: 4.0,
            accel: 100.0,
            accel_t: 0.1,
            cruise_t: 0.1,
            decel_t: 0.06,
        }
    }

    #[test]
    fn distance_profile() {
        let m = trapezoid();
        assert!((m.end_time() - 2.26).abs() < 1e-12);
        assert!((m.distance_at(0.1) - 0.5).abs() < 1e-12);
        assert!((m.distance_at(0.2) - 1.5).abs() < 1e-12);
        assert!((m.distance_at(0.26) - 1.92).abs() < 1e-12);
        assert!((m.velocity_at(0.05) - 5.0).abs() < 1e-12);
        assert!((m.velocity_at(0.26) - 4.0).abs() < 1e-9);
        let p = m.position_at(0.26);
        for (a, b) in p.iter().zip(m.end_pos) {
            assert!((a - b).abs() < 1e-12);
        }
    }

    #[test]
    fn inverse_matches_forward() {
        let m = trapezoid();
        for i in 0..=260 {
            let t = i as f64 * 0.001;
            let s = m.distance_at(t);
            let back = m.time_at_distance(s);
            assert!((back - t).abs() < 1e-9, "t {t} s {s} back {back}");
        }
    }
}
