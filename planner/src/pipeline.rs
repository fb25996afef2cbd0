//! The planner's top level: G-code lines in, per-stepper step commands out, in time order.
//!
//! Flow per [`Pipeline::generate`] call: final moves from the toolhead → every stepper generates
//! its steps (independently: each lane could run on its own thread) → each compressor emits the
//! commands whose first step's ideal time is before the horizon (the end of the final moves minus
//! [`COMPRESS_LOOKAHEAD_S`], so commands near the horizon still see the steps after it) → a k-way
//! merge by clock.
//!
//! Ordering: a command's key is the clock of its first step (`reset_step_clock` and
//! `set_next_step_dir` take the key of the `queue_step` they precede). Commands emitted later have
//! a first step whose ideal time is ≥ the horizon, so their key is ≥ horizon − max_error; only
//! keys below that are released, the rest wait for the next call. The output is therefore
//! globally sorted. When the toolhead is at rest everything is released, and the next move is
//! delayed by max_error so that later commands still sort after the released ones.

use std::cmp::Reverse;
use std::collections::BinaryHeap;

use crate::compress::StepCompressor;
use crate::gcode::GcodeLine;
use crate::kinematics::{Kinematics, StepperKin};
use crate::machine::{Applied, GcodeState, PlanError, PlanErrorKind};
use crate::stepgen::{IdealStep, StepCmd};
use crate::toolhead::{Move, Toolhead, ToolheadConfig};

/// Print time of final moves kept back from compression as lookahead (s).
pub const COMPRESS_LOOKAHEAD_S: f64 = 0.25;

/// One stepper as the planner needs it.
#[derive(Debug, Clone, PartialEq)]
pub struct StepperSpec {
    pub name: String,
    /// 0..=3 = X, Y, Z, E.
    pub axis: usize,
    pub step_dist: f64,
}

/// Everything the planner needs from the printer configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct PipelineConfig {
    pub toolhead: ToolheadConfig,
    pub steppers: Vec<StepperSpec>,
    /// MCU ticks per print second.
    pub clock_freq: f64,
    /// Largest step time error allowed by compression (s), 25e-6 in Klipper.
    pub max_error_s: f64,
    /// Position of X, Y, Z after G28 (position_endstop).
    pub home_position: [f64; 3],
}

/// Counters for reports.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PipelineStats {
    /// Moves accepted by the toolhead.
    pub moves: u64,
    /// Steps emitted per stepper.
    pub steps: Vec<u64>,
    /// `queue_step` commands emitted per stepper.
    pub queue_steps_per_stepper: Vec<u64>,
    /// `queue_step` commands emitted in total.
    pub queue_steps: u64,
    /// End print time of the last final move.
    pub print_time_end: f64,
}

/// One stepper's step path.
#[derive(Debug)]
struct Lane {
    kin: StepperKin,
    comp: StepCompressor,
    /// Commands emitted by the compressor and not yet released, with their sort keys.
    held: Vec<(u64, StepCmd)>,
    /// Scratch for the compressor's output.
    fresh: Vec<StepCmd>,
}

/// G-code → step commands.
#[derive(Debug)]
pub struct Pipeline {
    state: GcodeState,
    th: Toolhead,
    lanes: Vec<Lane>,
    clock_freq: f64,
    max_err_ticks: u32,
    moves: Vec<Move>,
    heap: BinaryHeap<Reverse<(u64, usize)>>,
    cursor: Vec<usize>,
    /// Compression horizon reached so far (ticks).
    upto: u64,
    planned_until: f64,
}

impl Pipeline {
    /// A pipeline whose toolhead is at rest at position 0 and whose first move starts at
    /// `start_print_time`.
    pub fn new(cfg: PipelineConfig, start_print_time: f64) -> Result<Pipeline, PlanError> {
        let bad = |msg: String| PlanError {
            line: 0,
            kind: PlanErrorKind::Config(msg),
        };
        cfg.toolhead.validate().map_err(|e| bad(e.to_string()))?;
        if !(cfg.clock_freq.is_finite() && cfg.clock_freq >= 1.0) {
            return Err(bad(format!("clock_freq {} must be ≥ 1", cfg.clock_freq)));
        }
        let max_err = cfg.max_error_s * cfg.clock_freq;
        if !(max_err.is_finite() && max_err >= 1.0 && max_err < (1u64 << 28) as f64) {
            return Err(bad(format!(
                "max_error_s {} is {max_err} ticks at {} Hz: must be 1 tick .. 2^28 ticks",
                cfg.max_error_s, cfg.clock_freq
            )));
        }
        if !(start_print_time.is_finite() && (0.0..=1e9).contains(&start_print_time)) {
            return Err(bad(format!(
                "start print time {start_print_time} must be in 0 ..= 1e9 s"
            )));
        }
        if cfg.home_position.iter().any(|v| !v.is_finite()) {
            return Err(bad(format!(
                "home position {:?} must be finite",
                cfg.home_position
            )));
        }
        let max_err_ticks = max_err.round() as u32;
        let kinematics = Kinematics::Cartesian;
        let mut lanes = Vec::with_capacity(cfg.steppers.len());
        for s in &cfg.steppers {
            if !(s.step_dist.is_finite() && s.step_dist > 1e-9 && s.step_dist < 1e3) {
                return Err(bad(format!(
                    "stepper '{}': step_dist {} must be in (1e-9, 1000) mm",
                    s.name, s.step_dist
                )));
            }
            let kin = kinematics
                .stepper(s.axis, s.step_dist)
                .map_err(|e| bad(format!("stepper '{}': {e}", s.name)))?;
            lanes.push(Lane {
                kin,
                comp: StepCompressor::new(s.step_dist, cfg.clock_freq, max_err_ticks),
                held: Vec::with_capacity(1024),
                fresh: Vec::with_capacity(1024),
            });
        }
        let n = lanes.len();
        Ok(Pipeline {
            state: GcodeState::new(cfg.home_position),
            th: Toolhead::new(cfg.toolhead, start_print_time),
            lanes,
            clock_freq: cfg.clock_freq,
            max_err_ticks,
            moves: Vec::with_capacity(1024),
            heap: BinaryHeap::with_capacity(n),
            cursor: vec![0; n],
            upto: 0,
            planned_until: start_print_time,
        })
    }

    /// Applies one G-code line to the toolhead.
    pub fn apply(&mut self, line: &GcodeLine) -> Result<Applied, PlanError> {
        self.state.apply(line, &mut self.th)
    }

    /// Ends the lookahead (the toolhead comes to rest after the last queued move), as M400
    /// does; for an idle G-code source.
    pub fn flush_lookahead(&mut self) {
        self.th.flush();
    }

    /// Appends the step commands that can no longer change, in clock order.
    pub fn generate(&mut self, out: &mut Vec<(usize, StepCmd)>) {
        self.th.take_moves(&mut self.moves);
        if self.moves.is_empty() {
            // Nothing new: everything earlier was released already, or waits for more moves.
            return;
        }
        let idle = self.th.queued_moves() == 0;
        let end = self.th.print_time();
        let horizon = if idle {
            end * self.clock_freq + 1.0
        } else {
            (end - COMPRESS_LOOKAHEAD_S) * self.clock_freq
        };
        let upto = if horizon > 0.0 { horizon as u64 } else { 0 };
        self.upto = self.upto.max(upto);
        self.run_lanes(false);
        if idle {
            self.release(u64::MAX, out);
            // Later steps may be up to max_error early: start them that much later.
            let _ = self.th.dwell(self.max_err_ticks as f64 / self.clock_freq);
            self.planned_until = end;
        } else {
            let bound = self.upto.saturating_sub(self.max_err_ticks as u64);
            self.release(bound, out);
            self.planned_until = self.planned_until.max(bound as f64 / self.clock_freq);
        }
    }

    /// Flushes everything (end of the file): the toolhead stops after the last move.
    pub fn finish(&mut self, out: &mut Vec<(usize, StepCmd)>) {
        self.th.flush();
        self.th.take_moves(&mut self.moves);
        self.run_lanes(true);
        self.release(u64::MAX, out);
        self.planned_until = self.planned_until.max(self.th.print_time());
    }

    /// Print time up to which every step has been emitted.
    pub fn planned_until(&self) -> f64 {
        self.planned_until
    }

    /// Commanded toolhead position (X, Y, Z, E).
    pub fn position(&self) -> [f64; 4] {
        self.th.position()
    }

    /// Net steps emitted per stepper.
    pub fn stepper_positions(&self) -> Vec<i64> {
        self.lanes.iter().map(|l| l.comp.position_steps()).collect()
    }

    /// Counters so far.
    pub fn stats(&self) -> PipelineStats {
        let steps: Vec<u64> = self.lanes.iter().map(|l| l.comp.step_count()).collect();
        let qs: Vec<u64> = self.lanes.iter().map(|l| l.comp.queue_step_count()).collect();
        PipelineStats {
            moves: self.th.moves_total(),
            queue_steps: qs.iter().sum(),
            steps,
            queue_steps_per_stepper: qs,
            print_time_end: self.th.print_time(),
        }
    }

    /// Compression lookahead of every stepper (see [`StepCompressor::set_lookahead_backoff`]):
    /// 0 is fastest, the default gives the fewest commands.
    pub fn set_lookahead_backoff(&mut self, steps: usize) {
        for l in &mut self.lanes {
            l.comp.set_lookahead_backoff(steps);
        }
    }

    /// Maximum step error in ticks.
    pub fn max_error_ticks(&self) -> u32 {
        self.max_err_ticks
    }

    /// Modal G-code state (read-only).
    pub fn gcode_state(&self) -> &GcodeState {
        &self.state
    }

    /// Declares axes homed without G28 (printers without endstops, tests).
    pub fn set_homed(&mut self, homed: [bool; 3]) {
        self.state.set_homed(homed);
    }

    /// Records every generated step's ideal time, per stepper, for [`Self::take_ideal`].
    pub fn set_record_ideal(&mut self, on: bool) {
        for l in &mut self.lanes {
            l.comp.set_record_ideal(on);
        }
    }

    /// Ideal steps generated for stepper `idx` since the last call (empty for a bad index).
    pub fn take_ideal(&mut self, idx: usize) -> Vec<IdealStep> {
        self.lanes
            .get_mut(idx)
            .map(|l| l.comp.take_ideal())
            .unwrap_or_default()
    }

    /// Step generation and compression for every lane (independent of each other).
    fn run_lanes(&mut self, all: bool) {
        let upto = self.upto;
        for lane in &mut self.lanes {
            for mv in &self.moves {
                lane.comp.push_move(mv, &lane.kin);
            }
            lane.fresh.clear();
            if all {
                lane.comp.finish(&mut lane.fresh);
            } else {
                lane.comp.flush(upto, &mut lane.fresh);
            }
            // Keys: a queue_step's first clock; reset/dir take the next queue_step's.
            let start = lane.held.len();
            let mut key = u64::MAX;
            lane.held.extend(lane.fresh.iter().map(|&c| (0, c)));
            for h in lane.held[start..].iter_mut().rev() {
                if let StepCmd::QueueStep { first_clock, .. } = h.1 {
                    key = first_clock;
                }
                h.0 = key;
            }
        }
        self.moves.clear();
    }

    /// Moves every held command with key < `bound` to `out`, merged by key (ties by stepper).
    fn release(&mut self, bound: u64, out: &mut Vec<(usize, StepCmd)>) {
        self.heap.clear();
        for (i, lane) in self.lanes.iter().enumerate() {
            self.cursor[i] = 0;
            if let Some(&(key, _)) = lane.held.first() {
                if key < bound || bound == u64::MAX {
                    self.heap.push(Reverse((key, i)));
                }
            }
        }
        while let Some(Reverse((_, i))) = self.heap.pop() {
            let lane = &self.lanes[i];
            let pos = self.cursor[i];
            out.push((i, lane.held[pos].1));
            self.cursor[i] = pos + 1;
            if let Some(&(key, _)) = lane.held.get(pos + 1) {
                if key < bound || bound == u64::MAX {
                    self.heap.push(Reverse((key, i)));
                }
            }
        }
        for (i, lane) in self.lanes.iter_mut().enumerate() {
            lane.held.drain(..self.cursor[i]);
        }
    }
}

#[cfg(test)]
mod tests;
