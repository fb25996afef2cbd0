//! Step generation: each stepper's ideal step times for a move, and the step command type.
//!
//! Convention (Klipper's): step k (position k·step_dist) is taken when the commanded position
//! crosses the half-step point between two step positions: going up from k−1 to k at
//! (k − ½)·step_dist, going down from k to k−1 at (k − ½)·step_dist. The stepper's step index
//! for a commanded position x is therefore n(x) = ⌊x / step_dist + ½⌋, and after a move ending at
//! x the net step count is round(x / step_dist).
//!
//! Closed form for linear kinematics: along a move the stepper is at x0 + (x1 − x0)·s/d where s
//! is the distance covered, so the crossing of boundary b happens at s = (b − x0)·d/(x1 − x0)
//! and its time follows from the move's profile inverse ([`crate::toolhead::Phases`]): one square
//! root per step while accelerating or decelerating; while cruising the step time is a line in the
//! step index, one multiply-add per step (benchy: 87 % of the steps).
//!
//! Position redefinitions (G28 without motion, `set_position`) show up as a move whose start is
//! not the previous move's end: the step index is then re-anchored at the new position without
//! stepping.

use crate::kinematics::StepperKin;
use crate::toolhead::{Move, Phases};

/// One step command for the MCU (see notes/contract.md "Step semantics").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StepCmd {
    /// `set_next_step_dir`: true = position +1 per step.
    SetDir { dir: bool },
    /// `reset_step_clock`: the MCU's `last_clock` becomes `clock`.
    ResetClock { clock: u64 },
    /// `queue_step`: repeat `count` times { last_clock += interval; step; interval += add }.
    /// `first_clock` / `last_clock` are the absolute clocks of its first and last step.
    QueueStep {
        interval: u32,
        count: u16,
        add: i16,
        first_clock: u64,
        last_clock: u64,
    },
}

/// A step as generated: its ideal time in MCU ticks and its direction (true = +1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IdealStep {
    pub clock: f64,
    pub dir: bool,
}

/// Receives a move's steps in time order (a closure `FnMut(clock, dir)` is one).
pub trait StepSink {
    /// One step at `clock` ticks going `dir` (true = +1).
    fn step(&mut self, clock: f64, dir: bool);

    /// The steps of a cruise: at max(t0 + i·dt, floor) ticks for i in `from..to`, all going
    /// `dir`, with dt > 0 (so they are in time order and only the first few can be raised to
    /// `floor`). The default calls [`Self::step`] for each; a sink that stores steps can write
    /// them in one tight loop instead, but must compute each clock with this same expression
    /// (bit-identical step times).
    #[inline]
    fn line(&mut self, t0: f64, dt: f64, from: i64, to: i64, floor: f64, dir: bool) {
        line_by_steps(self, t0, dt, from, to, floor, dir);
    }

    /// The next `steps` steps (given to [`Self::step`] right after) lie on `curve`: a hint for
    /// a sink that compresses them (their times are still each step's own). Default: ignored.
    #[inline]
    fn curve(&mut self, _curve: Curve, _steps: usize) {}
}

/// A stretch of steps on one constant acceleration: the squared speed is linear in the step
/// index, v²(j) = r0 + r1·j for step j from the stretch's first, and a step takes about
/// q / v(j) ticks (q = step distance × clock frequency). Plain moves' acceleration and
/// deceleration phases, and shaped stretches where the summed trajectory is quadratic, are such
/// curves: their step clocks are c(j) = α + β·√(γ + j) (γ = r0 / r1, α and β from the phase).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Curve {
    pub q: f64,
    pub r0: f64,
    pub r1: f64,
}

impl Curve {
    /// The second derivative of the step clock in the step index at (real) step `j`, in ticks
    /// per step²: d²c/dj² = −q·r1 / (2·(r0 + r1·j)^{3/2}) (the add a command centred there
    /// would carry). NaN or infinite where the speed reaches 0.
    #[inline]
    pub fn curvature(&self, j: f64) -> f64 {
        let v2 = self.r0 + self.r1 * j;
        -0.5 * self.q * self.r1 / (v2 * v2.sqrt())
    }

    /// The same curve from its step `j` on.
    #[inline]
    pub fn from_step(self, j: usize) -> Curve {
        Curve {
            r0: self.r0 + self.r1 * j as f64,
            ..self
        }
    }
}

/// Clock of step `i` of a cruise line: max(t0 + i·dt, floor). Every writer of a line uses this
/// one expression, so step times are bit-identical however the line is written.
#[inline(always)]
pub fn line_clock(t0: f64, dt: f64, i: i64, floor: f64) -> f64 {
    let t = t0 + i as f64 * dt;
    if t > floor {
        t
    } else {
        floor
    }
}

/// [`StepSink::line`] as one [`StepSink::step`] per step (the default, and the fallback of
/// sinks that write lines their own way).
#[inline]
pub fn line_by_steps<S: StepSink + ?Sized>(
    sink: &mut S,
    t0: f64,
    dt: f64,
    from: i64,
    to: i64,
    floor: f64,
    dir: bool,
) {
    for i in from..to {
        sink.step(line_clock(t0, dt, i, floor), dir);
    }
}

impl<F: FnMut(f64, bool)> StepSink for F {
    #[inline(always)]
    fn step(&mut self, clock: f64, dir: bool) {
        self(clock, dir)
    }
}

/// Step-generation state of one stepper.
#[derive(Debug, Clone)]
pub struct StepGen {
    step_dist: f64,
    inv_step_dist: f64,
    clock_freq: f64,
    /// Stepper position (mm) at the end of the last move.
    last_pos: f64,
    /// Step index of `last_pos`.
    cur_n: i64,
    /// Ideal clock of the last step (steps are never emitted out of order).
    last_clock: f64,
}

impl StepGen {
    /// A stepper at `start_pos` mm whose clock runs `clock_freq` ticks per print second.
    pub fn new(step_dist: f64, clock_freq: f64, start_pos: f64) -> StepGen {
        let mut g = StepGen {
            step_dist,
            inv_step_dist: 1.0 / step_dist,
            clock_freq,
            last_pos: start_pos,
            cur_n: 0,
            last_clock: 0.0,
        };
        g.cur_n = g.step_index(start_pos);
        g
    }

    /// n(x) = ⌊x / step_dist + ½⌋ (saturating for absurd positions).
    #[inline]
    pub fn step_index(&self, x: f64) -> i64 {
        let v = x * self.inv_step_dist + 0.5;
        let t = v as i64;
        // Truncation rounds toward zero: step down for negative non-integers.
        if (t as f64) > v {
            t - 1
        } else {
            t
        }
    }

    /// Net steps [`Self::gen_move`] will emit for `mv` (exact for linear kinematics; a hint for
    /// reserving room otherwise).
    pub fn steps_in(&self, mv: &Move, kin: &StepperKin) -> usize {
        let x0 = kin.position(&mv.start_pos);
        let from = if x0 != self.last_pos {
            self.step_index(x0)
        } else {
            self.cur_n
        };
        self.step_index(kin.position(&mv.end_pos)).abs_diff(from) as usize
    }

    /// A new step distance: the stepper stays at its position, whose step index is counted in
    /// steps of the new size.
    pub fn set_step_dist(&mut self, step_dist: f64) {
        self.step_dist = step_dist;
        self.inv_step_dist = 1.0 / step_dist;
        self.cur_n = self.step_index(self.last_pos);
    }

    /// The stepper position (mm) at the end of the last move.
    pub fn last_pos(&self) -> f64 {
        self.last_pos
    }

    /// Ideal clock of the last step generated (later steps never come before it).
    pub fn last_clock(&self) -> f64 {
        self.last_clock
    }

    /// Makes every later step come no earlier than `clock` (steps queued from another source).
    pub fn raise_last_clock(&mut self, clock: f64) {
        if clock > self.last_clock {
            self.last_clock = clock;
        }
    }

    /// Step index of the commanded position after the last move.
    pub fn commanded_steps(&self) -> i64 {
        self.cur_n
    }

    /// Generates the steps of `mv` into `sink` in time order (`emit(ideal_clock, dir)` for
    /// each, the cruise phase as one [`StepSink::line`]). On linear kinematics every step of one
    /// move goes the same way (the compressor relies on it to find direction changes without
    /// looking at each step).
    pub fn gen_move(&mut self, mv: &Move, kin: &StepperKin, mut sink: impl StepSink) {
        let x0 = kin.position(&mv.start_pos);
        let x1 = kin.position(&mv.end_pos);
        if x0 != self.last_pos {
            self.cur_n = self.step_index(x0);
        }
        self.last_pos = x1;
        let target = self.step_index(x1);
        if target == self.cur_n {
            return;
        }
        if kin.linear_coeffs().is_none() {
            self.gen_iterative(mv, kin, target, |c, d| sink.step(c, d));
            return;
        }
        let base = mv.print_time * self.clock_freq;
        let freq = self.clock_freq;
        let phases = Phases::new(mv);
        let d = mv.move_d;
        let scale = d / (x1 - x0);
        let sd = self.step_dist;
        let mut last = self.last_clock;
        // Steps in time order: up from cur_n + 1, or down from cur_n; the half-step boundary of
        // step k is (k − ½)·step_dist either way.
        let up = target > self.cur_n;
        let (first, n, dk) = if up {
            (self.cur_n + 1, target - self.cur_n, 1)
        } else {
            (self.cur_n, self.cur_n - target, -1)
        };
        // Step i of this move is at distance s0 + i·ds (ds > 0). The cruise phase is a line in
        // i: its steps (most steps of a print) take one multiply-add each. At the phase's ends
        // the profile is continuous, so which formula a boundary step takes changes its time
        // by rounding only.
        let s0 = ((first as f64 - 0.5) * sd - x0) * scale;
        let ds = dk as f64 * sd * scale;
        let (c_from, c_to) = match phases.cruise() {
            Some((start_d, end_d, _, _)) if ds > 0.0 => {
                let at = |dist: f64| {
                    let i = ((dist - s0) / ds).ceil();
                    if i <= 0.0 {
                        0
                    } else if i >= n as f64 {
                        n
                    } else {
                        i as i64
                    }
                };
                (at(start_d), at(end_d))
            }
            _ => (n, n),
        };
        let mut k = first;
        let line = phases.cruise();
        for (i_from, i_to, cruising) in [(0, c_from, false), (c_from, c_to, true), (c_to, n, false)] {
            match line {
                Some((start_d, _, start_t, inv_vc)) if cruising => {
                    // t(i) = base + freq·(start_t + (s0 + i·ds − start_d)·inv_vc)
                    let t0 = base + freq * (start_t + (s0 - start_d) * inv_vc);
                    let dt = freq * ds * inv_vc;
                    if i_to > i_from {
                        sink.line(t0, dt, i_from, i_to, last, up);
                        // The steps rise with i (dt > 0): the last one is the latest.
                        last = line_clock(t0, dt, i_to - 1, last);
                    }
                    k += (i_to - i_from) * dk;
                }
                _ => {
                    // Accelerating before the step at `accel_d`, decelerating from it on (no
                    // step of this loop is in the cruise): v² = v₀² + 2a·s, resp.
                    // v_c² − 2a·(s − cruise_end_d), linear in the step index.
                    let acc_d = mv.accel_d();
                    let split = if ds > 0.0 {
                        // (A NaN converts to 0: the integer clamp keeps the split in range.)
                        (((acc_d - s0) / ds).ceil() as i64).clamp(i_from, i_to)
                    } else {
                        i_to
                    };
                    let two_a = 2.0 * mv.accel;
                    let curves = [
                        (i_from, split, mv.start_v * mv.start_v, 0.0, two_a),
                        (
                            split,
                            i_to,
                            mv.cruise_v * mv.cruise_v,
                            acc_d + mv.cruise_d(),
                            -two_a,
                        ),
                    ];
                    for (a, b, v2, from_d, slope) in curves {
                        if b <= a {
                            continue;
                        }
                        if ds > 0.0 {
                            let r0 = v2 + slope * (s0 + a as f64 * ds - from_d);
                            let curve = Curve {
                                q: freq * ds,
                                r0,
                                r1: slope * ds,
                            };
                            sink.curve(curve, (b - a) as usize);
                        }
                        for _ in a..b {
                            let bound = (k as f64 - 0.5) * sd;
                            let s = ((bound - x0) * scale).clamp(0.0, d);
                            let t = base + phases.time_at(s) * freq;
                            let clock = if t > last { t } else { last };
                            last = clock;
                            sink.step(clock, up);
                            k += dk;
                        }
                    }
                }
            }
        }
        self.last_clock = last;
        self.cur_n = target;
    }

    /// Fallback for non-linear kinematics: scans the move in short time slices and bisects each
    /// half-step crossing. Reversals inside one slice (shorter than a step) net out unseen.
    fn gen_iterative(&mut self, mv: &Move, kin: &StepperKin, target: i64, mut emit: impl FnMut(f64, bool)) {
        const SLICE_S: f64 = 0.000_5;
        const BISECT_ITERS: usize = 40;
        let total = mv.duration();
        let slices = ((total / SLICE_S).ceil() as usize).clamp(1, 1 << 24);
        let base = mv.print_time * self.clock_freq;
        let mut n = self.cur_n;
        let mut ta = 0.0;
        for i in 1..=slices {
            let tb = if i == slices {
                total
            } else {
                total * i as f64 / slices as f64
            };
            let xb = if i == slices {
                self.last_pos
            } else {
                kin.position_at(mv, tb)
            };
            let nb = self.step_index(xb);
            while n != nb {
                let dir = nb > n;
                let boundary = if dir {
                    (n as f64 + 0.5) * self.step_dist
                } else {
                    (n as f64 - 0.5) * self.step_dist
                };
                let (mut lo, mut hi) = (ta, tb);
                for _ in 0..BISECT_ITERS {
                    let mid = 0.5 * (lo + hi);
                    let x = kin.position_at(mv, mid);
                    let crossed = if dir { x >= boundary } else { x < boundary };
                    if crossed {
                        hi = mid;
                    } else {
                        lo = mid;
                    }
                }
                let clock = (base + hi * self.clock_freq).max(self.last_clock);
                self.last_clock = clock;
                emit(clock, dir);
                n += if dir { 1 } else { -1 };
            }
            ta = tb;
        }
        debug_assert_eq!(n, target);
        self.cur_n = target;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mv(start: f64, end: f64, v: f64) -> Move {
        // Accelerate 0 → v, cruise, decelerate to 0 at 1000 mm/s² along X.
        let d = (end - start).abs();
        let a = 1000.0;
        let ad = v * v / (2.0 * a);
        let (vc, accel_d) = if 2.0 * ad > d {
            ((a * d).sqrt(), d / 2.0)
        } else {
            (v, ad)
        };
        let at = vc / a;
        Move {
            print_time: 1.0,
            start_pos: [start, 0.0, 0.0, 0.0],
            end_pos: [end, 0.0, 0.0, 0.0],
            axes_r: [(end - start).signum(), 0.0, 0.0, 0.0],
            move_d: d,
            start_v: 0.0,
            cruise_v: vc,
            end_v: 0.0,
            accel: a,
            accel_t: at,
            cruise_t: (d - 2.0 * accel_d) / vc,
            decel_t: at,
        }
    }

    fn collect(g: &mut StepGen, m: &Move, kin: &StepperKin) -> Vec<(f64, bool)> {
        let mut v = Vec::new();
        g.gen_move(m, kin, |c, d| v.push((c, d)));
        v
    }

    #[test]
    fn steps_at_half_step_crossings() {
        let kin = StepperKin::axis(0, 0.1);
        let mut g = StepGen::new(0.1, 1e6, 0.0);
        let m = mv(0.0, 1.0, 20.0);
        let steps = collect(&mut g, &m, &kin);
        assert_eq!(steps.len(), 10);
        for (k, &(clock, dir)) in steps.iter().enumerate() {
            assert!(dir);
            let t = (clock - 1e6) / 1e6;
            let x = m.position_at(t)[0];
            assert!((x - (k as f64 + 0.5) * 0.1).abs() < 1e-9, "step {k}: x {x}");
        }
        assert!(steps.windows(2).all(|w| w[0].0 <= w[1].0));
        assert_eq!(g.commanded_steps(), 10);
        // Back down to 0.26 mm: 10 → 3 (round(2.6) = 3), seven steps down.
        let back = mv(1.0, 0.26, 20.0);
        let mut b = back;
        b.print_time = m.end_time();
        let steps = collect(&mut g, &b, &kin);
        assert_eq!(steps.len(), 7);
        assert!(steps.iter().all(|s| !s.1));
        assert_eq!(g.commanded_steps(), 3);
    }

    #[test]
    fn cruise_line_matches_the_profile_late_in_a_print() {
        // Cruise steps come from a line in the step index; each must agree with the profile's
        // own time to far below a tick, even an hour into a print at 50 MHz, both ways.
        let kin = StepperKin::axis(0, 0.0125);
        for (start, end) in [(10.0, 150.0), (150.0, 10.0)] {
            let mut m = mv(start, end, 120.0);
            m.print_time = 3600.0;
            let mut g = StepGen::new(0.0125, 50e6, start);
            let steps = collect(&mut g, &m, &kin);
            assert_eq!(steps.len(), 11_200);
            let phases = Phases::new(&m);
            let x0 = start;
            for (i, &(clock, _)) in steps.iter().enumerate() {
                let k = if end > start {
                    g.step_index(x0) + 1 + i as i64
                } else {
                    g.step_index(x0) - i as i64
                };
                let b = (k as f64 - 0.5) * 0.0125;
                let s = ((b - x0) * (m.move_d / (end - start))).clamp(0.0, m.move_d);
                let want = (m.print_time + phases.time_at(s)) * 50e6;
                assert!((clock - want).abs() < 1e-3, "step {i}: {clock} vs {want}");
            }
        }
    }

    #[test]
    fn position_redefinition_reanchors_without_steps() {
        let kin = StepperKin::axis(0, 0.1);
        let mut g = StepGen::new(0.1, 1e6, 0.0);
        let mut m = mv(5.0, 5.5, 20.0);
        m.print_time = 2.0;
        let steps = collect(&mut g, &m, &kin);
        assert_eq!(steps.len(), 5);
        assert_eq!(g.commanded_steps(), 55);
    }

    #[test]
    fn iterative_fallback_matches_closed_form() {
        let kin = StepperKin::axis(0, 0.0125);
        let m = mv(10.0, 13.7, 80.0);
        let mut g1 = StepGen::new(0.0125, 50e6, 10.0);
        let closed = collect(&mut g1, &m, &kin);
        let mut g2 = StepGen::new(0.0125, 50e6, 10.0);
        let target = g2.step_index(13.7);
        g2.last_pos = 13.7;
        let mut iter = Vec::new();
        g2.gen_iterative(&m, &kin, target, |c, d| iter.push((c, d)));
        assert_eq!(closed.len(), iter.len());
        for (a, b) in closed.iter().zip(&iter) {
            assert_eq!(a.1, b.1);
            assert!((a.0 - b.0).abs() < 0.01, "{a:?} vs {b:?}");
        }
    }
}
