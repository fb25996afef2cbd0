//! One `queue_step` command per cruise line, found from the line's formula instead of a search
//! over its step windows.
//!
//! A cruise (plain or shaped, see [`crate::stepgen::StepSink::line`]) puts step i at the ideal
//! clock c(i) = t0 + i·dt. The compressor keeps each such stretch of pending steps as a
//! [`LineSpan`]; when the oldest pending step lies in one, [`line_fit`] gives the command with
//! add 0 covering the most of it in O(1), whatever its length.
//!
//! # The error bound
//! Let the command start after the MCU's `last_clock` L, its steps k = 1..n being the span's
//! steps from the oldest pending one, whose ideal clocks are c_k = c_1 + (k − 1)·dt. With add 0
//! and interval I, step k lands at p_k = L + k·I (an integer). Step k's window is
//! [⌈c_k − E⌉, ⌊c_k⌋] (E = max_error in ticks, an integer), and for an integer p,
//! ⌈c − E⌉ ≤ p ≤ ⌊c⌋ ⇔ c − E ≤ p ≤ c. So the command is valid exactly when
//! h(k) = c_k − p_k ∈ [0, E] for every k ≤ n, with
//!
//! h(k) = h_1 + (k − 1)·δ,  h_1 = c_1 − L − I,  δ = dt − I.
//!
//! h is linear in k, so its extremes over 1..n are at k = 1 and k = n: the command is valid when
//! both ends are, and no step in between needs to be looked at. h(1) ∈ [0, E] is a range of I of
//! width E; for δ > 0 the end n stays valid while h_1 + (n − 1)·δ ≤ E, for δ < 0 while
//! h_1 + (n − 1)·δ ≥ 0, for δ = 0 always. The longest command is taken by the I in h(1)'s range
//! nearest to dt from below or from above (a smaller |δ| of the same sign never ends sooner), so
//! the two candidates ⌊dt⌋ and ⌈dt⌉, each clamped into that range, cover every I worth trying.
//!
//! Floating point: c_k in the window is `t0 + i as f64 * dt` rounded once, and h is evaluated
//! here in a few more roundings. With clocks below 2^40 ticks every such rounding is below
//! 2^−12 ticks, so where the formula puts h within [ε, E − ε], ε = 2^−4, the step is inside
//! [c_k − E, c_k] for the clock its window was made from. Where the formula puts h within ε of
//! a bound (a command whose first step lands a fraction of a tick from its window's edge, which
//! the search would take), those steps, at most [`MAX_EXACT`] at the start, are checked one by
//! one against their stored integer windows instead, and the formula takes over from the first
//! step it puts inside the margin. Steps after the formula's last one are likewise checked one
//! by one (the few the margin left out, and those after the span), while they fit: so every
//! step of a command is either proven by the formula with room for rounding or checked exactly.
//!
//! # When an add could do better
//! A command with add A valid on steps 1, 1 + h, 1 + 2h of a line has
//! p_{1+2h} − 2·p_{1+h} + p_1 = A·h² while the line's c has second difference 0, and each
//! p − c lies in [−E, 0]: so |A|·h² ≤ 2E. Covering m ≥ 2·√(2E) + 3 steps of a line (h ≥ √(2E)
//! plus rounding) therefore forces A = 0, and the search over adds has nothing to find: the
//! longest command is one of add 0. Shorter commands are left to the per-step search
//! ([`min_line`]).
//!
//! # The line's last command
//! When a command reaches the span's end, the steps after it (a deceleration, an acceleration)
//! may still fit it. Every interval in [bottom, top] is valid on the whole rest of the span
//! (m steps), top = ⌊min(c_1 − L, (c_m − L)/m)⌋ (both ends' upper bounds) and
//! bottom = ⌈max(c_1 − L − E, (c_m − L − E)/m)⌉ (both lower bounds), with the margin ε; that
//! range is narrowed step by step through the windows after the span, as the search's pass does
//! with add 0, until it empties: the longest command of add 0 ending latest (its largest
//! interval), and the largest interval one step shorter, for the lookahead. The compressor then
//! makes the search's lookahead choice (end a step earlier when the next command covers more):
//! inside a line both next commands come from the formula, at a line's last command the search
//! finds the next one. On random programs through every kinematics, shaped and not, this gives
//! no more commands than the per-step search (`pipeline::tests::line_fit`).

use super::fit::{Fit, StepWindow};
use super::{Span, MAX_INTERVAL};

/// A stretch of pending steps on one line: the step at pending index `start + j` (j <
/// `end − start`) has the ideal clock `t0 + (i0 + j) as f64 * dt` (bit-identical to
/// [`crate::stepgen::line_clock`] above its floor) and one direction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct LineSpan {
    pub start: usize,
    pub end: usize,
    pub t0: f64,
    pub dt: f64,
    pub i0: i64,
}

impl LineSpan {
    /// The ideal clock of the step at pending index `p` (start ≤ p < end).
    #[inline]
    fn clock(&self, p: usize) -> f64 {
        self.t0 + (self.i0 + (p - self.start) as i64) as f64 * self.dt
    }
}

impl Span for LineSpan {
    #[inline]
    fn range(&self) -> (usize, usize) {
        (self.start, self.end)
    }

    #[inline]
    fn moved(self, cut: usize, by: usize) -> LineSpan {
        LineSpan {
            start: self.start + cut - by,
            end: self.end - by,
            i0: self.i0 + cut as i64,
            ..self
        }
    }
}

/// Fewest steps a span is kept for (shorter ones are left to the per-step search).
pub(crate) const MIN_SPAN: usize = 16;
/// Fewest line steps a command from the formula covers with max_error `e` ticks: below it a
/// command with an add might go further (module doc, "When an add could do better").
fn min_line(e: f64) -> usize {
    (2.0 * (2.0 * e).sqrt()) as usize + 3
}

/// Most steps checked one by one at a command's start where the formula is within ε of a bound
/// (a candidate interval stops there when it would need more).
const MAX_EXACT: usize = 32;

/// Clocks at or above this many ticks are left to the per-step search (see the module doc).
const MAX_CLOCK: f64 = (1u64 << 40) as f64;
/// The margin of the module doc's floating-point argument, in ticks.
const EPS: f64 = 1.0 / 16.0;

/// The longest add-0 command from `last` over the pending steps `head..` of `span` (`steps` is
/// the pending buffer; the command ends before `run_end`, where the direction turns or the
/// count is full), as proven in the module doc; `None` when the per-step search should choose
/// (clocks out of range, or fewer line steps than [`min_line`]).
pub(crate) fn line_fit(
    span: &LineSpan,
    steps: &[StepWindow],
    head: usize,
    run_end: usize,
    last: u64,
    max_err: i64,
) -> Option<LineFit> {
    let limit = span.end.min(run_end).min(steps.len());
    let avail = limit.checked_sub(head)?;
    let e = max_err as f64;
    let min_n = min_line(e);
    if avail < min_n || head < span.start {
        return None;
    }
    let c1 = span.clock(head);
    let dt = span.dt;
    let cn = span.clock(limit - 1);
    if !(c1 >= 0.0 && cn < MAX_CLOCK && dt > 0.0) {
        return None;
    }
    let rel = c1 - last as f64;
    // h(1) = rel − I ∈ [ε, E − ε] (the formula's range), and one more either side (the
    // first step's own window decides there).
    let i_lo = ((rel - e + EPS).ceil() as i64).max(0);
    let i_hi = ((rel - EPS).floor() as i64).min(MAX_INTERVAL as i64);
    if i_lo > i_hi {
        return None;
    }
    let (i_min, i_max) = ((i_lo - 1).max(0), (i_hi + 1).min(MAX_INTERVAL as i64));
    // The candidates: ⌊dt⌋ and ⌈dt⌉ clamped into h(1)'s range, and the largest and smallest
    // interval valid on the whole rest of the span (the line's last command).
    let m = avail as f64;
    let to_end = cn - last as f64;
    let top = ((rel - EPS).min((to_end - EPS) / m).floor() as i64).min(MAX_INTERVAL as i64);
    let bottom = ((rel - e + EPS).max((to_end - e + EPS) / m).ceil() as i64).max(0);
    let end = run_end.min(steps.len());
    // Step k (1-based) of the command with interval iv in its own window.
    let fits = |k: usize, iv: i64| {
        let p = last + k as u64 * iv as u64;
        let w = steps[head + k - 1];
        w.lo <= p && p <= w.hi
    };
    let mut best: Option<(usize, i64)> = None;
    for iv in [dt.floor() as i64, dt.ceil() as i64, top, bottom] {
        let iv = iv.clamp(i_min, i_max);
        let delta = dt - iv as f64;
        let h = |k: usize| rel - iv as f64 + (k - 1) as f64 * delta;
        let inside = |k: usize| (EPS..=e - EPS).contains(&h(k));
        // Steps the formula leaves within ε of a bound at the start: each in its own window.
        let mut n = 0;
        while n < avail.min(MAX_EXACT) && !inside(n + 1) {
            if !fits(n + 1, iv) {
                break;
            }
            n += 1;
        }
        if n < avail && inside(n + 1) {
            // From step j = n + 1 the formula: steps after j that stay in [ε, E − ε].
            let hj = h(n + 1);
            let more = if delta > 0.0 {
                (e - EPS - hj) / delta
            } else if delta < 0.0 {
                (hj - EPS) / -delta
            } else {
                f64::INFINITY
            };
            let left = (avail - n - 1) as f64;
            n = if more >= left {
                avail
            } else {
                n + 1 + more.max(0.0) as usize
            };
        }
        // Then each step's own window: the few the margin left out, and after the span's end.
        while head + n < end && fits(n + 1, iv) {
            n += 1;
        }
        if best.is_none_or(|(bn, biv)| n > bn || (n == bn && iv > biv)) {
            best = Some((n, iv));
        }
    }
    let (mut n, mut iv) = best?;
    // The largest interval for the first n − 1 steps (the lookahead's one step shorter command):
    // on the line the upper bounds of its ends, after it each step's own.
    let prefix_of = |n: usize, iv: i64| {
        let on_line = n.saturating_sub(1).clamp(1, avail);
        let c_end = span.clock(head + on_line - 1);
        let mut top = (rel - EPS)
            .min((c_end - last as f64 - EPS) / on_line as f64)
            .floor() as i64;
        for k in avail + 1..n {
            top = top.min((steps[head + k - 1].hi as i64 - last as i64) / k as i64);
        }
        top.clamp(iv, MAX_INTERVAL as i64)
    };
    let mut prefix = prefix_of(n, iv);
    // Every interval in [bottom, top] (and h(1)'s range) is valid on the whole rest of the span:
    // narrow that range step by step after it, as the search's pass does with add 0.
    let (mut lo_r, mut hi_r) = (bottom.max(i_lo), top.min(i_hi));
    if lo_r <= hi_r {
        let mut k = avail;
        let mut prev_hi = prefix_of(avail, lo_r).min(hi_r);
        while head + k < end {
            let w = steps[head + k];
            let kk = k as i64 + 1;
            let (l, u) = (w.lo as i64 - last as i64, w.hi as i64 - last as i64);
            let nlo = lo_r.max(-((-l).div_euclid(kk)));
            let nhi = hi_r.min(u.div_euclid(kk));
            if nlo > nhi {
                break;
            }
            prev_hi = hi_r;
            (lo_r, hi_r) = (nlo, nhi);
            k += 1;
        }
        if k > n || (k == n && hi_r > iv) {
            (n, iv, prefix) = (k, hi_r, prev_hi);
        }
    }
    if n < min_n {
        return None;
    }
    // The ends against their integer windows (belt and braces: the proof covers them).
    if !(fits(1, iv) && fits(n, iv)) {
        return None;
    }
    Some(LineFit {
        fit: Fit {
            interval: iv,
            count: n,
            add: 0,
            prefix_interval: prefix,
            add_cap: i16::MAX as i64,
        },
        last: n >= avail,
    })
}

/// What [`line_fit`] found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct LineFit {
    pub fit: Fit,
    /// The command reaches the span's end (the lookahead may end it earlier).
    pub last: bool,
}

#[cfg(test)]
mod tests {
    use super::super::fit::NO_PREFIX;
    use super::*;

    fn windows(span: &LineSpan, err: i64) -> Vec<StepWindow> {
        (0..span.end)
            .map(|p| {
                let c = if p < span.start { 0.0 } else { span.clock(p) };
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
    fn valid(w: &[StepWindow], head: usize, last: u64, f: &Fit) -> bool {
        (1..=f.count).all(|k| {
            let p = last + (k as u64) * f.interval as u64;
            let s = w[head + k - 1];
            s.lo <= p && p <= s.hi
        })
    }

    #[test]
    fn an_integer_rate_is_one_command() {
        let span = LineSpan {
            start: 0,
            end: 1000,
            t0: 1_000_000.5,
            dt: 5000.0,
            i0: 1,
        };
        let w = windows(&span, 1250);
        let f = line_fit(&span, &w, 0, 1000, 1_000_000, 1250).unwrap().fit;
        assert_eq!((f.count, f.interval, f.add), (1000, 5000, 0));
        assert!(valid(&w, 0, 1_000_000, &f));
    }

    #[test]
    fn a_fractional_rate_drifts_out_after_about_e_over_the_fraction() {
        // dt = 5000.3: with I = 5000 the error grows 0.3 ticks a step, with 5001 it shrinks
        // 0.7; from the middle of the window the better one lasts about 625/0.3 steps.
        let span = LineSpan {
            start: 0,
            end: 60_000,
            t0: 1_000_000.0 + 625.0,
            dt: 5000.3,
            i0: 1,
        };
        let w = windows(&span, 1250);
        let last = 1_000_000;
        let f = line_fit(&span, &w, 0, 60_000, last, 1250).unwrap().fit;
        assert!(valid(&w, 0, last, &f));
        assert!(f.count > 2000 && f.count < 2200, "{f:?}");
        // One more step is out of its window (the command is the longest with its interval).
        let next = last + (f.count as u64 + 1) * f.interval as u64;
        let s = w[f.count];
        assert!(next < s.lo || next > s.hi);
    }

    proptest::proptest! {
        /// Whatever the line and the start, a command given is valid on every step, and it is
        /// never shorter than the longest add-0 command found by trying every interval.
        #[test]
        fn line_commands_are_valid_and_longest(
            dt in 50.0f64..200_000.0,
            t0 in 0.0f64..1e9,
            i0 in 0i64..1000,
            len in 2usize..600,
            head in 0usize..50,
            back in 0.0f64..3000.0,
            err in 1i64..500,
        ) {
            let span = LineSpan { start: 0, end: head + len, t0, dt, i0 };
            let w = windows(&span, err);
            let c1 = span.clock(head);
            let last = (c1 - back).max(0.0) as u64;
            let Some(LineFit { fit: f, .. }) = line_fit(&span, &w, head, head + len, last, err) else {
                return Ok(());
            };
            if f.count >= 2 {
                let shorter = Fit { interval: f.prefix_interval, count: f.count - 1, ..f };
                proptest::prop_assert!(valid(&w, head, last, &shorter), "{:?}", f);
            }
            proptest::prop_assert!(valid(&w, head, last, &f), "{:?}", f);
            // Brute force over the intervals landing the first step.
            let first = w[head];
            let mut longest = 0;
            for iv in first.lo.saturating_sub(last)..=first.hi.saturating_sub(last) {
                let g = Fit { interval: iv as i64, count: 1, add: 0, prefix_interval: NO_PREFIX, add_cap: 0 };
                let n = (1..=len).take_while(|&k| valid(&w, head, last, &Fit { count: k, ..g })).count();
                longest = longest.max(n);
            }
            // The margin ε at both ends costs up to 2ε/|δ| steps.
            let frac = (dt - dt.floor()).min(dt.ceil() - dt);
            let slack = if frac > 0.0 { (2.0 * EPS / frac).ceil() as usize } else { 0 };
            proptest::prop_assert!(f.count + 1 + slack >= longest, "{} vs {}", f.count, longest);
        }
    }
}
