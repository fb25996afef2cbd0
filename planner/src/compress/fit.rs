//! Fitting one `queue_step` command to a run of step windows.
//!
//! Step k (1-based) of a command (interval I, add A) from the MCU's `last_clock` L lands at
//! p_k = L + k·I + A·T_k with T_k = k(k−1)/2; its window is [lo_k, hi_k]. For a fixed integer A
//! every window bounds I: ⌈(lo_k − L − A·T_k)/k⌉ ≤ I ≤ ⌊(hi_k − L − A·T_k)/k⌋, and each
//! interval I + (k−1)·A must stay in [0, 2^29]. Intersecting these step by step gives the
//! longest run for that A in one pass ([`run_with_add`]). When the intersection empties at step
//! m, step m's window lies above the reachable range (a larger A moves late steps later) or below
//! it (a smaller A).
//!
//! [`best_fit`] searches A: it starts at a guess (the previous command's A), then bisects with
//! that direction, also bounded by how far apart the A of two valid sequences can be: two
//! sequences valid on r steps differ by d_k = k·ΔI + T_k·ΔA with |d_k| ≤ max_error, and
//! d_2h − 2·d_h = ΔA·h², so |ΔA| ≤ 3·max_error / h² with h = ⌊r/2⌋. Among the commands with
//! the most steps it then takes the one whose last step is latest: for a fixed count c the last
//! step c·I_max(A) + T_c·A never decreases with A (I_max(A) falls by at most (k−1)/2 ≤ (c−1)/2
//! per unit of A), so that is the largest A still reaching c steps, found by binary search. A
//! late end leaves the next command the most room (measured: 0.5 % fewer commands).
//!
//! Both searches cut their range of A after a failed pass: the steps whose windows last moved
//! the bounds of I (the run's `binding` steps) and the step the pass failed at must all be landed
//! by a better A, and two steps a < b bound A exactly in the real-valued relaxation
//! ([`pair_adds`]). The latest-end search first probes the top of its range (the deviation
//! bound, the [`two_window_adds`] bound, and [`Fit::add_cap`]: the smallest A above the answer
//! that the longest-fit search tried fell short, and the A reaching c steps form a range), and
//! after a failed probe whose pair cut lowered the top below it, probes that new top next
//! (benchy: 1.22 M latest-end passes with plain bisection after the first probe, 0.67 M so,
//! 0.60 M with the cap).

/// A generated step waiting for compression: its clock window and direction.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct StepWindow {
    pub lo: u64,
    pub hi: u64,
    pub dir: bool,
}

/// One command's parameters (interval is the largest feasible for that count and add).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Fit {
    pub interval: i64,
    pub count: usize,
    pub add: i64,
    /// The largest interval with the same add for the first `count − 1` steps (the run that
    /// found this fit passed through it): the command one step shorter without another pass.
    /// [`NO_PREFIX`] when not known.
    pub prefix_interval: i64,
    /// No add above this one covers `count` steps: the search for the longest command tried
    /// a larger add that fell short (`i16::MAX` when not known).
    pub add_cap: i64,
}

/// [`Fit::prefix_interval`] when the fit did not come from a run.
pub(crate) const NO_PREFIX: i64 = i64::MIN;

/// The adds with which a command from `last` lands the first two of `steps` (at least two):
/// I ∈ [l1, u1] and 2I + A ∈ [l2, u2] (relative to `last`, I ≥ 0).
#[inline]
pub(crate) fn first_two_adds(steps: &[StepWindow], last: u64) -> (i64, i64) {
    let l = |i: usize| steps[i].lo as i64 - last as i64;
    let u = |i: usize| steps[i].hi as i64 - last as i64;
    let (l1, u1) = (l(0).max(0), u(0).min(MAX_IV));
    (l(1) - 2 * u1, u(1) - 2 * l1)
}

impl Fit {
    /// No command yet (a search's starting point).
    pub const NONE: Fit = Fit {
        interval: 0,
        count: 0,
        add: 0,
        prefix_interval: NO_PREFIX,
        add_cap: i16::MAX as i64,
    };

    /// Clock of the command's last step when it starts from `last`.
    #[inline]
    pub fn end(&self, last: u64) -> u64 {
        let c = self.count as i64;
        (last as i64 + c * self.interval + c * (c - 1) / 2 * self.add) as u64
    }

    /// The same command one step shorter, when known without another pass.
    #[inline]
    pub fn shortened(&self) -> Option<Fit> {
        (self.count >= 2 && self.prefix_interval != NO_PREFIX).then_some(Fit {
            interval: self.prefix_interval,
            count: self.count - 1,
            add: self.add,
            prefix_interval: NO_PREFIX,
            add_cap: i16::MAX as i64,
        })
    }
}

/// Which way `add` should move to extend a run that failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Bend {
    /// The run covered every step given.
    None,
    Up,
    Down,
}

const MAX_IV: i64 = super::MAX_INTERVAL as i64;
/// Most values of `add` tried per command while looking for the longest run (the default of
/// the `passes` cap [`longest_fit`] takes).
pub(crate) const MAX_TRIALS: usize = 24;

/// One pass of [`run`]: how far `add` got.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Run {
    pub count: usize,
    /// The largest interval landing the `count` steps.
    pub interval: i64,
    /// The largest interval landing the first `count − 1` steps (count ≥ 1).
    pub prefix_interval: i64,
    pub bend: Bend,
    /// The steps (1-based, 0 = none) whose windows last raised the lower and lowered the upper
    /// bound of the interval before the run stopped: with the step it stopped at, the pairs
    /// most likely to rule out adds ([`pair_adds`]).
    pub binding: (usize, usize),
}

impl Run {
    /// The command of this run with `add`.
    #[inline]
    fn fit(&self, add: i64) -> Fit {
        Fit {
            interval: self.interval,
            count: self.count,
            add,
            prefix_interval: self.prefix_interval,
            add_cap: i16::MAX as i64,
        }
    }
}

/// The longest run of `steps` from `last` with this `add`: (count, largest interval for that
/// count, which way add should move to go further).
#[cfg(test)]
pub(crate) fn run_with_add(steps: &[StepWindow], last: u64, add: i64) -> (usize, i64, Bend) {
    let r = run(steps, last, add);
    (r.count, r.interval, r.bend)
}

/// [`run_with_add`], also giving the largest interval one step earlier.
#[inline]
pub(crate) fn run(steps: &[StepWindow], last: u64, add: i64) -> Run {
    if add >= 0 {
        run_signed::<true>(steps, last, add)
    } else {
        run_signed::<false>(steps, last, add)
    }
}

/// [`run`] for an add of known sign (`POS`: add ≥ 0). Each step's interval I + (k−1)·A must
/// stay in [0, MAX_INTERVAL]: with A ≥ 0 only the upper end can bind (the lower bound of I
/// never falls below 0), with A < 0 only the lower one (the upper bound never exceeds
/// MAX_INTERVAL), so each pass checks one.
#[inline(always)]
fn run_signed<const POS: bool>(steps: &[StepWindow], last: u64, add: i64) -> Run {
    let mut lo_i: i64 = 0;
    let mut hi_i: i64 = MAX_IV;
    let mut prev_hi: i64 = MAX_IV;
    let (mut j_lo, mut j_hi) = (0usize, 0usize);
    let mut base = last as i64; // last + add · T_k
    let mut ka: i64 = 0; // add · (k − 1): this step's interval is I + ka
    let mut k: i64 = 0;
    for st in steps {
        k += 1;
        base += ka;
        let l = st.lo as i64 - base;
        let u = st.hi as i64 - base;
        let mut nlo = lo_i;
        let mut nhi = hi_i;
        // The bounds move a little at a time: one step is usually enough, a division otherwise.
        // lo_i ≥ 0, so a violated lower bound has l > 0 (⌈l/k⌉ by truncation); a violated upper
        // bound with u < 0 fails whatever its value (every I ≥ 0): −1 stands for ⌊u/k⌋ there.
        if k * nlo < l {
            j_lo = k as usize;
            nlo = if k * (nlo + 1) >= l {
                nlo + 1
            } else {
                (l + k - 1) / k
            };
        }
        if k * nhi > u {
            j_hi = k as usize;
            nhi = if k * (nhi - 1) <= u {
                nhi - 1
            } else if u < 0 {
                -1
            } else {
                u / k
            };
        }
        // This step's interval must stay in [0, MAX_INTERVAL].
        if POS {
            nhi = nhi.min(MAX_IV - ka);
        } else {
            nlo = nlo.max(-ka);
        }
        if nlo > nhi {
            let bend = if nlo > hi_i {
                Bend::Up
            } else if nhi < lo_i || nlo + nhi < lo_i + hi_i {
                Bend::Down
            } else {
                Bend::Up
            };
            return Run {
                count: k as usize - 1,
                interval: hi_i,
                prefix_interval: prev_hi,
                bend,
                binding: (j_lo, j_hi),
            };
        }
        lo_i = nlo;
        prev_hi = hi_i;
        hi_i = nhi;
        ka += add;
    }
    Run {
        count: steps.len(),
        interval: hi_i,
        prefix_interval: prev_hi,
        bend: Bend::None,
        binding: (j_lo, j_hi),
    }
}

/// Largest |ΔA| between two sequences both valid on `count` steps.
#[inline]
pub(crate) fn add_deviation(count: usize, max_err: i64) -> i64 {
    let h = (count / 2) as i64;
    if h == 0 {
        i64::MAX / 4
    } else {
        3 * max_err / (h * h)
    }
}

/// The adds with which some command, even with a real-valued interval, lands steps n/2 and n of
/// `steps` from `last` in their windows (`None`: no add does, so no command covers n steps).
/// For steps a < b: aI + A·T_a ∈ [la, ua] and bI + A·T_b ∈ [lb, ub] (relative to `last`) have a
/// common I exactly when A·D ∈ [b·ua − a·lb, b·la − a·ub] turned around, D = b·T_a − a·T_b =
/// ab(a − b)/2 < 0. Centred where the windows are (the deviation bound of two fits is centred on a
/// fit found), a few multiplications: it lets the search stop once one more step is out of reach.
/// n < 2 or beyond the steps given: the whole i16 range.
pub(crate) fn two_window_adds(steps: &[StepWindow], last: u64, n: usize) -> Option<(i64, i64)> {
    if n < 2 || n > steps.len() {
        return Some(ALL_ADDS);
    }
    let rel = |v: u64| v as i64 - last as i64;
    let sb = steps[n - 1];
    let (b, lb, ub) = (n as i64, rel(sb.lo), rel(sb.hi));
    #[inline(always)]
    fn with_b(sa: StepWindow, last: u64, a: usize, b: (i64, i64, i64)) -> (i64, i64) {
        let rel = |v: u64| v as i64 - last as i64;
        pair_bounds(a as i64, rel(sa.lo), rel(sa.hi), b.0, b.1, b.2)
    }
    let (mut lo, mut hi) = with_b(steps[n / 2 - 1], last, n / 2, (b, lb, ub));
    // Two more pairs tighten it on longer runs.
    if n >= 8 {
        for a in [n / 4, n - n / 4] {
            let (l, h) = with_b(steps[a - 1], last, a, (b, lb, ub));
            lo = lo.max(l);
            hi = hi.min(h);
        }
    }
    let (lo, hi) = (lo.max(ALL_ADDS.0), hi.min(ALL_ADDS.1));
    (lo <= hi).then_some((lo, hi))
}

/// The adds with which a command lands the step after run `r` (count + 1) together with each
/// of the steps that bound its interval ([`pair_adds`] of each pair, intersected; the whole
/// i64 range when none applies), and whether some pair rules out every add.
#[inline]
pub(crate) fn binding_adds(steps: &[StepWindow], last: u64, r: &Run) -> ((i64, i64), bool) {
    let m = r.count + 1;
    let (mut lo, mut hi, mut none) = (i64::MIN, i64::MAX, false);
    for j in [r.binding.0, r.binding.1] {
        if j == 0 || j >= m {
            continue;
        }
        match pair_adds(steps, last, j, m) {
            Some((l, h)) => {
                lo = lo.max(l);
                hi = hi.min(h);
            }
            None => none = true,
        }
    }
    ((lo, hi), none)
}

/// Every add a command can carry (an i16).
const ALL_ADDS: (i64, i64) = (i16::MIN as i64, i16::MAX as i64);

/// [`two_window_adds`] for steps a < b (1-based). Checked i64 arithmetic: on an overflow
/// (clocks ~2^45 ticks apart) it rules nothing out.
fn pair_adds(steps: &[StepWindow], last: u64, a: usize, b: usize) -> Option<(i64, i64)> {
    let rel = |v: u64| v as i64 - last as i64;
    let (sa, sb) = (steps[a - 1], steps[b - 1]);
    let (lo, hi) = pair_bounds(a as i64, rel(sa.lo), rel(sa.hi), b as i64, rel(sb.lo), rel(sb.hi));
    let (lo, hi) = (lo.max(ALL_ADDS.0), hi.min(ALL_ADDS.1));
    (lo <= hi).then_some((lo, hi))
}

/// The adds of [`pair_adds`] for steps a < b with windows [la, ua] and [lb, ub] relative to
/// `last`, not clamped to the i16 range; (i64::MIN, i64::MAX) on an overflow.
#[inline(always)]
fn pair_bounds(a: i64, la: i64, ua: i64, b: i64, lb: i64, ub: i64) -> (i64, i64) {
    // 2·D = ab(a − b) < 0. A·D ∈ [b·ua − a·lb, b·la − a·ub] turned around: A ≥ 2(b·ua −
    // a·lb)/(2D) and A ≤ 2(b·la − a·ub)/(2D); negated to divide by −2D > 0.
    // ≥ 1 as a < b (the bound lets the divisions below skip their zero and overflow checks).
    let neg_d2 = (a * b * (b - a)).max(1);
    // Clocks less than 2^40 ticks apart (hours): no product can overflow, and truncating
    // division with a remainder fix-up is floor and ceiling (neg_d2 > 0).
    const SMALL: i64 = 1 << 40;
    if la.min(lb) >= -SMALL && ua.max(ub) <= SMALL {
        let nl = -2 * (b * ua - a * lb);
        let nh = -2 * (b * la - a * ub);
        let lo = nl / neg_d2 + i64::from(nl % neg_d2 > 0);
        let hi = nh / neg_d2 - i64::from(nh % neg_d2 < 0);
        return (lo, hi);
    }
    let num = |x: i64, y: i64| b.checked_mul(x)?.checked_sub(a.checked_mul(y)?)?.checked_mul(-2);
    let (Some(nl), Some(nh)) = (num(ua, lb), num(la, ub)) else {
        return (i64::MIN, i64::MAX);
    };
    let lo = nl.div_euclid(neg_d2) + i64::from(nl.rem_euclid(neg_d2) != 0);
    let hi = nh.div_euclid(neg_d2);
    (lo, hi)
}

/// The add that a command from `last` through steps h and 2h of `steps` (window midpoints)
/// would carry: p_2h − 2·p_h + p_0 = A·h² (`None` when there are fewer than 2h steps or h < 2).
/// A first guess for [`longest_fit`] when a command of about h steps is expected. Benchy: the
/// lookahead's search for the next command makes 8 % fewer passes (1.20 M → 1.10 M) than
/// starting from the previous command's add, the whole plan 3.200 G → 3.165 G instructions,
/// the same commands.
pub(crate) fn curvature_add(steps: &[StepWindow], last: u64, h: usize) -> Option<i64> {
    let h = h.min(steps.len() / 2);
    if h < 2 {
        return None;
    }
    let mid = |i: usize| (steps[i].lo + (steps[i].hi - steps[i].lo) / 2) as i64 - last as i64;
    let h2 = (h * h) as i64;
    Some((mid(2 * h - 1) - 2 * mid(h - 1)) / h2)
}

/// A command covering the most of `steps` (one direction, non-empty) from `last`, trying at
/// most `passes` adds (at most [`MAX_TRIALS`]; with fewer the command may be shorter).
pub(crate) fn longest_fit(
    steps: &[StepWindow],
    last: u64,
    max_err: i64,
    guess_add: i64,
    passes: usize,
) -> Fit {
    longest_fit_within(
        steps,
        last,
        max_err,
        guess_add,
        (i16::MIN as i64, i16::MAX as i64),
        passes,
    )
}

/// [`longest_fit`] trying only the adds in `within` (the lookahead passes the adds that can
/// reach the count it needs: a shorter result is of no use to it).
pub(crate) fn longest_fit_within(
    steps: &[StepWindow],
    last: u64,
    max_err: i64,
    guess_add: i64,
    within: (i64, i64),
    passes: usize,
) -> Fit {
    let single = || run(&steps[..1], last, 0).fit(0);
    if steps.len() < 2 {
        return single();
    }
    let (lo, hi) = first_two_adds(steps, last);
    let mut amin = lo.max(within.0);
    let mut amax = hi.min(within.1);
    if amin > amax {
        return single();
    }
    let mut add = guess_add.clamp(amin, amax);
    let mut best = Fit::NONE;
    // The adds tried (the first few).
    let mut tried = [0i64; 16];
    let mut n_tried = 0;
    for _ in 0..passes.clamp(1, MAX_TRIALS) {
        let r = run(steps, last, add);
        if let Some(t) = tried.get_mut(n_tried) {
            *t = add;
            n_tried += 1;
        }
        let (count, bend) = (r.count, r.bend);
        if count > best.count || (count == best.count && add > best.add) {
            best = r.fit(add);
        }
        if bend == Bend::None {
            break;
        }
        if count >= 2 {
            let dev = add_deviation(count, max_err);
            amin = amin.max(add - dev);
            amax = amax.min(add + dev);
        }
        // An add doing better lands step count + 1 together with the steps that bound this
        // run's interval.
        let ((lo, hi), none) = binding_adds(steps, last, &r);
        amin = amin.max(lo);
        amax = amax.min(hi);
        if none && count >= best.count {
            break;
        }
        if bend == Bend::Up {
            amin = amin.max(add + 1);
        } else {
            amax = amax.min(add - 1);
        }
        if amin > amax {
            break;
        }
        add = amin + (amax - amin) / 2;
    }
    if best.count < 2 {
        return single();
    }
    // A larger add tried fell short (else it would be the best), and the adds covering a
    // count form a range (as the latest-end search assumes).
    for &a in &tried[..n_tried] {
        if a > best.add {
            best.add_cap = best.add_cap.min(a - 1);
        }
    }
    best
}

/// The command covering the most of `steps` (one direction, non-empty) from `last`, ending as
/// late as possible.
#[cfg(test)]
pub(crate) fn best_fit(steps: &[StepWindow], last: u64, max_err: i64, guess_add: i64) -> Fit {
    latest_end(
        steps,
        last,
        max_err,
        longest_fit(steps, last, max_err, guess_add, MAX_TRIALS),
    )
}

/// Among the commands with `fit.count` steps, the one whose last step is latest (with the
/// fewest wire bytes among those, see [`smaller_encoding`]).
pub(crate) fn latest_end(steps: &[StepWindow], last: u64, max_err: i64, fit: Fit) -> Fit {
    smaller_encoding(steps, last, latest_end_plain(steps, last, max_err, fit))
}

/// [`latest_end`] without the byte saving: the largest add.
fn latest_end_plain(steps: &[StepWindow], last: u64, max_err: i64, fit: Fit) -> Fit {
    let mut best = fit;
    let c = best.count;
    if c < 2 {
        return best;
    }
    let (mut lo, mut hi) = (
        best.add,
        (best.add + add_deviation(c, max_err)).min(i16::MAX as i64),
    );
    hi = hi.min(best.add_cap);
    if hi > lo {
        if let Some((_, top)) = two_window_adds(steps, last, c) {
            hi = hi.min(top);
        }
    }
    hi = hi.max(lo);
    // The top of the range first: often it is the answer.
    let mut top_next = true;
    while lo < hi {
        let mid = if top_next { hi } else { lo + (hi - lo + 1) / 2 };
        let r = run(&steps[..c], last, mid);
        if r.count == c {
            lo = mid;
            best = r.fit(mid);
            top_next = false;
        } else {
            hi = mid - 1;
            // An add landing all c steps lands the failing step with those that bound the run:
            // when that cuts the range below the probe, the new top is the next probe.
            let m = r.count + 1;
            let mut cut = hi;
            for j in [r.binding.0, r.binding.1] {
                if j == 0 || j >= m {
                    continue;
                }
                if let Some((_, top)) = pair_adds(steps, last, j, m) {
                    cut = cut.min(top);
                }
            }
            top_next = cut < hi;
            hi = cut.max(lo);
        }
    }
    best
}

/// Bytes of `v` as a VLQ on the wire.
#[inline]
pub(crate) fn vlq_len(v: i64) -> usize {
    match v {
        -32..=95 => 1,
        -4096..=12287 => 2,
        -524_288..=1_572_863 => 3,
        -67_108_864..=201_326_591 => 4,
        _ => 5,
    }
}

/// Among the commands with `fit.count` steps ending as late as `fit` (which ends latest), one
/// whose `add` and `interval` take fewer bytes on the wire: `add` clamped into the one-byte VLQ
/// range, else into the two-byte one. Short commands have many adds with the same end (for two
/// steps the end only depends on 2I + A) and the latest-end search returns the largest;
/// benchy: 31 kB (0.8 %) fewer wire bytes for the same commands. (Letting the end come a few
/// ticks earlier saved at most 10 kB more and cost commands.)
fn smaller_encoding(steps: &[StepWindow], last: u64, fit: Fit) -> Fit {
    let c = fit.count;
    let bytes = |f: &Fit| vlq_len(f.add) + vlq_len(f.interval);
    if c < 2 || vlq_len(fit.add) == 1 {
        return fit;
    }
    let end = fit.end(last);
    let c_i = c as i64;
    let t_c = c_i * (c_i - 1) / 2;
    let mut range: Option<(i64, i64)> = None;
    for (lo, hi) in [(-32, 95), (-4096, 12287)] {
        let a = fit.add.clamp(lo, hi);
        if a == fit.add {
            break;
        }
        // The end moves in steps of the count's granularity: the bound or its neighbour inside
        // the range (for two steps, the other parity).
        let inward = if a < fit.add { a - 1 } else { a + 1 };
        for a in [a, inward] {
            // Ending no earlier with this add needs an interval of at least ⌈rest / c⌉ (≥ 0):
            // no pass when even that takes no fewer bytes, or the add cannot land the steps.
            let rest = end as i64 - last as i64 - t_c * a;
            let need_iv = (rest.max(0) + c_i - 1) / c_i;
            if vlq_len(a) + vlq_len(need_iv) >= bytes(&fit) {
                continue;
            }
            let (alo, ahi) =
                *range.get_or_insert_with(|| two_window_adds(steps, last, c).unwrap_or((i64::MAX, i64::MIN)));
            if a < alo || a > ahi {
                continue;
            }
            if let Some(f) = fit_prefix(steps, last, c, a) {
                if f.end(last) >= end && bytes(&f) < bytes(&fit) {
                    return f;
                }
            }
        }
    }
    fit
}

/// The fit of exactly the first `count` steps with `add` (which must reach them), largest
/// interval.
pub(crate) fn fit_prefix(steps: &[StepWindow], last: u64, count: usize, add: i64) -> Option<Fit> {
    let r = run(steps.get(..count)?, last, add);
    (r.count == count && count > 0).then_some(r.fit(add))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn windows(clocks: &[u64], err: u64) -> Vec<StepWindow> {
        clocks
            .iter()
            .map(|&c| StepWindow {
                lo: c - err,
                hi: c,
                dir: true,
            })
            .collect()
    }

    #[test]
    fn exact_quadratic_is_found_in_full() {
        // p_k = 1000 + 300k + 7·k(k−1)/2
        let clocks: Vec<u64> = (1..=200u64)
            .map(|k| 1000 + 300 * k + 7 * k * (k - 1) / 2)
            .collect();
        let f = best_fit(&windows(&clocks, 0), 1000, 0, 0);
        assert_eq!((f.interval, f.count, f.add), (300, 200, 7));
        assert_eq!(f.end(1000), *clocks.last().unwrap());
    }

    #[test]
    fn curvature_add_of_an_exact_quadratic() {
        // p_k = 1000 + 300k + 7·k(k−1)/2: the add is 7 whatever the span.
        let clocks: Vec<u64> = (1..=40u64)
            .map(|k| 1000 + 300 * k + 7 * k * (k - 1) / 2)
            .collect();
        let w = windows(&clocks, 0);
        for h in [2, 5, 20] {
            assert_eq!(curvature_add(&w, 1000, h), Some(7), "h = {h}");
        }
        // The span is cut to the steps given; too few steps give no guess.
        assert_eq!(curvature_add(&w, 1000, 100), Some(7));
        assert_eq!(curvature_add(&w[..3], 1000, 5), None);
    }

    #[test]
    fn run_reports_the_bend() {
        let clocks: Vec<u64> = (1..=50u64).map(|k| 100 * k + 5 * k * k).collect();
        let w = windows(&clocks, 2);
        let (n, _, bend) = run_with_add(&w, 0, 0);
        assert!(n < 50);
        assert_eq!(bend, Bend::Up);
        let (n, _, bend) = run_with_add(&w, 0, 40);
        assert!(n < 50);
        assert_eq!(bend, Bend::Down);
    }

    #[test]
    fn short_commands_take_a_small_add_with_the_same_end() {
        // Two steps: the end is 2I + A, which many adds reach; the largest one needs 3 bytes.
        let w = windows(&[20_000, 40_050], 1250);
        let plain = latest_end_plain(&w, 0, 1250, longest_fit(&w, 0, 1250, 0, MAX_TRIALS));
        let f = latest_end(&w, 0, 1250, longest_fit(&w, 0, 1250, 0, MAX_TRIALS));
        assert_eq!((f.count, f.end(0)), (2, plain.end(0)));
        assert!(vlq_len(plain.add) > 1, "{plain:?}");
        assert_eq!(vlq_len(f.add), 1, "{f:?}");
        assert_eq!(fit_prefix(&w, 0, 2, f.add), Some(f));
    }

    #[test]
    fn vlq_lengths_match_the_wire_encoding() {
        let mut buf = [0u8; 8];
        for v in [
            -67_108_865i64,
            -67_108_864,
            -524_289,
            -524_288,
            -4097,
            -4096,
            -33,
            -32,
            0,
            95,
            96,
        ] {
            let n = links_vlq_len(v as i32, &mut buf);
            assert_eq!(vlq_len(v), n, "{v}");
        }
        for v in [12287i64, 12288, 1_572_863, 1_572_864, 201_326_591, 201_326_592] {
            assert_eq!(vlq_len(v), links_vlq_len(v as i32, &mut buf), "{v}");
        }
    }

    /// The protocol's VLQ length rule written out (docs/protocol.md "Integer encoding").
    fn links_vlq_len(v: i32, _buf: &mut [u8; 8]) -> usize {
        let v = v as i64;
        if (-(1 << 5)..3 << 5).contains(&v) {
            1
        } else if (-(1 << 12)..3 << 12).contains(&v) {
            2
        } else if (-(1 << 19)..3 << 19).contains(&v) {
            3
        } else if (-(1 << 26)..3 << 26).contains(&v) {
            4
        } else {
            5
        }
    }

    proptest::proptest! {
        /// The byte saving never changes the command's length or end, never adds bytes, and its
        /// command is valid.
        #[test]
        fn smaller_encoding_keeps_count_and_end(
            gaps in proptest::collection::vec(2_000u64..400_000, 2..30),
            err in 1u64..2_000,
        ) {
            let mut t = 1_000_000u64;
            let clocks: Vec<u64> = gaps.iter().map(|g| { t += g; t }).collect();
            let w = windows(&clocks, err);
            let last = 1_000_000 - 5_000;
            let fit = longest_fit(&w, last, err as i64, 0, MAX_TRIALS);
            let plain = latest_end_plain(&w, last, err as i64, fit);
            let f = latest_end(&w, last, err as i64, fit);
            proptest::prop_assert_eq!(f.count, plain.count);
            proptest::prop_assert_eq!(f.end(last), plain.end(last));
            proptest::prop_assert!(vlq_len(f.add) + vlq_len(f.interval) <= vlq_len(plain.add) + vlq_len(plain.interval));
            proptest::prop_assert_eq!(fit_prefix(&w, last, f.count, f.add).map(|g| g.count), Some(f.count));
        }
    }

    /// Reference for [`run_with_add`]: the longest prefix some integer interval satisfies,
    /// by trying every interval in the (small) range the test uses.
    fn brute_run(steps: &[StepWindow], last: u64, add: i64, max_iv: i64) -> (usize, i64) {
        let ok = |n: usize, iv: i64| {
            (1..=n as i64).all(|k| {
                let p = last as i64 + k * iv + add * k * (k - 1) / 2;
                let step_iv = iv + (k - 1) * add;
                (0..=MAX_IV).contains(&step_iv)
                    && (steps[k as usize - 1].lo as i64..=steps[k as usize - 1].hi as i64).contains(&p)
            })
        };
        let mut best = (0, MAX_IV);
        for n in 1..=steps.len() {
            match (0..=max_iv).rev().find(|&iv| ok(n, iv)) {
                Some(iv) => best = (n, iv),
                None => break,
            }
        }
        best
    }

    proptest::proptest! {
        /// The incremental bounds (one step or a division) agree with trying every interval.
        #[test]
        fn run_with_add_matches_brute_force(
            gaps in proptest::collection::vec(0u64..300, 1..12),
            err in 0u64..40,
            add in -20i64..20,
            last in 0u64..50,
        ) {
            let mut t = 100u64;
            let clocks: Vec<u64> = gaps.iter().map(|g| { t += g; t }).collect();
            let w = windows(&clocks, err.min(100));
            let (n, iv, _) = run_with_add(&w, last, add);
            let (bn, biv) = brute_run(&w, last, add, 5_000);
            proptest::prop_assert_eq!(n, bn);
            if n > 0 {
                proptest::prop_assert_eq!(iv, biv);
            }
        }
    }

    proptest::proptest! {
        /// The pair bound's fast path agrees with exact rational arithmetic.
        #[test]
        fn pair_adds_is_exact(
            a in 1usize..200,
            gap in 1usize..200,
            los in proptest::collection::vec(-5_000_000i64..5_000_000, 2),
            widths in proptest::collection::vec(0i64..3_000, 2),
            last in 0u64..1_000_000,
        ) {
            let b = a + gap;
            let mut w = vec![StepWindow { lo: 0, hi: 0, dir: true }; b];
            for (i, k) in [a, b].into_iter().enumerate() {
                let lo = (last as i64 + 10_000_000 + los[i]) as u64;
                w[k - 1] = StepWindow { lo, hi: lo + widths[i] as u64, dir: true };
            }
            let rel = |v: u64| (v as i64 - last as i64) as i128;
            let (la, ua) = (rel(w[a - 1].lo), rel(w[a - 1].hi));
            let (lb, ub) = (rel(w[b - 1].lo), rel(w[b - 1].hi));
            let (ai, bi) = (a as i128, b as i128);
            let d = ai * bi * (bi - ai);
            let nl = -2 * (bi * ua - ai * lb);
            let nh = -2 * (bi * la - ai * ub);
            let lo = nl.div_euclid(d) + i128::from(nl.rem_euclid(d) != 0);
            let hi = nh.div_euclid(d);
            let (lo, hi) = (lo.max(i16::MIN as i128), hi.min(i16::MAX as i128));
            let want = (lo <= hi).then_some((lo as i64, hi as i64));
            proptest::prop_assert_eq!(pair_adds(&w, last, a, b), want);
        }
    }

    proptest::proptest! {
        /// The two-window bound never rules out an add that covers n steps.
        #[test]
        fn two_window_adds_keep_every_valid_add(
            gaps in proptest::collection::vec(0u64..3_000, 2..40),
            err in 0u64..400,
            last in 0u64..500,
        ) {
            let mut t = 1_000u64;
            let clocks: Vec<u64> = gaps.iter().map(|g| { t += g; t }).collect();
            let w = windows(&clocks, err);
            for add in -60i64..60 {
                let (c, _, _) = run_with_add(&w, last, add);
                for n in 2..=c {
                    let r = two_window_adds(&w, last, n);
                    proptest::prop_assert!(
                        r.is_some_and(|(lo, hi)| (lo..=hi).contains(&add)),
                        "add {} covers {} steps but the bound is {:?}", add, n, r
                    );
                }
            }
        }
    }
}
