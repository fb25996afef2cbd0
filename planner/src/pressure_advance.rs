//! The extruder with pressure advance: step times from a non-linear position function, by the
//! iterative solver (time slices, bisection of each half-step crossing).
//!
//! Model (Klipper's documented one): the extruder runs ahead of the nominal filament position
//! E(t) by `advance` × the extrusion velocity, the velocity being averaged over
//! `smooth_time` centred on t:
//!
//!   e(t) = E(t) + (P(t + T/2) − P(t − T/2)) / T
//!
//! where P is the cumulative advance × extrusion of the moves that get pressure advance
//! (extruding moves with X/Y motion, as Klipper), each move with the advance in force when it
//! was queued, and T = smooth_time. With one advance this is advance · (average extrusion
//! velocity); a new advance (SET_PRESSURE_ADVANCE, [`PaGen::set_advance`]) takes effect
//! from the next move, blended in over T by the same average. e is continuous; at rest for T/2 it equals
//! E, so step counts are exact once the toolhead stops. Positions at t need the moves up to
//! t + T/2: the generator keeps the recent moves and only generates steps up to the last known
//! move's end − T/2 until told the toolhead is at rest.

use std::collections::VecDeque;

use crate::toolhead::Move;

/// Time slice of the iterative solver (s): a step reversal shorter than this nets out unseen.
const SLICE_S: f64 = 0.000_5;
/// Bisection rounds per step (time resolution ≈ slice / 2^rounds).
const BISECT_ROUNDS: usize = 30;

/// Pressure advance parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PressureAdvance {
    /// Seconds (mm of filament per mm/s of extrusion velocity), ≥ 0.
    pub advance: f64,
    /// Averaging window (s), in (0, 0.2].
    pub smooth_time: f64,
}

impl PressureAdvance {
    /// Checks the numbers.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.advance.is_finite() && self.advance >= 0.0 && self.advance < 10.0) {
            return Err(format!("pressure_advance {} must be in [0, 10)", self.advance));
        }
        if !(self.smooth_time.is_finite() && self.smooth_time > 0.0 && self.smooth_time <= 0.2) {
            return Err(format!(
                "pressure_advance_smooth_time {} must be in (0, 0.2]",
                self.smooth_time
            ));
        }
        Ok(())
    }
}

/// A known move and the cumulative pressure-advanced extrusion before it.
#[derive(Debug, Clone, Copy)]
struct Known {
    mv: Move,
    p_before: f64,
    /// The advance applied to this move (0 when it gets none).
    advance: f64,
}

/// Step generation for an extruder with pressure advance.
#[derive(Debug, Clone)]
pub struct PaGen {
    pa: PressureAdvance,
    step_dist: f64,
    clock_freq: f64,
    moves: VecDeque<Known>,
    /// Nominal E and cumulative P at the end of the last known move.
    end_e: f64,
    end_p: f64,
    /// Print time up to which steps were generated.
    t_done: f64,
    cur_n: i64,
    last_clock: f64,
    started: bool,
    /// −1 when the stepper's direction is inverted (SET_EXTRUDER_ROTATION_DISTANCE < 0).
    sign: f64,
}

impl PaGen {
    pub fn new(pa: PressureAdvance, step_dist: f64, clock_freq: f64) -> PaGen {
        PaGen {
            pa,
            step_dist,
            clock_freq,
            moves: VecDeque::new(),
            end_e: 0.0,
            end_p: 0.0,
            t_done: 0.0,
            cur_n: 0,
            last_clock: 0.0,
            started: false,
            sign: 1.0,
        }
    }

    /// Half the averaging window (s): how far positions depend on the future.
    pub fn half_window(&self) -> f64 {
        0.5 * self.pa.smooth_time
    }

    fn step_index(&self, x: f64) -> i64 {
        (x / self.step_dist + 0.5).floor() as i64
    }

    /// The advance for the moves pushed from now on (≥ 0; smooth_time stays).
    pub fn set_advance(&mut self, advance: f64) {
        if advance.is_finite() && advance >= 0.0 {
            self.pa.advance = advance;
        }
    }

    /// The advance applied to the next moves.
    pub fn advance(&self) -> f64 {
        self.pa.advance
    }

    /// Adds the next final move (in order).
    pub fn push_move(&mut self, mv: &Move) {
        let advanced = mv.axes_r[3] > 0.0 && (mv.axes_r[0] != 0.0 || mv.axes_r[1] != 0.0);
        if !self.started {
            self.started = true;
            self.end_e = mv.start_pos[3];
            self.cur_n = self.step_index(mv.start_pos[3]);
            self.t_done = mv.print_time - self.half_window();
        } else if mv.start_pos[3] != self.end_e {
            // Position redefinition (G92 E): re-anchor without stepping.
            let shift = mv.start_pos[3] - self.end_e;
            for k in &mut self.moves {
                k.mv.start_pos[3] += shift;
                k.mv.end_pos[3] += shift;
            }
            self.end_e = mv.start_pos[3];
            let now = self.stepper_position(self.t_done);
            self.cur_n = self.step_index(now);
        }
        let p_before = self.end_p;
        let advance = if advanced { self.pa.advance } else { 0.0 };
        self.end_p += advance * (mv.end_pos[3] - mv.start_pos[3]);
        self.end_e = mv.end_pos[3];
        self.moves.push_back(Known {
            mv: *mv,
            p_before,
            advance,
        });
    }

    /// Nominal E and cumulative P at print time t.
    fn nominal(&self, t: f64) -> (f64, f64) {
        let i = self.moves.partition_point(|k| k.mv.print_time <= t);
        if i == 0 {
            return match self.moves.front() {
                Some(k) => (k.mv.start_pos[3], k.p_before),
                None => (self.end_e, self.end_p),
            };
        }
        let k = &self.moves[i - 1];
        let rel = t - k.mv.print_time;
        let e = if rel >= k.mv.duration() {
            k.mv.end_pos[3]
        } else {
            k.mv.start_pos[3] + k.mv.axes_r[3] * k.mv.distance_at(rel)
        };
        (e, k.p_before + k.advance * (e - k.mv.start_pos[3]))
    }

    /// The extruder position (mm) at print time t.
    pub fn position(&self, t: f64) -> f64 {
        let h = self.half_window();
        let (e, _) = self.nominal(t);
        let (_, p_hi) = self.nominal(t + h);
        let (_, p_lo) = self.nominal(t - h);
        e + (p_hi - p_lo) / self.pa.smooth_time
    }

    /// The stepper's position (mm, its direction) at print time t.
    fn stepper_position(&self, t: f64) -> f64 {
        self.sign * self.position(t)
    }

    /// A new step distance and direction (`sign` −1: inverted) from here on, with the steps
    /// up to now generated: the stepper stays where it is and counts steps of the new size.
    pub fn set_step_dist(&mut self, step_dist: f64, sign: f64) {
        self.step_dist = step_dist;
        self.sign = if sign < 0.0 { -1.0 } else { 1.0 };
        self.cur_n = self.step_index(self.stepper_position(self.t_done));
    }

    /// Generates steps up to the last known move's end − T/2, or through its end + T/2 when
    /// `at_rest` (the next move starts after that); `emit(ideal_clock, dir)`.
    pub fn generate(&mut self, at_rest: bool, mut emit: impl FnMut(f64, bool)) {
        let Some(last) = self.moves.back() else {
            return;
        };
        let h = self.half_window();
        let end = last.mv.end_time();
        let t_end = if at_rest { end + h } else { end - h };
        if t_end <= self.t_done {
            return;
        }
        // Only where an extruding move is within T/2 can the position change.
        let mut active: Vec<(f64, f64)> = Vec::new();
        for k in self.moves.iter().filter(|k| k.mv.axes_r[3] != 0.0) {
            let (a, b) = (k.mv.print_time - h, k.mv.end_time() + h);
            match active.last_mut() {
                Some(last) if a <= last.1 => last.1 = last.1.max(b),
                _ => active.push((a, b)),
            }
        }
        for (a, b) in active {
            let (a, b) = (a.max(self.t_done), b.min(t_end));
            if a < b {
                self.solve(a, b, &mut emit);
            }
        }
        self.t_done = t_end;
        // Forget moves no position at or after t_done − T/2 depends on.
        while self.moves.len() > 1 && self.moves[1].mv.print_time <= self.t_done - h {
            self.moves.pop_front();
        }
    }

    /// Steps of the interval [t0, t1] (slices, bisection of each half-step crossing).
    fn solve(&mut self, t0: f64, t1: f64, emit: &mut impl FnMut(f64, bool)) {
        let slices = (((t1 - t0) / SLICE_S).ceil() as usize).clamp(1, 1 << 30);
        let span = t1 - t0;
        let mut ta = t0;
        for s in 1..=slices {
            let tb = if s == slices {
                t1
            } else {
                t0 + span * s as f64 / slices as f64
            };
            let nb = self.step_index(self.stepper_position(tb));
            while self.cur_n != nb {
                let up = nb > self.cur_n;
                let boundary = (self.cur_n as f64 + if up { 0.5 } else { -0.5 }) * self.step_dist;
                let (mut lo, mut hi) = (ta, tb);
                for _ in 0..BISECT_ROUNDS {
                    let mid = 0.5 * (lo + hi);
                    let x = self.stepper_position(mid);
                    if (up && x >= boundary) || (!up && x < boundary) {
                        hi = mid;
                    } else {
                        lo = mid;
                    }
                }
                let clock = (hi * self.clock_freq).max(self.last_clock);
                self.last_clock = clock;
                emit(clock, up);
                self.cur_n += if up { 1 } else { -1 };
            }
            ta = tb;
        }
    }

    /// Net steps generated so far.
    pub fn position_steps(&self) -> i64 {
        self.cur_n
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A move along X with extrusion ratio `er` (mm of E per mm) from x0 to x1.
    fn mv(t: f64, x0: f64, x1: f64, e0: f64, er: f64) -> Move {
        let d = x1 - x0;
        let v = 50.0;
        let a = 1000.0;
        let accel_t = v / a;
        let accel_d = 0.5 * v * accel_t;
        Move {
            print_time: t,
            start_pos: [x0, 0.0, 0.0, e0],
            end_pos: [x1, 0.0, 0.0, e0 + er * d],
            axes_r: [1.0, 0.0, 0.0, er],
            move_d: d,
            start_v: 0.0,
            cruise_v: v,
            end_v: 0.0,
            accel: a,
            accel_t,
            cruise_t: (d - 2.0 * accel_d) / v,
            decel_t: accel_t,
        }
    }

    #[test]
    fn advance_leads_while_extruding_and_settles_at_rest() {
        let pa = PressureAdvance {
            advance: 0.05,
            smooth_time: 0.04,
        };
        let mut g = PaGen::new(pa, 0.01, 1e6);
        let m = mv(1.0, 0.0, 20.0, 0.0, 0.05);
        g.push_move(&m);
        // Mid-cruise: E velocity 2.5 mm/s → 0.125 mm ahead.
        let t = 1.0 + m.duration() / 2.0;
        let ahead = g.position(t) - m.position_at(t - 1.0)[3];
        assert!((ahead - 0.125).abs() < 1e-9, "{ahead}");
        let mut steps = Vec::new();
        g.generate(true, |c, d| steps.push((c, d)));
        assert_eq!(g.position_steps(), 100, "1 mm of filament");
        let net: i64 = steps.iter().map(|s| if s.1 { 1 } else { -1 }).sum();
        assert_eq!(net, 100);
        assert!(steps.windows(2).all(|w| w[0].0 <= w[1].0));
        // With advance the last steps go backwards (the advance is taken back while slowing).
        assert!(steps.iter().any(|s| !s.1));
        // The first step is taken before the nominal position reaches half a step.
        let nominal_first = 1.0 + m.time_at_distance(0.005 / 0.05);
        assert!(steps[0].0 / 1e6 < nominal_first);
    }

    #[test]
    fn validates() {
        let ok = PressureAdvance {
            advance: 0.1,
            smooth_time: 0.04,
        };
        assert!(ok.validate().is_ok());
        assert!(PressureAdvance { advance: -1.0, ..ok }.validate().is_err());
        assert!(PressureAdvance {
            smooth_time: 0.0,
            ..ok
        }
        .validate()
        .is_err());
        assert!(PressureAdvance {
            advance: f64::NAN,
            ..ok
        }
        .validate()
        .is_err());
    }
}
