//! Step compression: packs one stepper's ideal step times into `queue_step` commands.
//!
//! Each step has a window of MCU clocks [⌈ideal − max_error⌉, ⌊ideal⌋] it must land in.
//! Commands are chosen greedily from the oldest pending step (`compress::fit` finds the command covering
//! the most steps, ending as late as possible), with a one-command lookahead: ending the command
//! one or two steps earlier moves the anchor of the next command, and is chosen when the two
//! commands together then cover more steps (benchy: 0.4 % fewer commands, see
//! [`DEFAULT_LOOKAHEAD_BACKOFF`]). The next command computed by the lookahead is kept and
//! reused. An earlier end is only tried when a cheap necessary test (`fit::two_window_adds`:
//! some add lands three pairs of the steps the next command would need) does not rule the gain
//! out, and the search for that next command then only tries the adds this test leaves. Every
//! pass over the steps also yields the interval one step earlier, so the lookahead's shorter
//! command costs no pass; a failed pass names the steps that bound it, and their pair with the
//! failing step narrows the adds left to try, in the search for the longest command and in the
//! one for the latest end (see `compress::fit`). Greedy choices are not globally optimal;
//! the checker, not the algorithm, is what guarantees correctness.
//!
//! Cost (callgrind instructions of `cadence-bench plan` on the benchy, cartesian printer,
//! `--threads 0`; each change kept gives the same commands and wire bytes, on the corexy
//! printer and with two threads too): 4.71 G before issue #3, 3.62 G after (−23 %). In order:
//! the latest-end search cuts its range with the pair of a failed probe's binding step and
//! failing step and probes the new top at once, and the byte-saving search skips adds whose
//! interval would take no fewer bytes or that cannot land the pairs (−0.09 G); passes
//! specialised on the sign of the add, which leaves one interval-range check per step
//! (−0.37 G); `pair_adds` without its zero and overflow checks, inlined into
//! `two_window_adds` (−0.16 G); the lookahead's follow-up command searched only among the adds
//! of its `two_window_adds` range, that test before `may_reach` (−0.09 G); the largest add the
//! search for the longest command tried above its answer caps the latest-end search (−0.02 G);
//! the `fit::may_reach` filter (a real-valued command through 4 sampled steps) dropped: with
//! the bounded follow-up search it cost more than it saved (−0.09 G); in the search for the
//! longest command, the `two_window_adds` stop for one more step (−0.22 G) and the deviation
//! bound around the best add so far (−0.04 G) dropped: with the binding-pair cuts they cost
//! more than they save. Tried and not kept: aiming each new probe at the centre of the adds
//! that could land 1.5× (or 2×, 1.25×, +2) the best count (11 % fewer steps scanned, 1 % more
//! instructions); a first guess clamped into the `two_window_adds` range of the current
//! command's count (0.7 % more instructions); the longest command's add instead of its
//! latest-end add as the follow-up's first guess (no change); the middle pair alone as the
//! stop test (2.5 % more than none); dropping the deviation bound around each probe too (1.6 %
//! more); requiring the byte-saving add to reach the same end by divisibility (0.3 % fewer, but
//! other commands: benchy cartesian −1, corexy +5).
//!
//! A second round, around the fitting (same commands and bytes): the windows written into room
//! made for the move's step count, each from one float-to-integer conversion, and direction
//! runs from a list of the indices where the direction turns instead of a pass over the steps:
//! 3.56 G → 3.35 G (corexy 3.86 G → 3.55 G). Passes over the steps per step compressed: 3.1
//! (benchy: 37.3 M steps scanned for 12.0 M, 61 % of them by the lookahead's follow-up search
//! for the next command, which is then reused), with commands of 26 steps on average. Tried and
//! not kept: a pass that keeps where the ends of the interval range put each step and
//! recomputes the bounds only when a window cuts them (+19 %: on the benchy most steps move a
//! bound, the runs being short); the interval-range check left out of the loop for the steps
//! before it can bind (+0.2 %); the prefix interval from the step that last lowered the upper
//! bound instead of a copy per step (+2 %); a per-step test of the direction as steps are
//! queued (−0.3 %, where checking only a move's first step on linear kinematics gives −1 %).
//!
//! Cruise lines (a move's cruise, a shaped stretch where every term cruises: most of a print's
//! steps) are kept as spans beside their windows, and a command starting in one comes from the
//! line's formula in O(1) whatever its length (`compress::line`, with its error bound's proof),
//! the per-step search only deciding where a command may carry an add (near a line's ends).
//! Constant-acceleration stretches (a move's acceleration and deceleration, a shaped stretch
//! whose summed trajectory is quadratic) can be kept as curve spans, a command from one taking
//! the add of the curve's formula without a search (`compress::curve`); off by default
//! ([`SearchTuning`]): on the benchy it took more instructions than the search, not fewer.
//!
//! The default ([`SearchTuning::default`]) trades a few commands for instructions: the search
//! tries at most [`DEFAULT_MAX_PASSES`] adds per command and takes the first longest command
//! found, without the latest-end search (benchy, cartesian, `--threads 2`, callgrind: 3.02 G →
//! 2.48 G instructions, 456,157 → 460,178 queue_step, Klipper 474,894; README "`cadence bench
//! plan`", per-command design).
//!
//! Commands never go back in time (every interval ≥ 0); a `reset_step_clock` precedes the first
//! step and any step more than 2^29 ticks after the previous one; `set_next_step_dir` precedes
//! the first step and each direction change.

mod curve;
mod fit;
mod line;
mod resync; // homing: resync after a stop on trigger

use std::collections::VecDeque;

use crate::kinematics::StepperKin;
use crate::stepgen::StepGen;
use crate::stepgen::{line_by_steps, line_clock, Curve, StepSink};
pub use crate::stepgen::{IdealStep, StepCmd};
use crate::toolhead::Move;
use curve::{curve_add, curve_command, CurveSpan};
use fit::{
    curvature_add, fit_prefix, latest_end, longest_fit, longest_fit_within, two_window_adds, Fit, StepWindow,
    MAX_TRIALS,
};
use line::{line_fit, LineSpan, MIN_SPAN};

/// Largest interval sent (and largest gap without a `reset_step_clock`), in ticks.
pub const MAX_INTERVAL: u64 = 1 << 29;
/// Most steps in one `queue_step` (`count` is a u16).
pub const MAX_COUNT: usize = 65535;
/// How many steps earlier than the longest fit the lookahead tries to end a command by default.
/// Benchy (cartesian reference printer, 50 MHz, release build, this VM, single thread): 0 →
/// 457,913 commands, 1 → 456,392 (CPU 0.45 s for the whole plan), 2 → 456,119 (0.59 s); with
/// the two planning threads 456,157 and 455,840 (Klipper: 456,811). Plain greedy without the
/// latest-end rule of `compress::fit` gave 459,945.
pub const DEFAULT_LOOKAHEAD_BACKOFF: usize = 1;

/// Default of [`SearchTuning::max_passes`].
pub const DEFAULT_MAX_PASSES: usize = 4;

/// How the commands off the cruise lines are found: the per-command design's choices and the
/// search's, each selectable so both can be measured (README "`cadence bench plan`").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SearchTuning {
    /// A command starting on a constant-acceleration curve takes the add of the curve's
    /// formula, its interval and count from one or two exact passes (`compress::curve`),
    /// instead of the search over adds.
    pub curve_commands: bool,
    /// The search for a command starting on a curve tries the add of the curve's formula
    /// first (`compress::curve`), its cuts then deciding as off the curves.
    pub curve_guess: bool,
    /// Among the commands of the longest count, search for the one ending latest
    /// (`fit::latest_end`, with the byte saving); off: the first longest found.
    pub latest_end: bool,
    /// Most adds the search for the longest command tries per command (1..=24).
    pub max_passes: usize,
    /// Most passes over the steps per curve command (the formula's add, then the nearest adds
    /// the way each pass bends).
    pub curve_passes: usize,
}

impl Default for SearchTuning {
    fn default() -> Self {
        SearchTuning {
            curve_commands: false,
            curve_guess: false,
            latest_end: false,
            max_passes: DEFAULT_MAX_PASSES,
            curve_passes: curve::PASSES,
        }
    }
}

impl SearchTuning {
    /// Whether the curve spans are kept.
    fn curves(&self) -> bool {
        self.curve_commands || self.curve_guess
    }

    /// The per-step search everywhere off the lines (the design before the per-command one).
    pub const SEARCH: SearchTuning = SearchTuning {
        curve_commands: false,
        curve_guess: false,
        latest_end: true,
        max_passes: MAX_TRIALS,
        curve_passes: curve::PASSES,
    };
}

/// The step generator and compressor of one stepper.
#[derive(Debug)]
pub struct StepCompressor {
    gen: StepGen,
    step_dist: f64,
    max_err: u64,
    pending: Vec<StepWindow>,
    head: usize,
    /// The indices i ≥ 1 of `pending` (ascending, those ≤ head may linger) whose step turns
    /// the other way from step i − 1: the direction run starting at `head` ends at the first
    /// one above it, found without a pass over the steps.
    flips: VecDeque<usize>,
    /// Stretches of pending steps on one cruise line (ascending, those ending ≤ head may
    /// linger): a command starting in one is found from the line's formula (`compress::line`).
    lines: VecDeque<LineSpan>,
    /// Stretches of pending steps on one constant-acceleration curve (ascending, those ending
    /// ≤ head may linger), kept while curve commands are on: a command from one takes the add
    /// of the curve's formula (`compress::curve`).
    curves: VecDeque<CurveSpan>,
    /// Whether commands in a line come from its formula (default) or the per-step search.
    line_fit: bool,
    /// How the commands off the lines are found.
    tuning: SearchTuning,
    last_clock: u64,
    started: bool,
    dir: Option<bool>,
    last_add: i64,
    /// Steps of the last command emitted (the expected length of the next).
    last_count: usize,
    position_steps: i64,
    step_count: u64,
    queue_steps: u64,
    record_ideal: bool,
    ideal: VecDeque<IdealStep>,
    /// Ideal clock of the last step queued (steps are kept in time order).
    last_ideal: f64,
    /// Steps the lookahead may end a command early (0 = plain greedy).
    backoff: usize,
    /// The next command as the lookahead computed it, valid while nothing it depends on changed.
    next: Option<NextFit>,
}

/// A command computed ahead: valid for this head index, MCU clock and run end.
#[derive(Debug, Clone, Copy)]
struct NextFit {
    head: usize,
    last_clock: u64,
    run_end: usize,
    fit: Fit,
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
            // Room for 1024 direction changes pending at once (the planner loop allocates
            // nothing after warm-up: tests/alloc_free.rs).
            flips: VecDeque::with_capacity(1 << 10),
            lines: VecDeque::with_capacity(1 << 10),
            curves: VecDeque::with_capacity(1 << 10),
            line_fit: true,
            tuning: SearchTuning::default(),
            last_clock: 0,
            started: false,
            dir: None,
            last_add: 0,
            last_count: 0,
            position_steps: 0,
            step_count: 0,
            queue_steps: 0,
            record_ideal: false,
            ideal: VecDeque::new(),
            last_ideal: 0.0,
            next: None,
            backoff: DEFAULT_LOOKAHEAD_BACKOFF,
        }
    }

    /// How many steps earlier than the longest possible a command may end when that lets the
    /// next command cover more (0 = plain greedy; default [`DEFAULT_LOOKAHEAD_BACKOFF`]).
    pub fn set_lookahead_backoff(&mut self, steps: usize) {
        self.backoff = steps;
        self.next = None;
    }

    /// Whether a command starting in a cruise line is found from the line's formula (default,
    /// see `compress::line`) or, like every other, by the per-step search (the reference the
    /// formula's commands are measured against).
    pub fn set_line_fit(&mut self, on: bool) {
        self.line_fit = on;
    }

    /// How the commands off the cruise lines are found ([`SearchTuning`]; default: curve
    /// commands from the formula, the latest-end search, 24 passes at most).
    pub fn set_tuning(&mut self, tuning: SearchTuning) {
        self.tuning = tuning;
        if !tuning.curves() {
            self.curves.clear();
        }
        self.next = None;
    }

    /// A new step distance from the next move on: the stepper stays where it is and counts
    /// steps of the new size from there.
    pub fn set_step_dist(&mut self, step_dist: f64) {
        self.step_dist = step_dist;
        self.gen.set_step_dist(step_dist);
    }

    /// The stepper position (mm, in its own coordinate) after the last move generated.
    pub fn commanded_position(&self) -> f64 {
        self.gen.last_pos()
    }

    /// mm per step.
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

    /// Generates this stepper's steps for `mv` (moves must be pushed in order). `kin` gives the
    /// stepper's map; its step distance is this compressor's. A step whose computed time falls
    /// before the previous one (floating-point noise) is raised to it; the recorded ideal step is
    /// the raised one.
    ///
    /// The windows are written into room made for the step count [`StepGen::steps_in`] gives
    /// (exact for linear kinematics, a hint otherwise: steps beyond it go to a side buffer
    /// appended after, unused room is cut off), so the per-step path is one store with no
    /// capacity check; the generator's own running maximum, started at the last step queued
    /// from any source, keeps the clocks in order.
    pub fn push_move(&mut self, mv: &Move, kin: &StepperKin) {
        let max_err = self.max_err as i64;
        let start = self.pending.len();
        let room = self.gen.steps_in(mv, kin);
        self.pending.resize(
            start + room,
            StepWindow {
                lo: 0,
                hi: 0,
                dir: false,
            },
        );
        let mut sink = WindowSink {
            slots: &mut self.pending[start..],
            used: 0,
            extra: Vec::new(),
            max_err,
            base: start,
            lines: self.line_fit.then_some(&mut self.lines),
            curves: self.tuning.curves().then_some(&mut self.curves),
        };
        self.gen.raise_last_clock(self.last_ideal);
        // Two loops rather than a test of the flag per step.
        if self.record_ideal {
            let sink = RecordingSink {
                inner: &mut sink,
                ideal: &mut self.ideal,
            };
            self.gen.gen_move(mv, kin, sink);
        } else {
            self.gen.gen_move(mv, kin, &mut sink);
        }
        let (used, mut extra) = (sink.used, sink.extra);
        self.pending.truncate(start + used);
        self.pending.append(&mut extra);
        self.last_ideal = self.last_ideal.max(self.gen.last_clock());
        // Direction changes: on linear kinematics a move's steps all go one way (see
        // `StepGen::gen_move`), so only its first step can turn; otherwise look at each.
        let from = start.max(1);
        let to = if kin.linear_coeffs().is_some() {
            (from + 1).min(self.pending.len())
        } else {
            self.pending.len()
        };
        for i in from..to {
            if self.pending[i].dir != self.pending[i - 1].dir {
                self.flips.push_back(i);
            }
        }
    }

    /// Queues one step at `ideal_clock` ticks (raised to the previous step's time if earlier),
    /// for callers that compute step times themselves.
    pub fn push_step(&mut self, ideal_clock: f64, dir: bool) {
        if !ideal_clock.is_finite() {
            return;
        }
        self.last_ideal = ideal_clock.max(self.last_ideal);
        let max_err = self.max_err as i64;
        if self.pending.last().is_some_and(|w| w.dir != dir) {
            self.flips.push_back(self.pending.len());
        }
        queue_step_time(
            &mut self.pending,
            &mut self.ideal,
            self.record_ideal,
            max_err,
            self.last_ideal,
            dir,
        );
    }

    /// Queues the steps of a line: at [`line_clock`]`(t0, dt, i, floor)` ticks for i in
    /// `from..to`, all going `dir`, dt > 0 ([`StepSink::line`]'s contract; `floor` is raised to
    /// the previous step's time). One store per step; the same windows and recorded ideal steps
    /// as [`Self::push_step`] for each of those clocks.
    pub fn push_line(&mut self, t0: f64, dt: f64, from: i64, to: i64, floor: f64, dir: bool) {
        if to <= from {
            return;
        }
        let last = line_clock(t0, dt, to - 1, floor);
        if !(t0.is_finite() && dt.is_finite() && dt > 0.0 && last.is_finite()) {
            for i in from..to {
                self.push_step(line_clock(t0, dt, i, floor), dir);
            }
            return;
        }
        let floor = floor.max(self.last_ideal);
        if self.pending.last().is_some_and(|w| w.dir != dir) {
            self.flips.push_back(self.pending.len());
        }
        let max_err = self.max_err as i64;
        let n = (to - from) as usize;
        let start = self.pending.len();
        self.pending.resize(start + n, StepWindow { lo: 0, hi: 0, dir });
        for (slot, i) in self.pending[start..].iter_mut().zip(from..to) {
            *slot = step_window(line_clock(t0, dt, i, floor), max_err, dir);
        }
        if self.line_fit {
            record_span(&mut self.lines, start, t0, dt, from, to, floor);
        }
        if self.record_ideal {
            for i in from..to {
                self.ideal.push_back(IdealStep {
                    clock: line_clock(t0, dt, i, floor),
                    dir,
                });
            }
        }
        self.last_ideal = line_clock(t0, dt, to - 1, floor);
    }

    /// The next `steps` steps queued (by [`Self::push_step`]) lie on `curve` (a hint: the
    /// commands from them take their adds from its formula, `compress::curve`).
    pub fn push_curve(&mut self, curve: Curve, steps: usize) {
        let start = self.pending.len();
        if self.tuning.curves() {
            record_curve(&mut self.curves, start, curve, steps);
        }
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
            self.flips.clear();
            self.lines.clear();
            self.curves.clear();
            self.next = None;
        } else if self.head > 4096 && self.head * 2 > self.pending.len() {
            self.pending.drain(..self.head);
            let head = self.head;
            self.flips.retain(|&f| f > head);
            for f in self.flips.iter_mut() {
                *f -= head;
            }
            drop_below(&mut self.lines, head);
            drop_below(&mut self.curves, head);
            self.head = 0;
            self.next = None;
        }
    }

    /// The command for the steps pending[head..run_end] (one direction), with the lookahead.
    fn choose_fit(&mut self, run_end: usize) -> Fit {
        let ahead = self.next.take();
        let run = &self.pending[self.head..run_end];
        let last = self.last_clock;
        let max_err = self.max_err as i64;
        let longest = match ahead {
            Some(n) if n.head == self.head && n.last_clock == last && n.run_end == run_end => n.fit,
            _ => match self.curve_command(self.head, run_end, last) {
                Some(f) => f,
                None => {
                    let guess = self
                        .curve_guess(self.head, run_end, last)
                        .unwrap_or(self.last_add);
                    longest_fit(run, last, max_err, guess, self.tuning.max_passes)
                }
            },
        };
        let fit = if self.tuning.latest_end {
            latest_end(run, last, max_err, longest)
        } else {
            longest
        };
        self.lookahead(run_end, fit)
    }

    /// `fit` (the longest command from the head, ending latest), or a command a step or two
    /// shorter when the next command then covers more; the next command is kept in `next`.
    fn lookahead(&mut self, run_end: usize, fit: Fit) -> Fit {
        let run = &self.pending[self.head..run_end];
        let last = self.last_clock;
        let max_err = self.max_err as i64;
        if fit.count >= run.len() || self.backoff == 0 {
            return fit;
        }
        // A next command starting in a cruise line long enough that it carries no add: the
        // longest comes from the line's formula, as it will be emitted (`compress::line`).
        let (head, lines, pending) = (self.head, &self.lines, &self.pending);
        let from_line = |f: &Fit| {
            if !self.line_fit {
                return None;
            }
            let at = head + f.count;
            let span = lines.iter().find(|l| l.end > at).filter(|l| l.start <= at)?;
            line_fit(span, pending, at, run_end, f.end(last), max_err).map(|l| l.fit)
        };
        // Only the length of the following command matters here.
        let follow = |f: &Fit| {
            if let Some(next) = from_line(f) {
                return next;
            }
            if let Some(next) = self.curve_command(head + f.count, run_end, f.end(last)) {
                return next;
            }
            let (rest, from) = (&run[f.count..], f.end(last));
            // First guess: the add of the steps' own curvature over a command as long as this one.
            let guess = self
                .curve_guess(head + f.count, run_end, from)
                .or_else(|| curvature_add(rest, from, f.count))
                .unwrap_or(f.add);
            longest_fit(rest, from, max_err, guess, self.tuning.max_passes)
        };
        let mut best = (fit, follow(&fit));
        let guess = best.1.add;
        // Ending earlier cannot help when the next command already reaches the run's end.
        // (Trying only when the next command is under half as long takes 30 % off compression
        // time on the benchy but gives 457,645 commands: more than Klipper's 456,811.)
        let tries = if fit.count + best.1.count >= run.len() {
            0
        } else {
            self.backoff.min(fit.count - 1)
        };
        for back in 1..=tries {
            let shorter = if back == 1 { fit.shortened() } else { None };
            let Some(f) = shorter.or_else(|| fit_prefix(run, last, fit.count - back, fit.add)) else {
                break;
            };
            // It only wins when the next command reaches `need` steps: skip it when no add lands
            // three pairs of those steps, and search only the adds that do (the same choices).
            let need = best.0.count + best.1.count + 1 - f.count;
            let rest = &run[f.count..];
            if need > rest.len() {
                continue;
            }
            let Some(within) = two_window_adds(rest, f.end(last), need) else {
                continue;
            };
            let next = match from_line(&f) {
                Some(next) => next,
                None => match self.curve_command(head + f.count, run_end, f.end(last)) {
                    Some(next) => next,
                    None => {
                        let guess = self
                            .curve_guess(head + f.count, run_end, f.end(last))
                            .unwrap_or(guess);
                        longest_fit_within(rest, f.end(last), max_err, guess, within, self.tuning.max_passes)
                    }
                },
            };
            if f.count + next.count > best.0.count + best.1.count {
                best = (f, next);
            }
        }
        let (chosen, next) = best;
        self.next = Some(NextFit {
            head: self.head + chosen.count,
            last_clock: chosen.end(last),
            run_end,
            fit: next,
        });
        chosen
    }

    /// The curve span holding pending index `at`, with the pending steps from `at` to
    /// `run_end`; `None` off every curve.
    fn curve_at(&self, at: usize, run_end: usize) -> Option<(&CurveSpan, &[StepWindow])> {
        let span = self
            .curves
            .iter()
            .find(|c| c.end > at)
            .filter(|c| c.start <= at)?;
        Some((span, self.pending.get(at..run_end)?))
    }

    /// The add of the curve's formula for a command from pending index `at` (before
    /// `run_end`) from `last`, when `at` lies on a curve and the formula is the search's
    /// first guess (`SearchTuning::curve_guess`).
    fn curve_guess(&self, at: usize, run_end: usize, last: u64) -> Option<i64> {
        if !self.tuning.curve_guess {
            return None;
        }
        let (span, steps) = self.curve_at(at, run_end)?;
        curve_add(span, steps, at, last, self.max_err as i64)
    }

    /// The command from pending index `at` (before `run_end`) from `last` when `at` lies on a
    /// curve, with the add of its formula (`compress::curve`).
    fn curve_command(&self, at: usize, run_end: usize, last: u64) -> Option<Fit> {
        if !self.tuning.curve_commands {
            return None;
        }
        let (span, steps) = self.curve_at(at, run_end)?;
        curve_command(
            span,
            steps,
            at,
            last,
            self.max_err as i64,
            self.tuning.curve_passes,
        )
    }

    /// The command from the head when it lies in a cruise line and the line's formula gives
    /// one (`compress::line`), ending before `run_end`.
    fn line_command(&mut self, run_end: usize) -> Option<Fit> {
        let head = self.head;
        while self.lines.front().is_some_and(|l| l.end <= head) {
            self.lines.pop_front();
        }
        let span = *self.lines.front()?;
        if span.start > head {
            return None;
        }
        let (last, max_err) = (self.last_clock, self.max_err as i64);
        let l = line_fit(&span, &self.pending, head, run_end, last, max_err)?;
        let fit = l.fit;
        if self.backoff == 0 || fit.count < 2 {
            return Some(fit);
        }
        // The lookahead, as the search's: one step shorter when the next command then covers
        // more. Inside the line both next commands come from the formula too; where one does
        // not (the line's last command), the search's lookahead decides.
        let next = |f: &Fit| {
            line_fit(
                &span,
                &self.pending,
                head + f.count,
                run_end,
                f.end(last),
                max_err,
            )
        };
        let shorter = fit.shortened();
        let pair = match (l.last, shorter) {
            (false, Some(s)) => next(&fit).zip(next(&s)).map(|(a, b)| (s, a.fit, b.fit)),
            _ => None,
        };
        Some(match pair {
            Some((s, after_fit, after_s)) => {
                if s.count + after_s.count > fit.count + after_fit.count {
                    s
                } else {
                    fit
                }
            }
            None => self.lookahead(run_end, fit),
        })
    }

    /// Emits one `queue_step` (preceded by a reset and/or direction change when needed).
    fn emit_one(&mut self, out: &mut Vec<StepCmd>) {
        let first = self.pending[self.head];
        if !self.started || first.lo > self.last_clock.saturating_add(MAX_INTERVAL) {
            let clock = first.lo.saturating_sub(1).max(self.last_clock);
            out.push(StepCmd::ResetClock { clock });
            self.last_clock = clock;
            self.started = true;
        }
        if self.dir != Some(first.dir) {
            out.push(StepCmd::SetDir { dir: first.dir });
            self.dir = Some(first.dir);
        }
        while self.flips.front().is_some_and(|&f| f <= self.head) {
            self.flips.pop_front();
        }
        let dir_run_end = self.flips.front().copied().unwrap_or(self.pending.len());
        let run_end = dir_run_end.min(self.head + MAX_COUNT);
        while self.curves.front().is_some_and(|c| c.end <= self.head) {
            self.curves.pop_front();
        }
        let fit = match self.line_command(run_end) {
            Some(f) => f,
            None => self.choose_fit(run_end),
        };
        let count = fit.count as u64;
        let first_clock = self.last_clock + fit.interval as u64;
        let last_clock = fit.end(self.last_clock);
        out.push(StepCmd::QueueStep {
            interval: fit.interval as u32,
            count: fit.count as u16,
            add: fit.add as i16,
            first_clock,
            last_clock,
        });
        self.last_clock = last_clock;
        self.last_add = fit.add;
        self.last_count = fit.count;
        self.head += fit.count;
        self.step_count += count;
        self.queue_steps += 1;
        self.position_steps += if first.dir { count as i64 } else { -(count as i64) };
    }
}

/// A [`StepSink`] queueing into a compressor: [`StepCompressor::push_step`] per step and
/// [`StepCompressor::push_line`] per line (generators that compute step times themselves).
#[derive(Debug)]
pub struct CompressorSink<'a>(pub &'a mut StepCompressor);

impl StepSink for CompressorSink<'_> {
    #[inline]
    fn step(&mut self, clock: f64, dir: bool) {
        self.0.push_step(clock, dir);
    }

    #[inline]
    fn line(&mut self, t0: f64, dt: f64, from: i64, to: i64, floor: f64, dir: bool) {
        self.0.push_line(t0, dt, from, to, floor, dir);
    }

    #[inline]
    fn curve(&mut self, curve: Curve, steps: usize) {
        self.0.push_curve(curve, steps);
    }
}

/// Writes a move's step windows into the room made for them (steps beyond it, only possible on
/// non-linear kinematics where the room is a hint, go to `extra`).
struct WindowSink<'a> {
    slots: &'a mut [StepWindow],
    used: usize,
    extra: Vec<StepWindow>,
    max_err: i64,
    /// Pending index of `slots[0]`.
    base: usize,
    /// Where a line's span is recorded (`None`: line commands are off).
    lines: Option<&'a mut VecDeque<LineSpan>>,
    /// Where a curve's span is recorded (`None`: curve commands are off).
    curves: Option<&'a mut VecDeque<CurveSpan>>,
}

impl StepSink for &mut WindowSink<'_> {
    #[inline]
    fn step(&mut self, clock: f64, dir: bool) {
        let w = step_window(clock, self.max_err, dir);
        match self.slots.get_mut(self.used) {
            Some(slot) => {
                *slot = w;
                self.used += 1;
            }
            None => self.extra.push(w),
        }
    }

    /// A cruise (87 % of the benchy's steps): one store per step into room checked once, no
    /// per-step test of the room (benchy, whole plan, `--threads 0`: 3.252 G → 3.200 G
    /// instructions under callgrind, the same windows).
    #[inline]
    fn line(&mut self, t0: f64, dt: f64, from: i64, to: i64, floor: f64, dir: bool) {
        let n = (to - from) as usize;
        let max_err = self.max_err;
        match self.slots.get_mut(self.used..self.used + n) {
            Some(room) => {
                for (slot, i) in room.iter_mut().zip(from..to) {
                    *slot = step_window(line_clock(t0, dt, i, floor), max_err, dir);
                }
                if let Some(lines) = self.lines.as_deref_mut() {
                    record_span(lines, self.base + self.used, t0, dt, from, to, floor);
                }
                self.used += n;
            }
            None => line_by_steps(self, t0, dt, from, to, floor, dir),
        }
    }

    #[inline]
    fn curve(&mut self, curve: Curve, steps: usize) {
        if let Some(curves) = self.curves.as_deref_mut() {
            let at = self.base + self.used + self.extra.len();
            record_curve(curves, at, curve, steps);
        }
    }
}

/// A [`WindowSink`] that also records each step's ideal time (tests, `--check`): lines stay
/// lines, so the commands are the same as without recording.
struct RecordingSink<'a, 'b> {
    inner: &'a mut WindowSink<'b>,
    ideal: &'a mut VecDeque<IdealStep>,
}

impl StepSink for RecordingSink<'_, '_> {
    #[inline]
    fn step(&mut self, clock: f64, dir: bool) {
        let mut inner = &mut *self.inner;
        inner.step(clock, dir);
        self.ideal.push_back(IdealStep { clock, dir });
    }

    #[inline]
    fn line(&mut self, t0: f64, dt: f64, from: i64, to: i64, floor: f64, dir: bool) {
        let mut inner = &mut *self.inner;
        inner.line(t0, dt, from, to, floor, dir);
        for i in from..to {
            self.ideal.push_back(IdealStep {
                clock: line_clock(t0, dt, i, floor),
                dir,
            });
        }
    }

    #[inline]
    fn curve(&mut self, curve: Curve, steps: usize) {
        let mut inner = &mut *self.inner;
        inner.curve(curve, steps);
    }
}

/// Records the steps `from..to` of a line written at pending index `at` on as a span, those
/// from the first above `floor` on (only the first few can be raised to it; [`line_clock`]
/// is the line's own value above it), when enough are left.
fn record_span(lines: &mut VecDeque<LineSpan>, at: usize, t0: f64, dt: f64, from: i64, to: i64, floor: f64) {
    let mut i = from;
    while i < to && line_clock(t0, dt, i, floor) <= floor {
        i += 1;
    }
    let start = at + (i - from) as usize;
    let end = at + (to - from) as usize;
    if end - start >= MIN_SPAN {
        lines.push_back(LineSpan {
            start,
            end,
            t0,
            dt,
            i0: i,
        });
    }
}

/// A stretch of pending steps given by a formula (`compress::line`, `compress::curve`).
pub(crate) trait Span: Copy {
    /// Its pending indices: start..end.
    fn range(&self) -> (usize, usize);
    /// The same formula without its first `cut` steps, every pending index lowered by `by`
    /// (≤ start + cut).
    fn moved(self, cut: usize, by: usize) -> Self;
}

/// Drops the pending steps below `head` from `spans` (compaction: index `head` becomes 0).
fn drop_below<S: Span>(spans: &mut VecDeque<S>, head: usize) {
    while spans.front().is_some_and(|s| s.range().1 <= head) {
        spans.pop_front();
    }
    for s in spans.iter_mut() {
        let cut = head.saturating_sub(s.range().0);
        *s = s.moved(cut, head);
    }
}

/// Records the next `steps` steps, from pending index `at`, as on `curve` (when a command
/// could start in them and carry an add: at least 3).
fn record_curve(curves: &mut VecDeque<CurveSpan>, at: usize, curve: Curve, steps: usize) {
    if steps >= 3 {
        curves.push_back(CurveSpan {
            start: at,
            end: at + steps,
            curve,
        });
    }
}

/// Appends a step with ideal time `clock` (≥ 0, ≥ the previous one) and its window.
#[inline]
fn queue_step_time(
    pending: &mut Vec<StepWindow>,
    ideal: &mut VecDeque<IdealStep>,
    record: bool,
    max_err: i64,
    clock: f64,
    dir: bool,
) {
    pending.push(step_window(clock, max_err, dir));
    if record {
        ideal.push_back(IdealStep { clock, dir });
    }
}

/// The window of a step with ideal time `clock` (≥ 0, below 2^53): [⌈clock − max_err⌉, ⌊clock⌋],
/// the start clamped to 0.
#[inline(always)]
fn step_window(clock: f64, max_err: i64, dir: bool) -> StepWindow {
    // clock ≥ 0, so truncation is floor (f64::floor and ceil are library calls on baseline
    // x86-64, and f64 ↔ i64 conversions are single instructions where f64 ↔ u64 ones are not).
    // max_err is an integer, so ⌈clock − max_err⌉ = ⌈clock⌉ − max_err: one conversion, where
    // clock − max_err as a float would need a second (the same value: that subtraction is exact
    // whenever its result is positive, and a start at or below 0 is clamped either way).
    let hi = clock as i64;
    let lo = (hi + i64::from(clock > hi as f64) - max_err).max(0) as u64;
    StepWindow {
        lo,
        hi: hi as u64,
        dir,
    }
}

#[cfg(test)]
mod tests;
