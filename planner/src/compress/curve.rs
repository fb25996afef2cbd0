//! The longest command from a step on one constant-acceleration curve, the adds the curve's
//! formula gives tried first (off by default: `StepCompressor::set_curve_fit`).
//!
//! On a curve (see [`crate::stepgen::Curve`]) the step clocks are c(j) = α + β·√(γ + j), whose
//! second difference at step j is the curve's [`Curve::curvature`]; a command (interval I,
//! add A) puts its steps on a quadratic whose second difference is A. The command covering
//! the most steps from a given one carries about the curvature at its middle: the first add
//! tried is that of the middle of a command as long as the previous one, the second that of
//! the middle of the first pass's run, and later ones the middle of the adds left, as the
//! search bisects.
//!
//! Every pass is the search's exact pass over the stored step windows (`fit::run`), so every
//! command given is valid whatever the formula says; the formula only orders the adds tried.
//! The range of adds left is cut after each pass as the search cuts it (the run's binding steps
//! paired with its failing step, the deviation bound of two valid commands, the failing step's
//! side), and by [`two_window_adds`] for one step more than the best: the command given is the
//! longest once that range is empty (every add left out could not have gone further, by the
//! same arguments as the search's, `compress::fit`). When it is not empty after
//! [`MAX_PASSES`] passes, `None`: the search decides, as it does off the curves.
//!
//! Hot path: no allocation (the adds tried go in a fixed array) and no panic (every step read
//! is within the slice's checked length: at least 3 steps, the pairs and runs inside it).
//!
//! Measured (benchy, `cadence bench plan --threads 2 --instructions`, 2026-12-03): the very
//! same commands and wire bytes as the search on the cartesian and corexy printers, plain and
//! mzv 50/40 Hz, but more instructions (cartesian 3.31 G against 2.97 G, mzv 4.46 G against
//! 3.98 G; corexy 3.45 G against 3.10 G, mzv 5.66 G against 5.15 G). With the formula's add as
//! the search's first guess alone, 2.97 G: the search finds the best add quickly either way,
//! its cost is ruling out the adds left. The benchy's commands starting on curves are short (6.5
//! steps on average), where many adds cover the same steps. Hence off: a per-command bound
//! from the formula, without passes, is what could make these commands cheaper; the curve
//! spans it needs are kept here.

use super::fit::{add_deviation, binding_adds, first_two_adds, run, two_window_adds, Bend, Fit, StepWindow};
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
    /// The add of a command of `n` steps from pending index `at`: the curvature at its middle,
    /// rounded (`None` where the formula gives no finite number).
    #[inline]
    fn add_at(&self, at: usize, n: usize) -> Option<i64> {
        let j = at.saturating_sub(self.start) as f64 + 0.5 * n.saturating_sub(1) as f64;
        let a = self.curve.curvature(j).round();
        a.is_finite()
            .then_some(a.clamp(i16::MIN as f64, i16::MAX as f64) as i64)
    }
}

/// Most passes over the steps before the search is left to decide.
const MAX_PASSES: usize = 10;
/// Every add a command can carry (an i16).
const ALL_ADDS: (i64, i64) = (i16::MIN as i64, i16::MAX as i64);

/// The longest command from `last` over `steps` (the pending steps from index `at`, one
/// direction), where `at` lies in `span`; `guess_count` is how long a command is expected
/// (the previous one's count). `None` when the passes did not prove it longest (module doc).
pub(crate) fn curve_longest(
    span: &CurveSpan,
    steps: &[StepWindow],
    at: usize,
    last: u64,
    max_err: i64,
    guess_count: usize,
) -> Option<Fit> {
    if steps.len() < 3 || at < span.start || at >= span.end {
        return None;
    }
    let (lo, hi) = first_two_adds(steps, last);
    let mut amin = lo.max(ALL_ADDS.0);
    let mut amax = hi.min(ALL_ADDS.1);
    let mut add = span.add_at(at, guess_count.clamp(2, steps.len()))?;
    let mut best = Fit::NONE;
    // The adds tried (an add above the best's fell short of its count).
    let mut tried = [0i64; MAX_PASSES];
    let mut n_tried = 0;
    let mut cut_for = 0;
    for pass in 0..MAX_PASSES {
        if amin > amax {
            break;
        }
        add = add.clamp(amin, amax);
        let r = run(steps, last, add);
        if let Some(t) = tried.get_mut(n_tried) {
            *t = add;
            n_tried += 1;
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
            return Some(finish(best, &tried[..n_tried]));
        }
        if r.count >= 2 {
            let dev = add_deviation(r.count, max_err);
            amin = amin.max(add - dev);
            amax = amax.min(add + dev);
        }
        // An add doing better than this run lands its failing step with its binding steps.
        let ((lo, hi), none) = binding_adds(steps, last, &r);
        (amin, amax) = if none {
            (1, 0)
        } else {
            (amin.max(lo), amax.min(hi))
        };
        if r.bend == Bend::Up {
            amin = amin.max(add + 1);
        } else {
            amax = amax.min(add - 1);
        }
        // Doing better than the best needs its count + 1 steps.
        if cut_for != best.count {
            cut_for = best.count;
            match two_window_adds(steps, last, best.count + 1) {
                Some((lo, hi)) => {
                    amin = amin.max(lo);
                    amax = amax.min(hi);
                }
                None => (amin, amax) = (1, 0),
            }
        }
        // Next: the curvature at the middle of the best run (once), then the middle of the
        // adds left, as the search bisects.
        add = match span.add_at(at, best.count).filter(|_| pass == 0) {
            Some(a) if a != add => a,
            _ => amin + (amax - amin) / 2,
        };
    }
    (amin > amax && best.count >= 1).then(|| finish(best, &tried[..n_tried]))
}

/// The best fit with its cap: an add tried above its add fell short of its count, so no add
/// from there up covers it (adds covering a count form a range, as the search assumes).
#[inline]
fn finish(mut best: Fit, tried: &[i64]) -> Fit {
    for &a in tried {
        if a > best.add {
            best.add_cap = best.add_cap.min(a - 1);
        }
    }
    best
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
    fn an_acceleration_gives_the_searchs_longest_command() {
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
        let f = curve_longest(&span, &w[1..], 1, w[0].hi, 1250, 20).unwrap();
        assert!(valid(&w[1..], w[0].hi, &f), "{f:?}");
        assert_eq!(f.count, longest_fit(&w[1..], w[0].hi, 1250, 0).count);
        assert!(f.count >= 8 && f.add < 0, "{f:?}");
    }

    proptest::proptest! {
        /// On an accelerating or decelerating stretch, a command given is valid and no shorter
        /// than the search's longest.
        #[test]
        fn curve_commands_are_valid_and_longest(
            v in 5.0f64..300.0,
            accel in 200.0f64..20_000.0,
            decel in proptest::bool::ANY,
            n in 3usize..400,
            skip in 0usize..50,
            back in 0.0f64..1.0,
            err in 10i64..2000,
            guess in 0usize..80,
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
            let last = (w[0].hi as f64 - back * err as f64) as u64;
            let last = last.min(w[0].hi);
            let Some(f) = curve_longest(&span, w, skip, last, err, guess) else {
                return Ok(());
            };
            proptest::prop_assert!(valid(w, last, &f), "{:?}", f);
            if f.count >= 2 && f.prefix_interval != NO_PREFIX {
                let shorter = Fit { interval: f.prefix_interval, count: f.count - 1, ..f };
                proptest::prop_assert!(valid(w, last, &shorter), "{:?}", f);
            }
            let s = longest_fit(w, last, err, 0);
            proptest::prop_assert!(f.count >= s.count, "curve {:?}, search {:?}", f, s);
        }
    }
}
