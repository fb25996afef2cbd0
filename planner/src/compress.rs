//! Step compression: packs one stepper's ideal step times into `queue_step` commands.
//!
//! Each step i has a window of MCU clocks [lo_i, hi_i] = [⌈ideal − max_error⌉, ⌊ideal⌋] it must
//! land in. From the MCU's `last_clock` L, a command (interval I, count n, add A) puts its k-th
//! step at p_k = L + k·I + A·k(k−1)/2. For a fixed integer A every window constrains I to an
//! interval, ⌈(lo_k − L − A·T_k)/k⌉ ≤ I ≤ ⌊(hi_k − L − A·T_k)/k⌋ with T_k = k(k−1)/2, so the
//! longest run for that A is found in one pass by intersecting them (plus 0 ≤ each interval ≤
//! 2^29). When the intersection empties at step m, step m's window lies above the reachable
//! range (a larger A bends the sequence up) or below it (a smaller A).
//!
//! The search over A starts at the previous command's A, then bisects using that direction and
//! a bound on how far apart the A of two valid sequences can be: two sequences valid for r steps
//! differ by d_k = k·ΔI + T_k·ΔA with |d_k| ≤ max_error, and d_2h − 2·d_h = ΔA·h², so
//! |ΔA| ≤ 3·max_error / h² with h = ⌊r/2⌋. The command with the most steps wins (ties: the
//! smaller |A|); its I is the largest feasible (steps as close to their ideal time as allowed).
//!
//! Commands never go back in time (every interval ≥ 0) and a `reset_step_clock` precedes the
//! first step and any step more than 2^29 ticks after the previous one.

use std::collections::VecDeque;

use crate::kinematics::StepperKin;
use crate::stepgen::StepGen;
use crate::toolhead::Move;
pub use crate::stepgen::{IdealStep, StepCmd};

/// Largest interval sent (and largest gap without a `reset_step_clock`), in ticks.
pub const MAX_INTERVAL: u64 = 1 << 29;
/// Most steps in one `queue_step` (`count` is a u16).
pub const MAX_COUNT: usize = 65535;
/// Most values of `add` tried per command.
const MAX_TRIALS: usize = 24;

/// A generated step waiting for compression.
#[derive(Debug, Clone, Copy)]
struct Pending {
    lo: u64,
    hi: u64,
    dir: bool,
}

/// The step generator and compressor of one stepper.
#[derive(Debug)]
pub struct StepCompressor {
    gen: StepGen,
    step_dist: f64,
    max_err: u64,
    pending: Vec<Pending>,
    head: usize,
    /// All of pending[head..dir_run_end] share pending[head].dir.
    dir_run_end: usize,
    last_clock: u64,
    started: bool,
    dir: Option<bool>,
    last_add: i64,
    position_steps: i64,
    step_count: u64,
    queue_steps: u64,
    record_ideal: bool,
    ideal: VecDeque<IdealStep>,
    /// Ideal clock of the last step queued (steps are kept in time order).
    last_ideal: f64,
}

impl StepCompressor {
    /// A compressor for a stepper at position 0 with `step_dist` mm per step, whose MCU clock runs
    /// `clock_freq` ticks per print second, allowing steps up to `max_error_ticks` early.
    pub fn new(step_dist: f64, clock_freq: f64, max_error_ticks: u32) -> StepCompressor {
        StepCompressor {
            gen: StepGen::new(step_dist, clock_freq, 0.0),
            step_dist,
            max_err: max_error_ticks as u64,
            pending: Vec::with_capacity(1 << 14),
            head: 0,
            dir_run_end: 0,
            last_clock: 0,
            started: false,
            dir: None,
            last_add: 0,
            position_steps: 0,
            step_count: 0,
            queue_steps: 0,
            record_ideal: false,
            ideal: VecDeque::new(),
            last_ideal: 0.0,
        }
    }

    /// Steps per mm inverse this compressor was built with.
    pub fn step_dist(&self) -> f64 {
        self.step_dist
    }

    /// Net signed steps emitted in commands so far.
    pub fn position_steps(&self) -> i64 {
        self.position_steps
    }

    /// Steps emitted in commands so far.
    pub fn step_count(&self) -> u64 {
        self.step_count
    }

    /// `queue_step` commands emitted so far.
    pub fn queue_step_count(&self) -> u64 {
        self.queue_steps
    }

    /// Steps generated but not compressed yet.
    pub fn pending_steps(&self) -> usize {
        self.pending.len() - self.head
    }

    /// The MCU's `last_clock` after the commands emitted so far.
    pub fn last_clock(&self) -> u64 {
        self.last_clock
    }

    /// Records every generated step's ideal time for [`Self::take_ideal`] (tests, checking).
    pub fn set_record_ideal(&mut self, on: bool) {
        self.record_ideal = on;
    }

    /// The ideal steps generated since the last call, in order.
    pub fn take_ideal(&mut self) -> Vec<IdealStep> {
        self.ideal.drain(..).collect()
    }

    /// Generates this stepper's steps for `mv` (moves must be pushed in order).
    pub fn push_move(&mut self, mv: &Move, kin: &StepperKin) {
        debug_assert_eq!(kin.step_dist, self.step_dist);
        let max_err = self.max_err as f64;
        let pending = &mut self.pending;
        let ideal = &mut self.ideal;
        let record = self.record_ideal;
        let mut last = self.last_ideal;
        self.gen.gen_move(mv, kin, |clock, dir| {
            last = clock.max(last);
            queue_step_time(pending, ideal, record, max_err, last, dir);
        });
        self.last_ideal = last;
    }

    /// Queues one step at `ideal_clock` ticks (raised to the previous step's time if earlier),
    /// for callers that compute step times themselves.
    pub fn push_step(&mut self, ideal_clock: f64, dir: bool) {
        if !ideal_clock.is_finite() {
            return;
        }
        self.last_ideal = ideal_clock.max(self.last_ideal);
        let max_err = self.max_err as f64;
        queue_step_time(&mut self.pending, &mut self.ideal, self.record_ideal, max_err, self.last_ideal, dir);
    }

    /// Compresses every pending step whose ideal time is before `upto_clock` (commands may also
    /// take in later pending steps).
    pub fn flush(&mut self, upto_clock: u64, out: &mut Vec<StepCmd>) {
        while self.head < self.pending.len() && self.pending[self.head].hi < upto_clock {
            self.emit_one(out);
        }
        self.compact();
    }

    /// Compresses every pending step.
    pub fn finish(&mut self, out: &mut Vec<StepCmd>) {
        while self.head < self.pending.len() {
            self.emit_one(out);
        }
        self.compact();
    }

    fn compact(&mut self) {
        if self.head == self.pending.len() {
            self.pending.clear();
            self.head = 0;
            self.dir_run_end = 0;
        } else if self.head > 4096 && self.head * 2 > self.pending.len() {
            self.pending.drain(..self.head);
            self.dir_run_end -= self.head;
            self.head = 0;
        }
    }

    /// Emits one `queue_step` (preceded by a reset and/or direction change when needed).
    fn emit_one(&mut self, out: &mut Vec<StepCmd>) {
        let first = self.pending[self.head];
        if !self.started || first.lo > self.last_clock + MAX_INTERVAL {
            let clock = first.lo.saturating_sub(1).max(self.last_clock);
            out.push(StepCmd::ResetClock { clock });
            self.last_clock = clock;
            self.started = true;
        }
        if self.dir != Some(first.dir) {
            out.push(StepCmd::SetDir { dir: first.dir });
            self.dir = Some(first.dir);
        }
        if self.dir_run_end <= self.head {
            self.dir_run_end = self.head + 1;
        }
        while self.dir_run_end < self.pending.len() && self.pending[self.dir_run_end].dir == first.dir {
            self.dir_run_end += 1;
        }
        let run_end = self.dir_run_end.min(self.head + MAX_COUNT);
        let run = &self.pending[self.head..run_end];
        let fit = best_fit(run, self.last_clock, self.max_err as i64, self.last_add);
        let count = fit.count as u64;
        let interval = fit.interval as u64;
        let first_clock = self.last_clock + interval;
        let t = count * (count - 1) / 2;
        let last_clock = (self.last_clock as i64 + (count * interval) as i64 + t as i64 * fit.add) as u64;
        out.push(StepCmd::QueueStep {
            interval: fit.interval as u32,
            count: fit.count as u16,
            add: fit.add as i16,
            first_clock,
            last_clock,
        });
        self.last_clock = last_clock;
        self.last_add = fit.add;
        self.head += fit.count;
        self.step_count += count;
        self.queue_steps += 1;
        self.position_steps += if first.dir { count as i64 } else { -(count as i64) };
    }
}

/// Appends a step with ideal time `clock` (≥ 0, ≥ the previous one) and its window.
#[inline]
fn queue_step_time(
    pending: &mut Vec<Pending>,
    ideal: &mut VecDeque<IdealStep>,
    record: bool,
    max_err: f64,
    clock: f64,
    dir: bool,
) {
    let hi = clock.floor() as u64;
    let lo = (clock - max_err).ceil().max(0.0) as u64;
    pending.push(Pending { lo, hi, dir });
    if record {
        ideal.push_back(IdealStep { clock, dir });
    }
}

/// One command's parameters.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Fit {
    interval: i64,
    count: usize,
    add: i64,
}

/// Which way `add` should move to extend a run that failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Bend {
    /// The run reached the end of the steps.
    None,
    Up,
    Down,
}

/// The longest run of `steps` reachable from `last` with this `add`: (count, largest interval,
/// which way add should move to go further).
#[inline]
fn run_with_add(steps: &[Pending], last: u64, add: i64) -> (usize, i64, Bend) {
    const MAX: i64 = MAX_INTERVAL as i64;
    let last = last as i64;
    let mut lo_i: i64 = 0;
    let mut hi_i: i64 = MAX;
    let mut add_sum: i64 = 0; // add · T_k
    for (k0, st) in steps.iter().enumerate() {
        let k0 = k0 as i64; // steps before this one
        let k = k0 + 1;
        add_sum += k0 * add;
        let l = st.lo as i64 - last - add_sum;
        let u = st.hi as i64 - last - add_sum;
        let mut nlo = lo_i;
        let mut nhi = hi_i;
        if k * nlo < l {
            nlo = div_ceil(l, k);
        }
        if k * nhi > u {
            nhi = div_floor(u, k);
        }
        // This step's interval, I + k0·add, must stay in [0, MAX].
        let ka = k0 * add;
        if nlo < -ka {
            nlo = -ka;
        }
        if nhi > MAX - ka {
            nhi = MAX - ka;
        }
        if nlo > nhi {
            let bend = if nlo > hi_i {
                Bend::Up
            } else if nhi < lo_i || nlo + nhi < lo_i + hi_i {
                Bend::Down
            } else {
                Bend::Up
            };
            return (k0 as usize, hi_i, bend);
        }
        lo_i = nlo;
        hi_i = nhi;
    }
    (steps.len(), hi_i, Bend::None)
}

#[inline]
fn div_floor(a: i64, b: i64) -> i64 {
    let q = a / b;
    if a % b != 0 && a < 0 {
        q - 1
    } else {
        q
    }
}

#[inline]
fn div_ceil(a: i64, b: i64) -> i64 {
    let q = a / b;
    if a % b != 0 && a > 0 {
        q + 1
    } else {
        q
    }
}

/// The command covering the most of `steps` (all one direction, non-empty) from `last`.
fn best_fit(steps: &[Pending], last: u64, max_err: i64, guess_add: i64) -> Fit {
    let single = || {
        let (count, interval, _) = run_with_add(&steps[..1], last, 0);
        debug_assert_eq!(count, 1);
        Fit { interval, count: count.max(1), add: 0 }
    };
    if steps.len() < 2 {
        return single();
    }
    // From the first two steps: I ∈ [l1, u1] and 2I + A ∈ [l2, u2].
    let l = |i: usize| steps[i].lo as i64 - last as i64;
    let u = |i: usize| steps[i].hi as i64 - last as i64;
    let (l1, u1) = (l(0).max(0), u(0).min(MAX_INTERVAL as i64));
    let mut amin = (l(1) - 2 * u1).max(i16::MIN as i64);
    let mut amax = (u(1) - 2 * l1).min(i16::MAX as i64);
    if amin > amax {
        return single();
    }
    let mut add = guess_add.clamp(amin, amax);
    let mut best = Fit { interval: 0, count: 0, add: 0 };
    for _ in 0..MAX_TRIALS {
        let (count, interval, bend) = run_with_add(steps, last, add);
        if count > best.count || (count == best.count && add.abs() < best.add.abs()) {
            best = Fit { interval, count, add };
        }
        if bend == Bend::None {
            break;
        }
        if count >= 2 {
            let h = (count / 2) as i64;
            let dev = 3 * max_err / (h * h);
            amin = amin.max(add - dev);
            amax = amax.min(add + dev);
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
    if best.count == 0 {
        return single();
    }
    best
}

#[cfg(test)]
mod tests;
