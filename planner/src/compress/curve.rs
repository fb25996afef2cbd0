//! A `queue_step` command from a step on one constant-acceleration curve, its add taken from
//! the curve's formula: no search over adds, no pass proving the command the longest.
//!
//! On a curve (see [`crate::stepgen::Curve`]) the step clocks are c(j) = α + β·√(γ + j), whose
//! second difference at step j is about the curve's [`Curve::curvature`] κ(j); a command
//! (interval I, add A) from the MCU's `last_clock` L puts step k at p_k = L + k·I +
//! A·k(k−1)/2, a quadratic whose second difference is A. Step k is valid when
//! e_k = c(j0 + k) − p_k ∈ [0, E] (its window [⌈c − E⌉, ⌊c⌋], E = max_error in ticks).
//!
//! # Why the curvature at the middle is the add
//! Δ²e_k ≈ κ(j0 + k) − A. κ is monotone along a curve (c''' = 3·q·r1²/(4·v⁵) > 0 for an
//! acceleration and a deceleration alike), so Δ²e changes sign at most once: e is concave then
//! convex, its first difference Δe is convex in k with at most two zeros, and e has at most
//! two interior extrema (a maximum then a minimum) besides the ends k = 1 and k = n. With
//! A = κ at the middle m of the command, Δ²e is negative before m and positive after, the
//! extrema sit symmetrically about m, and the spread of e over n steps is the cubic term's:
//! max e − min e ≈ c'''·n³/72 (a cubic against the quadratic matching its second derivative at
//! the centre, at the ends and at m ± n/(2√3)), within 4/3 of the least any add reaches
//! (Chebyshev's equioscillating residue, c'''·n³/96). So a command of n steps with this add
//! exists whenever c'''·n³/72 + n²/16 (A rounded to an integer) + 1 (I an integer) ≤ E: the
//! add is right for a command as long as the expected one.
//!
//! # What a command costs
//! The add is the curvature at the middle of the expected command (the previous command's
//! length), rounded and clamped into the adds landing the first two steps
//! (`fit::first_two_adds`). The interval and count come from one exact pass over the stored
//! windows with that add (`fit::run`, which also gives the largest interval one step shorter):
//! the pass is the verification, so every command is valid on every step whatever the float
//! formula says (no float margin is needed), and its count is the longest for that add. When
//! the pass stops short of the expected middle, a second one tries the curvature at the middle
//! of the run it got ([`PASSES`] in all). The search (`compress::fit`) would go on bisecting
//! over adds to prove the command the longest (≈ 10 passes for the benchy's commands starting
//! on curves, 6.5 steps on average); a command here may be a step shorter than the longest,
//! which the benchy's counts measure (README "`cadence bench plan`", per-command design).
//!
//! Where the formula does not apply (delta and other non-linear kinematics, fewer than 3 steps
//! left, steps between spans) the search decides.
//!
//! Hot path: no allocation and no panic (the slice is checked to hold at least 3 steps; the
//! passes are `fit::run`'s).

use super::fit::{binding_adds, first_two_adds, run, Bend, Fit, StepWindow};
use super::Span;
use crate::stepgen::Curve;

/// A stretch of pending steps on one curve: the step at pending index `start + j` (j <
/// `end − start`) is the curve's step j.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct CurveSpan {
    pub start: usize,
    pub end: usize,
    pub curve: Curve,
}

impl Span for CurveSpan {
    #[inline]
    fn range(&self) -> (usize, usize) {
        (self.start, self.end)
    }

    #[inline]
    fn moved(self, cut: usize, by: usize) -> CurveSpan {
        CurveSpan {
            start: self.start + cut - by,
            end: self.end - by,
            curve: self.curve.from_step(cut),
        }
    }
}

impl CurveSpan {
    /// The add for a command whose first step is at pending index `at` (on the span), whose
    /// anchor (the MCU's `last_clock`) lies `e0` ticks before the ideal clock of the step before
    /// `at`, its steps to stay within `band` ticks (module doc, "The add"); `None` where the
    /// formula gives no finite number.
    #[inline]
    fn add_for(&self, at: usize, e0: f64, band: f64) -> Option<i64> {
        let c = &self.curve;
        // Curve index of the command's anchor (its step k = 0): the step before `at`.
        let j0 = at.saturating_sub(self.start) as f64 - 1.0;
        // s = c'''/6 = q·r1²/(8·v⁵), taken at the band's centre (the second round moves it there).
        let third = |j: f64| {
            let v2 = c.r0 + c.r1 * j;
            c.q * c.r1 * c.r1 / (8.0 * v2 * v2 * v2.sqrt())
        };
        // Where on the equioscillating cubic's first rising branch the anchor's error lies:
        // x0 = cos((2π + arccos(2·e0/band − 1))/3) ∈ [−1, −½].
        let y = (2.0 * e0 / band - 1.0).clamp(-1.0, 1.0);
        let x0 = ((2.0 * std::f64::consts::PI + y.acos()) / 3.0).cos();
        let mut centre = j0;
        for _ in 0..2 {
            let n_band = (16.0 * band / third(centre)).cbrt();
            // The band's centre from the anchor: N/2 − t0, t0 = N·(1 + x0)/2.
            centre = j0 - 0.5 * n_band * x0;
        }
        let a = c.curvature(centre).round();
        a.is_finite()
            .then_some(a.clamp(i16::MIN as f64, i16::MAX as f64) as i64)
    }

    /// The ideal clock of the step before pending index `at` less `last`, estimated from the
    /// window of the step at `at` (its middle tick) and the curve's step time there.
    #[inline]
    fn anchor_error(&self, first: StepWindow, at: usize, last: u64) -> f64 {
        let c = &self.curve;
        let j = at.saturating_sub(self.start) as f64;
        let dt = c.q / (c.r0 + c.r1 * (j - 0.5)).max(f64::MIN_POSITIVE).sqrt();
        first.hi as f64 + 0.5 - dt - last as f64
    }
}

/// Default of the most passes over the steps per curve command (`SearchTuning::curve_passes`).
pub(crate) const PASSES: usize = 3;

/// The add of the curve's formula for a command from `last` over `steps` (the pending steps
/// from index `at`, one direction, `at` in `span`), clamped into the adds that land the first
/// two steps (module doc); `None` where the formula gives none.
pub(crate) fn curve_add(
    span: &CurveSpan,
    steps: &[StepWindow],
    at: usize,
    last: u64,
    max_err: i64,
) -> Option<i64> {
    formula_add(span, steps, at, last, max_err).map(|(a, _)| a)
}

/// [`curve_add`] with the range of adds landing the first two steps.
#[inline]
fn formula_add(
    span: &CurveSpan,
    steps: &[StepWindow],
    at: usize,
    last: u64,
    max_err: i64,
) -> Option<(i64, (i64, i64))> {
    if steps.len() < 3 || at < span.start || at >= span.end {
        return None;
    }
    let (lo, hi) = first_two_adds(steps, last);
    let (lo, hi) = (lo.max(i16::MIN as i64), hi.min(i16::MAX as i64));
    if lo > hi {
        return None;
    }
    let band = (max_err as f64 - 1.0).max(1.0);
    let e0 = span.anchor_error(steps[0], at, last).clamp(0.0, band);
    Some((span.add_for(at, e0, band)?.clamp(lo, hi), (lo, hi)))
}

/// The command from `last` over `steps` (the pending steps from index `at`, one direction,
/// `at` in `span`) with the add of the curve's formula (module doc); `None` where the formula
/// gives no add.
pub(crate) fn curve_command(
    span: &CurveSpan,
    steps: &[StepWindow],
    at: usize,
    last: u64,
    max_err: i64,
    passes: usize,
) -> Option<Fit> {
    let (mut add, (lo, hi)) = formula_add(span, steps, at, last, max_err)?;
    let mut best = Fit::NONE;
    // The smallest add tried that fell short of the best count (adds covering a count form a
    // range, as the search assumes): it caps the latest-end search.
    let mut short_above = i16::MAX as i64 + 1;
    for _ in 0..passes.max(1) {
        let r = run(steps, last, add);
        if r.count < best.count && add > best.add {
            short_above = short_above.min(add);
        } else if r.count > best.count && best.add > add {
            short_above = short_above.min(best.add);
        }
        if r.count > best.count || (r.count == best.count && add > best.add) {
            best = Fit {
                interval: r.interval,
                count: r.count,
                add,
                prefix_interval: r.prefix_interval,
                add_cap: i16::MAX as i64,
            };
        }
        if r.bend == Bend::None {
            break;
        }
        // The nearest add the bend's way that could land the failing step with the steps that
        // bound this run (`fit::binding_adds`).
        let ((blo, bhi), none) = binding_adds(steps, last, &r);
        let (blo, bhi) = (blo.max(lo), bhi.min(hi));
        let next = if r.bend == Bend::Up {
            (add + 1).max(blo)
        } else {
            (add - 1).min(bhi)
        };
        if none || next < blo || next > bhi {
            break;
        }
        add = next;
    }
    if short_above > best.add {
        best.add_cap = short_above - 1;
    }
    (best.count >= 1).then_some(best)
}

#[cfg(test)]
mod tests {
    use super::super::fit::{longest_fit, NO_PREFIX};
    use super::*;

    /// The windows of steps on `curve` from `t0`: each step q / v(j − ½) ticks after the
    /// previous one (the curve's clocks up to a fraction of a tick).
    fn windows(curve: &Curve, n: usize, t0: f64, err: i64) -> Vec<StepWindow> {
        let mut c = t0;
        (0..n)
            .map(|j| {
                let v2 = curve.r0 + curve.r1 * (j as f64 - 0.5);
                c += curve.q / v2.max(1e-9).sqrt();
                let hi = c as i64;
                let lo = (hi + i64::from(c > hi as f64) - err).max(0) as u64;
                StepWindow {
                    lo,
                    hi: hi as u64,
                    dir: true,
                }
            })
            .collect()
    }

    /// Every step of the command inside its window, by brute force.
    fn valid(w: &[StepWindow], last: u64, f: &Fit) -> bool {
        (1..=f.count as i64).all(|k| {
            let p = last as i64 + k * f.interval + f.add * k * (k - 1) / 2;
            let s = w[k as usize - 1];
            s.lo as i64 <= p && p <= s.hi as i64
        })
    }

    #[test]
    fn an_acceleration_gives_about_the_searchs_longest_command() {
        // 20 mm/s up at 3000 mm/s², 0.0125 mm steps, 50 MHz, 25 µs bound.
        let curve = Curve {
            q: 0.0125 * 50e6,
            r0: 400.0,
            r1: 2.0 * 3000.0 * 0.0125,
        };
        let w = windows(&curve, 300, 1e9, 1250);
        let span = CurveSpan {
            start: 0,
            end: 300,
            curve,
        };
        let f = curve_command(&span, &w[1..], 1, w[0].hi, 1250, PASSES).unwrap();
        assert!(valid(&w[1..], w[0].hi, &f), "{f:?}");
        let s = longest_fit(&w[1..], w[0].hi, 1250, 0, usize::MAX).count;
        assert!(f.count + 1 >= s, "{f:?}, search {s}");
        assert!(f.count >= 8 && f.add < 0, "{f:?}");
    }

    proptest::proptest! {
        /// On an accelerating or decelerating stretch, a command given is valid on every step,
        /// one step shorter too, and covers at least half the steps of the search's longest (from a
        /// start the previous step's landing, as in the compressor).
        #[test]
        fn curve_commands_are_valid_and_longest(
            v in 5.0f64..300.0,
            accel in 200.0f64..20_000.0,
            decel in proptest::bool::ANY,
            n in 3usize..400,
            skip in 1usize..50,
            back in 0.0f64..1.0,
            err in 10i64..2000,
        ) {
            let (sd, freq) = (0.0125, 50e6);
            // Decelerating from v over n + skip steps, or accelerating from v.
            let r1 = if decel { -2.0 * accel * sd } else { 2.0 * accel * sd };
            let r0 = v * v - if decel { r1 * (n + skip) as f64 } else { 0.0 };
            let r0 = r0.max(1.0);
            let curve = Curve { q: sd * freq, r0, r1 };
            let t0 = 1e9;
            let all = windows(&curve, n + skip, t0, err);
            let w = &all[skip..];
            let span = CurveSpan { start: 0, end: n + skip, curve };
            // The previous command landed the step before in its window, as in the compressor.
            let prev = all[skip - 1];
            let last = ((prev.hi as f64 - back * err as f64) as u64).clamp(prev.lo, prev.hi);
            let Some(f) = curve_command(&span, w, skip, last, err, PASSES) else {
                return Ok(());
            };
            proptest::prop_assert!(valid(w, last, &f), "{:?}", f);
            if f.count >= 2 && f.prefix_interval != NO_PREFIX {
                let shorter = Fit { interval: f.prefix_interval, count: f.count - 1, ..f };
                proptest::prop_assert!(valid(w, last, &shorter), "{:?}", f);
            }
            let s = longest_fit(w, last, err, 0, usize::MAX);
            proptest::prop_assert!(2 * f.count >= s.count, "curve {:?}, search {:?}", f, s);
        }
    }
}
