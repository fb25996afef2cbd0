//! Step generation for a stepper whose X/Y motion is input shaped ([`crate::shaper`]).
//!
//! The stepper follows s(t) = Σₐ cₐ · Σⱼ aₐⱼ · xₐ(t + oₐⱼ) over the axes X, Y, Z it depends on
//! (its linear map's coefficients cₐ; Z and unshaped axes carry the identity pulse), where
//! xₐ is the commanded toolhead trajectory: a chain of pieces (each phase of a move, and rest
//! between moves) on which every axis is a quadratic in time. Each term (axis, pulse) of the sum
//! is that chain shifted by its offset, so s is itself piecewise quadratic, its breakpoints the
//! union of the shifted piece boundaries. The generator walks those segments in time order with
//! a cursor per term (no search, no allocation once warm), sums the terms' quadratics into one
//! s(ta + w) = s₀ + s₁·w + s₂·w², splits it at its extremum and solves each half-step crossing
//! (Klipper's step convention, as [`crate::stepgen`]) in closed form:
//! w = 2d / (v ± √(v² + 4·s₂·d)) from the part's start, d the distance to the crossing (no
//! cancellation either way). Where every term is in a cruise (s₂ = 0) the crossings are a line
//! in the step index, handed on as one [`StepSink::line`] (benchy, mzv 50/40 Hz: most shaped
//! steps).
//!
//! The shaped position at t depends on the commanded trajectory up to t + lead (the largest
//! offset), so steps are generated up to the end of the known moves − lead, and through their
//! end + lag (the largest negative offset) once the toolhead is at rest. A new position without
//! motion (G92, G28) shifts the whole known trajectory and re-anchors the step index, like the
//! plain generator. Moves that do not move this stepper's axes add no pieces.

use std::collections::VecDeque;

use crate::shaper::{InputShaper, MAX_PULSES};
use crate::stepgen::{line_clock, Curve, StepSink};
use crate::toolhead::Move;

/// Terms of the sum: up to [`MAX_PULSES`] per axis X, Y, Z.
const MAX_TERMS: usize = 3 * MAX_PULSES;

/// How far before the first move the initial rest piece starts (s): before any term looks.
const REST_BEFORE_S: f64 = 10.0;

/// One pulse of one axis, weighted by the stepper's coefficient of that axis.
#[derive(Debug, Clone, Copy, Default)]
struct Term {
    axis: usize,
    offset: f64,
    weight: f64,
}

/// A stretch of the commanded trajectory from `t0` until the next piece's `t0`, on which axis
/// a is at `p[a] + v[a]·u + h[a]·u²` (u = t − t0).
#[derive(Debug, Clone, Copy)]
struct Piece {
    t0: f64,
    p: [f64; 3],
    v: [f64; 3],
    h: [f64; 3],
}

impl Piece {
    fn rest(t0: f64, p: [f64; 3]) -> Piece {
        Piece {
            t0,
            p,
            v: [0.0; 3],
            h: [0.0; 3],
        }
    }
}

/// True when `shaper` changes the motion of a stepper with linear map `coeffs` (X, Y, Z, E):
/// it follows a shaped axis and not the extruder.
pub fn shapes(coeffs: &[f64; 4], shaper: &InputShaper) -> bool {
    coeffs[3] == 0.0 && ((coeffs[0] != 0.0 && shaper.x.enabled()) || (coeffs[1] != 0.0 && shaper.y.enabled()))
}

/// The shaped step generator of one stepper.
#[derive(Debug, Clone)]
pub struct ShapedGen {
    coeffs: [f64; 3],
    terms: [Term; MAX_TERMS],
    n_terms: usize,
    /// Largest offset (s, ≥ 0) and largest negative offset, negated (s, ≥ 0).
    lead: f64,
    lag: f64,
    step_dist: f64,
    inv_step_dist: f64,
    clock_freq: f64,
    pieces: VecDeque<Piece>,
    /// Absolute index of `pieces[0]` (pieces forgotten so far).
    popped: usize,
    /// Per term: absolute index of the piece its shifted time is in.
    cursor: [usize; MAX_TERMS],
    /// Commanded X, Y, Z at the end of the last move.
    last: [f64; 3],
    /// Print time up to which the commanded trajectory is known.
    known_until: f64,
    /// Print time up to which steps were generated.
    t_done: f64,
    cur_n: i64,
    last_clock: f64,
    started: bool,
}

impl ShapedGen {
    /// A generator for the stepper whose linear map is `coeffs` (X, Y, Z, E; E must be 0),
    /// `step_dist` mm per step, its clock at `clock_freq` ticks per print second.
    pub fn new(coeffs: &[f64; 4], shaper: &InputShaper, step_dist: f64, clock_freq: f64) -> ShapedGen {
        let mut g = ShapedGen {
            coeffs: [coeffs[0], coeffs[1], coeffs[2]],
            terms: [Term::default(); MAX_TERMS],
            n_terms: 0,
            lead: 0.0,
            lag: 0.0,
            step_dist,
            inv_step_dist: 1.0 / step_dist,
            clock_freq,
            pieces: VecDeque::with_capacity(256),
            popped: 0,
            cursor: [0; MAX_TERMS],
            last: [0.0; 3],
            known_until: 0.0,
            t_done: 0.0,
            cur_n: 0,
            last_clock: 0.0,
            started: false,
        };
        g.set_terms(shaper);
        g
    }

    fn set_terms(&mut self, shaper: &InputShaper) {
        let mut n = 0;
        for (axis, pulses) in shaper.axis_pulses().iter().enumerate() {
            let c = self.coeffs[axis];
            if c == 0.0 {
                continue;
            }
            for (offset, a) in pulses.iter() {
                if let Some(t) = self.terms.get_mut(n) {
                    *t = Term {
                        axis,
                        offset,
                        weight: c * a,
                    };
                    n += 1;
                }
            }
        }
        self.n_terms = n;
        let offsets = self.terms[..n].iter().map(|t| t.offset);
        self.lead = offsets.clone().fold(0.0, f64::max);
        self.lag = -offsets.fold(0.0, f64::min);
        self.cursor = [self.popped; MAX_TERMS];
    }

    /// New shaper settings, with the toolhead at rest after the known moves (call
    /// [`Self::generate`] with `at_rest` first: the old shaping's steps are all out). The next
    /// move must start at least the old lag + the new lead after the last one ended.
    pub fn set_shaper(&mut self, shaper: &InputShaper) {
        self.set_terms(shaper);
        if self.started {
            // At rest from known_until on: every term reads the rest piece from here.
            self.t_done = self.t_done.max(self.known_until + self.lag);
        }
    }

    /// Forgets the known trajectory (a homing move was stopped part-way: its steps not generated
    /// are dropped, and print time may go back): the next move starts the generator again at
    /// its own start position, as a new one.
    pub fn restart(&mut self) {
        self.started = false;
        self.pieces.clear();
        self.popped = 0;
        self.cursor = [0; MAX_TERMS];
        self.known_until = f64::NEG_INFINITY;
        self.last_clock = 0.0;
    }

    /// The stepper's shaped position (mm) at print time `t` (from the known trajectory).
    pub fn position(&self, t: f64) -> f64 {
        self.terms[..self.n_terms]
            .iter()
            .map(|term| {
                let tau = t + term.offset;
                let i = self.pieces.partition_point(|p| p.t0 <= tau).saturating_sub(1);
                self.pieces
                    .get(i)
                    .map_or(term.weight * self.last[term.axis], |p| {
                        let u = tau - p.t0;
                        let a = term.axis;
                        term.weight * (p.p[a] + (p.v[a] + p.h[a] * u) * u)
                    })
            })
            .sum()
    }

    /// n(x) = ⌊x / step_dist + ½⌋.
    #[inline]
    fn step_index(&self, x: f64) -> i64 {
        (x * self.inv_step_dist + 0.5).floor() as i64
    }

    /// Adds the next final move (in order).
    pub fn push_move(&mut self, mv: &Move) {
        let start = [mv.start_pos[0], mv.start_pos[1], mv.start_pos[2]];
        if !self.started {
            self.started = true;
            self.last = start;
            self.pieces.clear();
            self.popped = 0;
            self.pieces
                .push_back(Piece::rest(mv.print_time - REST_BEFORE_S, start));
            self.cursor = [0; MAX_TERMS];
            self.t_done = mv.print_time - self.lead;
            self.cur_n = self.step_index(self.position(self.t_done));
        } else if (0..3).any(|a| self.coeffs[a] != 0.0 && start[a] != self.last[a]) {
            // Position redefinition: shift the known trajectory, re-anchor without stepping.
            let shift = [0, 1, 2].map(|a| start[a] - self.last[a]);
            for p in self.pieces.iter_mut() {
                for (x, d) in p.p.iter_mut().zip(shift) {
                    *x += d;
                }
            }
            self.last = start;
            self.cur_n = self.step_index(self.position(self.t_done));
        }
        let moves_here = (0..3).any(|a| self.coeffs[a] != 0.0 && mv.axes_r[a] != 0.0);
        if moves_here {
            // The rest piece after the previous move gives way when this one follows at once.
            if self.pieces.len() > 1 && self.pieces.back().is_some_and(|p| p.t0 >= mv.print_time) {
                self.pieces.pop_back();
                let back = self.popped + self.pieces.len() - 1;
                for c in &mut self.cursor {
                    *c = (*c).min(back);
                }
            }
            let r = [mv.axes_r[0], mv.axes_r[1], mv.axes_r[2]];
            let piece = |t0: f64, d0: f64, v: f64, acc: f64| Piece {
                t0,
                p: [0, 1, 2].map(|a| start[a] + r[a] * d0),
                v: [0, 1, 2].map(|a| r[a] * v),
                h: [0, 1, 2].map(|a| 0.5 * r[a] * acc),
            };
            let t_cruise = mv.print_time + mv.accel_t;
            let t_decel = t_cruise + mv.cruise_t;
            if mv.accel_t > 0.0 {
                self.pieces
                    .push_back(piece(mv.print_time, 0.0, mv.start_v, mv.accel));
            }
            if mv.cruise_t > 0.0 {
                self.pieces
                    .push_back(piece(t_cruise, mv.accel_d(), mv.cruise_v, 0.0));
            }
            if mv.decel_t > 0.0 {
                let d = mv.accel_d() + mv.cruise_d();
                self.pieces.push_back(piece(t_decel, d, mv.cruise_v, -mv.accel));
            }
            let end = [mv.end_pos[0], mv.end_pos[1], mv.end_pos[2]];
            self.pieces.push_back(Piece::rest(mv.end_time(), end));
        }
        self.last = [mv.end_pos[0], mv.end_pos[1], mv.end_pos[2]];
        self.known_until = self.known_until.max(mv.end_time());
    }

    /// Generates the steps up to the last known move's end − lead, or through its end + lag
    /// when `at_rest` (the next move starts no earlier than lag + lead after it);
    /// `sink` gets them in time order.
    pub fn generate(&mut self, at_rest: bool, mut sink: impl StepSink) {
        if !self.started || self.n_terms == 0 {
            return;
        }
        let t_end = if at_rest {
            self.known_until + self.lag
        } else {
            self.known_until - self.lead
        };
        if t_end.is_nan() || t_end <= self.t_done {
            return;
        }
        let mut ta = self.t_done;
        loop {
            // Advance each term's cursor to the piece its time is in; the segment ends at the
            // first next boundary.
            let mut tb = t_end;
            for k in 0..self.n_terms {
                let o = self.terms[k].offset;
                while let Some(next) = self.pieces.get(self.cursor[k] + 1 - self.popped) {
                    let at = next.t0 - o;
                    if at <= ta {
                        self.cursor[k] += 1;
                    } else {
                        tb = tb.min(at);
                        break;
                    }
                }
            }
            let (mut s0, mut s1, mut s2) = (0.0, 0.0, 0.0);
            for k in 0..self.n_terms {
                let term = self.terms[k];
                let Some(p) = self.pieces.get(self.cursor[k] - self.popped) else {
                    continue;
                };
                let a = term.axis;
                let u = ta + term.offset - p.t0;
                s0 += term.weight * (p.p[a] + (p.v[a] + p.h[a] * u) * u);
                s1 += term.weight * (p.v[a] + 2.0 * p.h[a] * u);
                s2 += term.weight * p.h[a];
            }
            self.segment(ta, tb - ta, [s0, s1, s2], &mut sink);
            if tb >= t_end {
                break;
            }
            ta = tb;
        }
        self.t_done = t_end;
        // Forget the pieces no term reads any more.
        let keep = self.cursor[..self.n_terms]
            .iter()
            .copied()
            .min()
            .unwrap_or(self.popped);
        while self.popped < keep && self.pieces.len() > 1 {
            self.pieces.pop_front();
            self.popped += 1;
        }
    }

    /// The steps of s(ta + w) = s₀ + s₁·w + s₂·w² for w in [0, len].
    #[inline]
    fn segment(&mut self, ta: f64, len: f64, s: [f64; 3], sink: &mut impl StepSink) {
        let [s0, s1, s2] = s;
        let at = |w: f64| s0 + (s1 + s2 * w) * w;
        // Split at the extremum when it is inside: each part is monotone.
        let turn = if s2 != 0.0 { -s1 / (2.0 * s2) } else { -1.0 };
        let parts = if turn > 0.0 && turn < len {
            [(0.0, turn), (turn, len)]
        } else {
            [(0.0, len), (len, len)]
        };
        for (wa, wb) in parts {
            let target = self.step_index(at(wb));
            if target == self.cur_n {
                continue;
            }
            let sa = at(wa);
            let va = s1 + 2.0 * s2 * wa;
            let span = wb - wa;
            let base = ta + wa;
            if s2 == 0.0 {
                // A line: crossing i at base + (d₀ + i·dd)/va, dd = ±step_dist.
                let up = target > self.cur_n;
                let n = (target - self.cur_n).abs();
                let half = if up { 0.5 } else { -0.5 };
                let d0 = (self.cur_n as f64 + half) * self.step_dist - sa;
                let dd = if up { self.step_dist } else { -self.step_dist };
                let t0 = (base + d0 / va) * self.clock_freq;
                let dt = dd / va * self.clock_freq;
                let end = (base + span) * self.clock_freq;
                // Only when it lies in the part (not a crawl at the edge of a boundary).
                if dt > 0.0 && t0 + (n - 1) as f64 * dt <= end + 1.0 {
                    sink.line(t0, dt, 0, n, self.last_clock, up);
                    self.last_clock = line_clock(t0, dt, n - 1, self.last_clock);
                    self.cur_n = target;
                    continue;
                }
            }
            // v² = va² + 4·s₂·d, d the distance from the part's start: linear in the step index.
            let up = target > self.cur_n;
            let (half, dd) = if up {
                (0.5, self.step_dist)
            } else {
                (-0.5, -self.step_dist)
            };
            let d0 = (self.cur_n as f64 + half) * self.step_dist - sa;
            let curve = Curve {
                q: self.step_dist * self.clock_freq,
                r0: va * va + 4.0 * s2 * d0,
                r1: 4.0 * s2 * dd,
            };
            sink.curve(curve, target.abs_diff(self.cur_n) as usize);
            while self.cur_n != target {
                let up = target > self.cur_n;
                let half = if up { 0.5 } else { -0.5 };
                let d = (self.cur_n as f64 + half) * self.step_dist - sa;
                let root = (va * va + 4.0 * s2 * d).max(0.0).sqrt();
                let den = if up { va + root } else { va - root };
                let mut u = 2.0 * d / den;
                // Negative or NaN (0/0 at a standstill on the boundary): at the part's start.
                if u.is_nan() || u < 0.0 {
                    u = 0.0;
                }
                if u > span {
                    u = span;
                }
                let clock = (base + u) * self.clock_freq;
                let clock = if clock > self.last_clock {
                    clock
                } else {
                    self.last_clock
                };
                self.last_clock = clock;
                sink.step(clock, up);
                self.cur_n += if up { 1 } else { -1 };
            }
        }
    }

    /// Net step index reached so far.
    pub fn position_steps(&self) -> i64 {
        self.cur_n
    }

    /// How long before a commanded motion its shaped steps start, and after it they settle (s).
    pub fn span(&self) -> f64 {
        self.lead.max(self.lag)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shaper::{AxisShaper, ShaperType};

    /// A rest-to-rest move along direction `r` (unit, X/Y) from `from` over `d` mm.
    fn mv(t: f64, from: [f64; 2], r: [f64; 2], d: f64, v: f64, accel: f64) -> Move {
        let ad = v * v / (2.0 * accel);
        let (vc, accel_d) = if 2.0 * ad > d {
            ((accel * d).sqrt(), d / 2.0)
        } else {
            (v, ad)
        };
        let at = vc / accel;
        Move {
            print_time: t,
            start_pos: [from[0], from[1], 0.0, 0.0],
            end_pos: [from[0] + r[0] * d, from[1] + r[1] * d, 0.0, 0.0],
            axes_r: [r[0], r[1], 0.0, 0.0],
            move_d: d,
            start_v: 0.0,
            cruise_v: vc,
            end_v: 0.0,
            accel,
            accel_t: at,
            cruise_t: (d - 2.0 * accel_d) / vc,
            decel_t: at,
        }
    }

    fn mzv(fx: f64, fy: f64) -> InputShaper {
        InputShaper {
            x: AxisShaper {
                freq: fx,
                ..AxisShaper::default()
            },
            y: AxisShaper {
                freq: fy,
                ..AxisShaper::default()
            },
        }
    }

    fn run(g: &mut ShapedGen, moves: &[Move]) -> Vec<(f64, bool)> {
        let mut steps = Vec::new();
        for m in moves {
            g.push_move(m);
            g.generate(false, |c, d| steps.push((c, d)));
        }
        g.generate(true, |c, d| steps.push((c, d)));
        steps
    }

    #[test]
    fn identity_matches_the_commanded_crossings() {
        // Without shaping the generator steps where the commanded position crosses each half step.
        let m = mv(1.0, [0.0, 0.0], [1.0, 0.0], 10.0, 100.0, 3000.0);
        let mut g = ShapedGen::new(&[1.0, 0.0, 0.0, 0.0], &InputShaper::default(), 0.0125, 1e6);
        let steps = run(&mut g, &[m]);
        assert_eq!(steps.len(), 800);
        for (k, &(clock, dir)) in steps.iter().enumerate() {
            assert!(dir);
            let x = m.position_at(clock / 1e6 - 1.0)[0];
            assert!((x - (k as f64 + 0.5) * 0.0125).abs() < 1e-9, "step {k}: {x}");
        }
    }

    #[test]
    fn shaped_steps_follow_the_convolution_and_end_at_the_target() {
        let shaper = mzv(50.0, 40.0);
        let [px, py, _] = shaper.axis_pulses();
        let moves = [
            mv(1.0, [10.0, 10.0], [0.6, 0.8], 25.0, 150.0, 3000.0),
            mv(1.5, [25.0, 30.0], [-1.0, 0.0], 3.0, 150.0, 3000.0),
        ];
        let commanded = |t: f64| {
            let m = moves
                .iter()
                .rev()
                .find(|m| m.print_time <= t)
                .unwrap_or(&moves[0]);
            m.position_at(t - m.print_time)
        };
        // corexy A = x + y: both axes' shapers at once.
        let mut g = ShapedGen::new(&[1.0, 1.0, 0.0, 0.0], &shaper, 0.0125, 1e6);
        let steps = run(&mut g, &moves);
        let mut n = g.step_index(20.0);
        for &(clock, dir) in &steps {
            let t = clock / 1e6;
            let shaped: f64 = px.iter().map(|(o, a)| a * commanded(t + o)[0]).sum::<f64>()
                + py.iter().map(|(o, a)| a * commanded(t + o)[1]).sum::<f64>();
            let boundary = (n as f64 + if dir { 0.5 } else { -0.5 }) * 0.0125;
            assert!((shaped - boundary).abs() < 1e-9, "{t}: {shaped} vs {boundary}");
            n += if dir { 1 } else { -1 };
        }
        assert!(steps.windows(2).all(|w| w[0].0 <= w[1].0));
        // Ends exactly at the commanded position: 22 + 30 = 52 mm.
        assert_eq!(n, g.position_steps());
        assert_eq!(n, 4160);
        assert!((g.position(10.0) - 52.0).abs() < 1e-12);
        // The shaped motion starts before the commanded one (by the shaper's lead).
        assert!(steps[0].0 / 1e6 < 1.0 && steps[0].0 / 1e6 > 1.0 - g.span());
    }

    #[test]
    fn position_redefinition_reanchors() {
        let shaper = mzv(50.0, 0.0);
        let mut g = ShapedGen::new(&[1.0, 0.0, 0.0, 0.0], &shaper, 0.0125, 1e6);
        let a = mv(1.0, [0.0, 0.0], [1.0, 0.0], 5.0, 100.0, 3000.0);
        let b = mv(2.0, [100.0, 0.0], [1.0, 0.0], 5.0, 100.0, 3000.0);
        let steps = run(&mut g, &[a, b]);
        assert_eq!(steps.len(), 800);
        assert_eq!(g.position_steps(), 8400);
    }

    #[test]
    fn other_axes_moves_add_nothing_and_shapers_change_at_rest() {
        let mut g = ShapedGen::new(&[0.0, 1.0, 0.0, 0.0], &mzv(50.0, 40.0), 0.0125, 1e6);
        let x_only = mv(1.0, [0.0, 0.0], [1.0, 0.0], 20.0, 100.0, 3000.0);
        let steps = run(&mut g, &[x_only]);
        assert!(steps.is_empty());
        assert_eq!(g.pieces.len(), 1);
        g.set_shaper(&InputShaper {
            y: AxisShaper {
                shaper_type: ShaperType::ThreeHumpEi,
                freq: 30.0,
                damping_ratio: 0.1,
            },
            ..InputShaper::default()
        });
        let y = mv(2.0, [20.0, 0.0], [0.0, 1.0], 20.0, 100.0, 3000.0);
        let steps = run(&mut g, &[y]);
        assert_eq!(steps.len(), 1600);
        assert!(steps[0].0 / 1e6 > 2.0 - g.span() - 1e-9);
    }
}
