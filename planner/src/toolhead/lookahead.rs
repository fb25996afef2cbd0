//! The lookahead pass: chooses each queued move's start, cruise and end speed.
//!
//! All speeds are squared (v²), because over a distance d at acceleration a the squared speed
//! changes by at most `delta_v2 = 2·a·d`. The pass walks the queue backward from its last move,
//! which must be able to stop:
//!
//! - `start_v2[i] = min(max_start_v2[i], start_v2[i+1] + delta_v2[i])` — the fastest start from
//!   which move i can still slow down to the next move's start. `max_start_v2` already holds the
//!   forward limit (junction speed, and what the previous moves can reach), filled in when the
//!   move was queued.
//! - A second, "smoothed" profile uses the reduced acceleration `max_accel · (1 −
//!   minimum_cruise_ratio)`. Along each speed hill of it (moves whose smoothed speed rises, then
//!   moves whose smoothed speed falls), the hill top `(smoothed_start + smoothed_reach) / 2` caps
//!   the cruise speed of every move on the hill. This keeps a share of each accelerate-then-
//!   decelerate stretch at cruise speed instead of a sawtooth of full-acceleration bursts.
//! - The cruise speed of a rising move is also capped by its own triangle peak
//!   `(start_v2 + end_v2 + delta_v2) / 2`; a falling move cruises at most at its start speed.
//!
//! Finality (lazy mode): adding moves behind the queue can only raise speeds near its end. Once
//! the backward walk has passed the tops of two hills, the moves before the earlier top can no
//! longer change: they are returned as final. Consistency between two passes is kept by the
//! caller clamping the new first move's `max_start_v2` to the speed the last final move ended at.

use super::moves::Move;

/// A move waiting in the lookahead queue with its speed limits (speeds squared).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Queued {
    /// Geometry and acceleration; speeds and times are filled when the move becomes final.
    pub mv: Move,
    pub kinematic: bool,
    pub max_start_v2: f64,
    pub max_cruise_v2: f64,
    pub delta_v2: f64,
    pub max_smoothed_v2: f64,
    pub smooth_delta_v2: f64,
    /// Shortest time the move can take (distance / speed limit), for flush timing.
    pub min_move_t: f64,
    /// Speeds chosen by the last pass that covered this move.
    pub start_v2: f64,
    pub cruise_v2: f64,
    pub end_v2: f64,
}

impl Queued {
    /// Lowers the speed and acceleration limits of the move (Z and extruder limits).
    pub fn limit_speed(&mut self, speed: f64, accel: f64) {
        let v2 = speed * speed;
        if v2 < self.max_cruise_v2 {
            self.max_cruise_v2 = v2;
            self.min_move_t = self.mv.move_d / speed;
        }
        self.mv.accel = self.mv.accel.min(accel);
        self.delta_v2 = 2.0 * self.mv.move_d * self.mv.accel;
        self.smooth_delta_v2 = self.smooth_delta_v2.min(self.delta_v2);
    }

    fn set(&mut self, start_v2: f64, cruise_v2: f64, end_v2: f64) {
        self.start_v2 = start_v2;
        self.cruise_v2 = cruise_v2;
        self.end_v2 = end_v2;
    }
}

/// A move on the falling side of a hill, waiting for the hill top to be known.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Falling {
    index: usize,
    start_v2: f64,
    end_v2: f64,
}

/// Junction limits between `prev` and `cur` (both queued, `prev` first), written into `cur`.
///
/// The junction speed is that of a virtual arc of radius R tangent to both moves whose
/// centripetal acceleration is `accel`: with θ the angle between the reversed previous
/// direction and the new one, `R = junction_deviation · sin(θ/2) / (1 − sin(θ/2))` and
/// `v² = R · accel`. `junction_deviation = scv² (√2 − 1) / max_accel` makes a 90° corner
/// exactly `square_corner_velocity`. The arc must also touch each move no further than its
/// middle: `v² ≤ ½·d·a·tan(θ/2) = delta_v2 · ¼ tan(θ/2)`. The extruder's share of the move may
/// not jump by more than `instant_corner_v` in speed: `v ≤ icv / |Δ(ΔE/d)|`.
pub(crate) fn calc_junction(prev: &Queued, cur: &mut Queued, junction_deviation: f64, instant_corner_v: f64) {
    if !cur.kinematic || !prev.kinematic {
        cur.max_start_v2 = 0.0;
        cur.max_smoothed_v2 = 0.0;
        return;
    }
    let (r, pr) = (cur.mv.axes_r, prev.mv.axes_r);
    let extrude_dr = r[3] - pr[3];
    let extruder_v2 = if extrude_dr != 0.0 {
        let v = instant_corner_v / extrude_dr.abs();
        v * v
    } else {
        cur.max_cruise_v2
    };
    let mut v2 = extruder_v2
        .min(cur.max_cruise_v2)
        .min(prev.max_cruise_v2)
        .min(prev.max_start_v2 + prev.delta_v2);
    let cos_theta = -(r[0] * pr[0] + r[1] * pr[1] + r[2] * pr[2]);
    let sin_half = (0.5 * (1.0 - cos_theta)).max(0.0).sqrt();
    let cos_half = (0.5 * (1.0 + cos_theta)).max(0.0).sqrt();
    let one_minus_sin = 1.0 - sin_half;
    if one_minus_sin > 0.0 && cos_half > 0.0 {
        let r_jd = sin_half / one_minus_sin;
        let quarter_tan = 0.25 * sin_half / cos_half;
        v2 = v2
            .min(r_jd * junction_deviation * cur.mv.accel)
            .min(r_jd * junction_deviation * prev.mv.accel)
            .min(cur.delta_v2 * quarter_tan)
            .min(prev.delta_v2 * quarter_tan);
    }
    cur.max_start_v2 = v2;
    cur.max_smoothed_v2 = v2.min(prev.max_smoothed_v2 + prev.smooth_delta_v2);
}

/// Runs the backward pass over `moves`, assigning speeds to the moves that become final, and
/// returns how many moves from the front are final. `lazy == false` finalizes every move (the
/// last one ends at rest). `falling` is scratch space (kept to avoid allocating per pass).
pub(crate) fn plan(moves: &mut [Queued], falling: &mut Vec<Falling>, lazy: bool) -> usize {
    falling.clear();
    let n = moves.len();
    // Moves with index < cut get their speeds; unknown yet in lazy mode.
    let mut cut = if lazy { None } else { Some(n) };
    let mut next_start_v2 = 0.0;
    let mut next_smoothed_v2 = 0.0;
    let mut peak_v2: Option<f64> = None;
    for i in (0..n).rev() {
        let m = moves[i];
        let reach_v2 = next_start_v2 + m.delta_v2;
        let start_v2 = m.max_start_v2.min(reach_v2);
        let reach_smoothed_v2 = next_smoothed_v2 + m.smooth_delta_v2;
        let smoothed_v2 = m.max_smoothed_v2.min(reach_smoothed_v2);
        if smoothed_v2 < reach_smoothed_v2 {
            // Forward-limited: the smoothed profile rises into this move.
            if smoothed_v2 + m.smooth_delta_v2 > next_smoothed_v2 || !falling.is_empty() {
                // A hill top lies in this move or at its end.
                if cut.is_none() && peak_v2.is_some() {
                    cut = Some(i);
                }
                let peak = m.max_cruise_v2.min(0.5 * (smoothed_v2 + reach_smoothed_v2));
                peak_v2 = Some(peak);
                if cut.is_some_and(|c| i < c) {
                    assign_falling(moves, falling, peak);
                }
                falling.clear();
            }
            if let (Some(c), Some(peak)) = (cut, peak_v2) {
                if i < c {
                    let cruise_v2 = (0.5 * (start_v2 + reach_v2)).min(m.max_cruise_v2).min(peak);
                    moves[i].set(start_v2.min(cruise_v2), cruise_v2, next_start_v2.min(cruise_v2));
                }
            }
        } else {
            falling.push(Falling {
                index: i,
                start_v2,
                end_v2: next_start_v2,
            });
        }
        next_start_v2 = start_v2;
        next_smoothed_v2 = smoothed_v2;
    }
    match cut {
        None => 0,
        Some(c) => {
            // Falling moves at the very front (possible only after a forced partial flush):
            // their hill top is already final, so they do not accelerate.
            assign_falling(moves, falling, f64::INFINITY);
            falling.clear();
            c
        }
    }
}

/// Assigns speeds to the falling moves of a hill whose top is `peak_v2`, front to back: each
/// cruises at most at its own start speed and at the speed of the moves before it.
fn assign_falling(moves: &mut [Queued], falling: &[Falling], peak_v2: f64) {
    let mut cruise_v2 = peak_v2;
    for f in falling.iter().rev() {
        cruise_v2 = cruise_v2.min(f.start_v2);
        if let Some(m) = moves.get_mut(f.index) {
            m.set(f.start_v2.min(cruise_v2), cruise_v2, f.end_v2.min(cruise_v2));
        }
    }
}
