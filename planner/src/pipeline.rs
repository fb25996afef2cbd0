//! The planner's top level: G-code lines in, per-stepper step commands out, in time order.
//!
//! Flow per [`Pipeline::generate`] call: final moves from the toolhead → every stepper generates
//! its steps (independently: inline, or spread over worker threads and the caller's, see
//! `lanes`) → each compressor emits the
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
//!
//! With worker threads the moves go out in batches (jobs); a job's bound may be used only once
//! every lane has answered it, so the merger releases below the bound of the newest job all
//! lanes have answered. At rest it waits for every lane, as the inline mode does.
//!
//! Clock domains: print time is the main MCU's clock / its `clock_freq`, and the horizon, the
//! release bounds and the sort keys are in those ticks. A stepper on another MCU counts its
//! steps in that MCU's clock: its [`ClockMap`] (`clock = offset + freq · print_time`, set at
//! construction with [`Pipeline::with_clocks`] and refreshed between batches with
//! [`Pipeline::set_clock_map`]) carries each move into that clock before its steps are
//! generated, and its commands' keys back into print ticks for the merge (see `lanes`).

mod forced; // FORCE_MOVE, STEPPER_BUZZ
mod homing; // homing: stop part-way through a homing move, resync
mod lanes;

use std::cmp::Reverse;
use std::collections::{BinaryHeap, VecDeque};
use std::sync::Arc;

use crate::compress::StepCompressor;
use crate::extruders::{ExtruderEvent, ExtruderStepper, Extruders};
use crate::gcode::CommandText;
use crate::gcode::GcodeLine;
use crate::kinematics::Kinematics;
use crate::machine::{Applied, GcodeState, PlanError, PlanErrorKind, Retraction, ARC_RESOLUTION};
use crate::pressure_advance::{PaGen, PressureAdvance};
use crate::shaped::{shapes, ShapedGen};
use crate::shaper::InputShaper;
use crate::stepgen::{IdealStep, StepCmd};
use crate::toolhead::{Move, Toolhead, ToolheadConfig};
use lanes::{
    place, LaneClock, LaneEvent, LaneOut, LaneState, Msg, PaChange, ShaperChange, Workers, CMDS_CAPACITY,
};

/// An extruder stepper's lane index, configured step distance and rotation distance.
#[derive(Debug, Clone, Copy, PartialEq)]
struct ExtruderLane(usize, f64, f64);

/// Klipper's default `pressure_advance_smooth_time` (s), for SET_PRESSURE_ADVANCE when the
/// configuration has no pressure advance.
pub const DEFAULT_SMOOTH_TIME: f64 = 0.040;

/// Print time of final moves kept back from compression as lookahead (s).
pub const COMPRESS_LOOKAHEAD_S: f64 = 0.25;

/// One stepper as the planner needs it.
#[derive(Debug, Clone, PartialEq)]
pub struct StepperSpec {
    pub name: String,
    /// Which of the kinematics' steppers: 0..=2 (cartesian X, Y, Z; corexy A, B, Z; corexz A, Y,
    /// B), 3 = the extruder.
    pub axis: usize,
    pub step_dist: f64,
    /// For an extruder stepper (axis 3) of a printer with several extruders or extruder
    /// steppers; `None`: the one extruder's stepper (follows extruder 0, the options'
    /// pressure advance).
    pub extruder: Option<ExtruderLink>,
}

/// How an extruder stepper starts (see [`crate::extruders`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExtruderLink {
    /// The extruder whose motion it follows (`None`: it stands still until synced).
    pub queue: Option<usize>,
    /// Its pressure advance (advance 0: off).
    pub pressure_advance: PressureAdvance,
    /// Its configured rotation distance (mm), which SET_EXTRUDER_ROTATION_DISTANCE scales
    /// the step distance against.
    pub rotation_distance: f64,
}

/// Where one stepper's MCU clock stands against print time: `clock = offset + freq ·
/// print_time` (ticks). The main MCU's clock defines print time (offset 0, freq its clock
/// rate: [`ClockMap::identity`]); another MCU's map comes from the two MCUs' clock-sync fits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClockMap {
    /// The MCU's clock at print time 0 (ticks; may be negative).
    pub offset: f64,
    /// The MCU's ticks per print second.
    pub freq: f64,
}

impl ClockMap {
    /// The map of the clock that defines print time: `clock = freq · print_time`.
    pub fn identity(freq: f64) -> ClockMap {
        ClockMap { offset: 0.0, freq }
    }

    /// The MCU's clock at `print_time`.
    pub fn clock(&self, print_time: f64) -> f64 {
        self.offset + self.freq * print_time
    }

    /// The print time at which the MCU's clock reads `clock`.
    pub fn print_time(&self, clock: f64) -> f64 {
        (clock - self.offset) / self.freq
    }

    /// A finite offset within ±2^62 ticks and a frequency ≥ 1 Hz.
    fn validate(&self) -> Result<(), String> {
        if !(self.freq.is_finite() && self.freq >= 1.0) {
            return Err(format!("clock map frequency {} must be ≥ 1", self.freq));
        }
        if !(self.offset.is_finite() && self.offset.abs() < (1u64 << 62) as f64) {
            return Err(format!(
                "clock map offset {} must be within ±2^62 ticks",
                self.offset
            ));
        }
        Ok(())
    }
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

/// How the pipeline runs (everything has a default; [`Pipeline::new`] uses them).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PipelineOptions {
    pub kinematics: Kinematics,
    /// Threads for step generation and compression, the caller's included, with at least one
    /// worker besides it (so 1 and 2 both start one worker; lanes placed by their expected share
    /// of the work, see `lanes::place`); 0 = all on the caller's thread.
    /// With threads, final moves are handed over in batches (see `batch_moves`), so output lags
    /// the input by up to one batch until the toolhead comes to rest.
    pub threads: usize,
    /// With threads: hand moves to the workers once this many are final...
    pub batch_moves: usize,
    /// ... or once they span this much print time (s).
    pub batch_print_time: f64,
    /// Pressure advance of the extruder (stepper axis 3); `None` or advance 0: off.
    pub pressure_advance: Option<PressureAdvance>,
    /// A G-code command the planner does not know is an error naming its line (default), or
    /// (`false`) [`Applied::Unsupported`] for the caller to warn about and skip.
    pub unknown_commands_are_errors: bool,
    /// G10/G11 settings (`[firmware_retraction]`; SET_RETRACTION changes them while printing).
    pub retraction: Retraction,
    /// Arc chord length in mm (`[gcode_arcs] resolution`).
    pub arc_resolution: f64,
    /// `[input_shaper]`: the X/Y shapers (SET_INPUT_SHAPER changes them while printing);
    /// `None`: the printer has no such section (SET_INPUT_SHAPER is an unknown command, as on
    /// Klipper). Cartesian, corexy and corexz only.
    pub input_shaper: Option<InputShaper>,
    /// `[exclude_object]`: the EXCLUDE_OBJECT commands are known and an excluded object's moves
    /// dropped (without it they are unknown commands, as on Klipper).
    pub exclude_object: bool,
    /// How many extruders (`[extruder]`, `[extruder1]`…) the printer has, at least 1.
    pub extruders: usize,
}

impl Default for PipelineOptions {
    fn default() -> Self {
        PipelineOptions {
            kinematics: Kinematics::Cartesian,
            threads: 0,
            batch_moves: 512,
            batch_print_time: 4.0,
            pressure_advance: None,
            unknown_commands_are_errors: true,
            retraction: Retraction::default(),
            arc_resolution: ARC_RESOLUTION,
            input_shaper: None,
            exclude_object: false,
            extruders: 1,
        }
    }
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

/// The main thread's view of one lane: commands not released yet, counters.
#[derive(Debug)]
struct LaneView {
    /// Commands received and not yet released, with their sort keys.
    held: Vec<(u64, StepCmd)>,
    ideal: Vec<IdealStep>,
    position: i64,
    steps: u64,
    queue_steps: u64,
}

impl Default for LaneView {
    /// Room for [`CMDS_CAPACITY`] held commands up front (no growth in steady state).
    fn default() -> Self {
        LaneView {
            held: Vec::with_capacity(CMDS_CAPACITY),
            ideal: Vec::new(),
            position: 0,
            steps: 0,
            queue_steps: 0,
        }
    }
}

/// Where the lanes run.
#[derive(Debug)]
enum Backend {
    Inline(Vec<LaneState>, Vec<LaneOut>),
    /// Worker threads, and the (index, lane)s run on the caller's thread with their output.
    Threads(Workers, Vec<(usize, LaneState)>, LaneOut),
}

/// G-code → step commands.
#[derive(Debug)]
pub struct Pipeline {
    state: GcodeState,
    th: Toolhead,
    backend: Backend,
    views: Vec<LaneView>,
    clock_freq: f64,
    max_err_ticks: u32,
    /// Final moves not handed to the lanes yet.
    moves: Vec<Move>,
    heap: BinaryHeap<Reverse<(u64, usize)>>,
    cursor: Vec<usize>,
    /// Compression horizon reached so far (ticks).
    upto: u64,
    planned_until: f64,
    opts: PipelineOptions,
    next_seq: u64,
    /// Per worker (one for inline): sequence number of the last job answered + 1.
    done: Vec<u64>,
    /// (job sequence, release bound once every lane answered it).
    bounds: VecDeque<(u64, u64)>,
    worker_error: Option<String>,
    /// How long after the toolhead stops step positions still change (pressure advance
    /// smoothing: half its window), s.
    settle: f64,
    /// Pressure advance changes not handed to the lanes yet: (index of the first move they
    /// apply to, counting every final move since the start; advance; smooth_time).
    pa_pending: VecDeque<(u64, LaneEvent)>,
    /// The lane the next pressure advance change is for (`None`: every extruder lane).
    pa_lane: Option<usize>,
    /// Each extruder stepper (in [`Extruders`]' order): its lane, configured step distance
    /// and rotation distance.
    extruder_lanes: Vec<ExtruderLane>,
    /// Each stepper's name, in stepper order.
    names: Vec<String>,
    /// The pressure advance smoothing time in force (s).
    smooth_time: f64,
    /// Final moves handed to the lanes so far.
    dispatched: u64,
    /// Input shaper changes not handed to the lanes yet: (index of the first move they apply
    /// to, counting every final move since the start; settings).
    shaper_pending: VecDeque<(u64, InputShaper)>,
    /// Lanes kept still by [`Self::freeze_lanes`], with the kinematics they get back.
    frozen: Vec<(usize, crate::kinematics::StepperKin)>,
}

impl Pipeline {
    /// A pipeline whose toolhead is at rest at position 0 and whose first move starts at
    /// `start_print_time` (cartesian, single-threaded).
    pub fn new(cfg: PipelineConfig, start_print_time: f64) -> Result<Pipeline, PlanError> {
        Self::with_options(cfg, start_print_time, PipelineOptions::default())
    }

    /// [`Self::new`] with a kinematics and threading choice.
    pub fn with_options(
        cfg: PipelineConfig,
        start_print_time: f64,
        opts: PipelineOptions,
    ) -> Result<Pipeline, PlanError> {
        Self::with_clocks(cfg, start_print_time, opts, &[])
    }

    /// [`Self::with_options`] with each stepper's MCU clock: `clocks[i]` maps print time to
    /// stepper i's clock (empty: every stepper counts `cfg.clock_freq` ticks per print second).
    /// A stepper's commands count ticks at its map's `freq` from here on; later maps
    /// ([`Self::set_clock_map`]) only follow the drift of that MCU's clock.
    pub fn with_clocks(
        cfg: PipelineConfig,
        start_print_time: f64,
        opts: PipelineOptions,
        clocks: &[ClockMap],
    ) -> Result<Pipeline, PlanError> {
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
        if !(opts.batch_print_time.is_finite() && opts.batch_print_time >= 0.0) {
            return Err(bad(format!(
                "batch_print_time {} must be ≥ 0",
                opts.batch_print_time
            )));
        }
        let max_err_ticks = max_err.round() as u32;
        let mut th = Toolhead::new(cfg.toolhead, start_print_time);
        if let Kinematics::Delta(g) = &opts.kinematics {
            g.validate().map_err(bad)?;
            th.set_xy_radius_limit(Some(g.max_xy_radius()));
        }
        // Each extruder stepper's pressure advance: its own, or the options' for the one
        // extruder's stepper.
        let lane_pa = |s: &StepperSpec| match s.extruder {
            Some(link) => Some(link.pressure_advance),
            None => opts.pressure_advance,
        };
        let extruder_pa = || cfg.steppers.iter().filter(|s| s.axis == 3).filter_map(lane_pa);
        let pa = extruder_pa()
            .filter(|p| p.advance > 0.0)
            .max_by(|a, b| a.smooth_time.total_cmp(&b.smooth_time));
        for p in extruder_pa().filter(|p| p.advance > 0.0) {
            p.validate().map_err(bad)?;
        }
        let shaper = opts.input_shaper.unwrap_or_default();
        shaper.validate().map_err(|e| bad(format!("input shaper: {e}")))?;
        if shaper.enabled() && matches!(opts.kinematics, Kinematics::Delta(_)) {
            return Err(bad(
                "input shaping is not supported on delta kinematics (cartesian, corexy, corexz)".into(),
            ));
        }
        if !clocks.is_empty() && clocks.len() != cfg.steppers.len() {
            return Err(bad(format!(
                "{} clock maps for {} steppers",
                clocks.len(),
                cfg.steppers.len()
            )));
        }
        let mut lanes = Vec::with_capacity(cfg.steppers.len());
        for (i, s) in cfg.steppers.iter().enumerate() {
            let map = clocks
                .get(i)
                .copied()
                .unwrap_or(ClockMap::identity(cfg.clock_freq));
            map.validate()
                .map_err(|e| bad(format!("stepper '{}': {e}", s.name)))?;
            let lane_freq = map.freq;
            let lane_err = cfg.max_error_s * lane_freq;
            if !(lane_err.is_finite() && lane_err >= 1.0 && lane_err < (1u64 << 28) as f64) {
                return Err(bad(format!(
                    "stepper '{}': max_error_s {} is {lane_err} ticks of its MCU clock at {lane_freq} Hz: \
                     must be 1 tick .. 2^28 ticks",
                    s.name, cfg.max_error_s
                )));
            }
            if !(s.step_dist.is_finite() && s.step_dist > 1e-9 && s.step_dist < 1e3) {
                return Err(bad(format!(
                    "stepper '{}': step_dist {} must be in (1e-9, 1000) mm",
                    s.name, s.step_dist
                )));
            }
            let kin = opts
                .kinematics
                .stepper(s.axis, s.step_dist)
                .map_err(|e| bad(format!("stepper '{}': {e}", s.name)))?;
            let pa_gen = lane_pa(s)
                .filter(|p| s.axis == 3 && p.advance > 0.0)
                .map(|p| PaGen::new(p, s.step_dist, lane_freq));
            let mut lane = LaneState::new(
                kin,
                StepCompressor::new(s.step_dist, lane_freq, lane_err.round() as u32),
                pa_gen,
            );
            lane.clock = LaneClock::new(map, cfg.clock_freq);
            if let Some(c) = kin.linear_coeffs().filter(|c| shapes(c, &shaper)) {
                if lane.pa.is_none() {
                    lane.shaped = Some(ShapedGen::new(c, &shaper, s.step_dist, lane_freq));
                }
            }
            lane.index = i;
            if s.axis == 3 {
                let smooth = lane_pa(s).map_or(DEFAULT_SMOOTH_TIME, |p| p.smooth_time);
                lane.extruder = Some((smooth, lane_freq));
                lane.queue = s.extruder.map_or(Some(0), |l| l.queue);
            }
            lanes.push(lane);
        }
        let n = lanes.len();
        // Shaped steps start `span` before a motion and settle `span` after it.
        let settle = pa.map_or(0.0, |p| 0.5 * p.smooth_time).max(shaper.span());
        let smooth_time = pa.map_or(DEFAULT_SMOOTH_TIME, |p| p.smooth_time);
        let mut state = GcodeState::new(cfg.home_position);
        state.set_unknown_is_error(opts.unknown_commands_are_errors);
        state.set_retraction(opts.retraction);
        state.set_arc_resolution(opts.arc_resolution);
        state.set_input_shaper(opts.input_shaper);
        state.set_exclude_object(opts.exclude_object);
        state.set_extruders(Extruders::new(
            opts.extruders,
            cfg.steppers
                .iter()
                .filter(|s| s.axis == 3)
                .map(|s| ExtruderStepper {
                    name: s.name.clone(),
                    queue: s.extruder.map_or(Some(0), |l| l.queue),
                    pressure_advance: lane_pa(s)
                        .map_or((0.0, DEFAULT_SMOOTH_TIME), |p| (p.advance, p.smooth_time)),
                    rotation_distance: s.extruder.map_or(0.0, |l| l.rotation_distance),
                })
                .collect(),
        ));
        let (backend, workers) = if opts.threads == 0 || n == 0 {
            let outs = (0..n).map(|_| LaneOut::with_capacity()).collect();
            (Backend::Inline(lanes, outs), 1)
        } else {
            let (groups, local) = place(lanes, opts.threads);
            let w = Workers::spawn(groups).map_err(|e| bad(format!("cannot start planner threads: {e}")))?;
            let c = w.count();
            (Backend::Threads(w, local, LaneOut::with_capacity()), c)
        };
        Ok(Pipeline {
            state,
            th,
            backend,
            views: (0..n).map(|_| LaneView::default()).collect(),
            clock_freq: cfg.clock_freq,
            max_err_ticks,
            moves: Vec::with_capacity(1024),
            heap: BinaryHeap::with_capacity(n),
            cursor: vec![0; n],
            upto: 0,
            planned_until: start_print_time,
            opts,
            next_seq: 0,
            done: vec![0; workers],
            bounds: VecDeque::new(),
            worker_error: None,
            settle,
            pa_pending: VecDeque::new(),
            pa_lane: None,
            names: cfg.steppers.iter().map(|s| s.name.clone()).collect(),
            extruder_lanes: cfg
                .steppers
                .iter()
                .enumerate()
                .filter(|(_, s)| s.axis == 3)
                .map(|(i, s)| ExtruderLane(i, s.step_dist, s.extruder.map_or(0.0, |l| l.rotation_distance)))
                .collect(),
            smooth_time,
            dispatched: 0,
            shaper_pending: VecDeque::new(),
            frozen: Vec::new(),
        })
    }

    /// Applies one G-code line to the toolhead. A new pressure advance applies from the next
    /// move on (the moves queued before keep the old one).
    pub fn apply(&mut self, line: &GcodeLine) -> Result<Applied, PlanError> {
        let shaper_before = self.state.input_shaper();
        let applied = self.state.apply(line, &mut self.th)?;
        if self.state.input_shaper() != shaper_before {
            self.change_shaper(line.line_no, shaper_before)?;
        }
        let applied = match applied {
            Applied::Extruder { event, said } => self.extruder_event(event, said)?,
            other => other,
        };
        if let Applied::PressureAdvance { advance, smooth_time } = applied {
            if smooth_time != self.smooth_time {
                // The extruder's position at t depends on the moves within half the window
                // around t: a new window is only exact from rest. Stop the toolhead, and wait
                // until the old window's tail and the new window's lead cannot overlap.
                self.th.flush();
                let gap =
                    0.5 * (self.smooth_time + smooth_time) + self.max_err_ticks as f64 / self.clock_freq;
                let _ = self.th.dwell(gap);
                self.smooth_time = smooth_time;
                self.settle = self.settle.max(0.5 * smooth_time);
            }
            // Every move queued so far comes before the change: those handed out, those taken
            // from the toolhead and those still in its lookahead.
            self.th.take_moves(&mut self.moves);
            let at = self.dispatched + self.moves.len() as u64 + self.th.queued_moves() as u64;
            self.pa_pending
                .push_back((at, LaneEvent::Advance(self.pa_lane.take(), advance, smooth_time)));
            if advance > 0.0 {
                self.settle = self.settle.max(0.5 * smooth_time);
            }
        }
        Ok(applied)
    }

    /// An extruder command's change, handed to the lanes from the next move on; what the
    /// caller sees (Klipper's answer, or the pressure advance to apply).
    fn extruder_event(&mut self, event: ExtruderEvent, said: CommandText) -> Result<Applied, PlanError> {
        let lane_of = |stepper: usize, views: &[ExtruderLane]| views.get(stepper).map(|v| v.0);
        let lane = match event {
            ExtruderEvent::Activate(q) => Some(LaneEvent::Active(q)),
            ExtruderEvent::Sync { stepper, queue } => {
                lane_of(stepper, &self.extruder_lanes).map(|l| LaneEvent::Follow(l, queue))
            }
            ExtruderEvent::Advance {
                stepper,
                advance,
                smooth_time,
            } => {
                // Through the pressure advance path (smooth time changes stop the toolhead).
                self.pa_lane = lane_of(stepper, &self.extruder_lanes);
                return Ok(Applied::PressureAdvance { advance, smooth_time });
            }
            ExtruderEvent::RotationDistance { stepper, distance } => {
                let Some(&ExtruderLane(l, step_dist, rotation)) = self.extruder_lanes.get(stepper) else {
                    return Ok(Applied::Report(said));
                };
                if rotation <= 0.0 {
                    return Err(PlanError {
                        line: 0,
                        kind: PlanErrorKind::BadParameter(
                            "SET_EXTRUDER_ROTATION_DISTANCE: this stepper's rotation_distance is not known"
                                .into(),
                        ),
                    });
                }
                Some(LaneEvent::StepDist(
                    l,
                    step_dist * distance.abs() / rotation,
                    distance < 0.0,
                ))
            }
        };
        if let Some(ev) = lane {
            self.th.take_moves(&mut self.moves);
            let at = self.dispatched + self.moves.len() as u64 + self.th.queued_moves() as u64;
            self.pa_pending.push_back((at, ev));
        }
        Ok(Applied::Report(said))
    }

    /// SET_INPUT_SHAPER changed the settings (they were `before`): the toolhead comes to rest
    /// and waits until the old shaping's tail and the new shaping's lead cannot overlap (as
    /// Klipper flushes step generation first); the lanes switch at the next move.
    fn change_shaper(&mut self, line: usize, before: Option<InputShaper>) -> Result<(), PlanError> {
        let Some(new) = self.state.input_shaper() else {
            return Ok(());
        };
        if new.enabled() && matches!(self.opts.kinematics, Kinematics::Delta(_)) {
            self.state.set_input_shaper(before);
            return Err(PlanError {
                line,
                kind: PlanErrorKind::BadParameter(
                    "SET_INPUT_SHAPER: input shaping is not supported on delta kinematics".into(),
                ),
            });
        }
        let old_span = before.map_or(0.0, |s| s.span());
        self.th.flush();
        let gap = old_span + new.span() + self.max_err_ticks as f64 / self.clock_freq;
        let _ = self.th.dwell(gap);
        self.settle = self.settle.max(new.span());
        self.th.take_moves(&mut self.moves);
        let at = self.dispatched + self.moves.len() as u64 + self.th.queued_moves() as u64;
        self.shaper_pending.push_back((at, new));
        Ok(())
    }

    /// Ends the lookahead (the toolhead comes to rest after the last queued move), as M400
    /// does; for an idle G-code source.
    pub fn flush_lookahead(&mut self) {
        self.th.flush();
    }

    /// Appends the step commands that can no longer change, in clock order.
    pub fn generate(&mut self, out: &mut Vec<(usize, StepCmd)>) {
        let before = self.moves.len();
        self.th.take_moves(&mut self.moves);
        let idle = self.th.queued_moves() == 0;
        let threaded = matches!(self.backend, Backend::Threads(..));
        if self.moves.is_empty() || (before == self.moves.len() && !idle) {
            // Nothing new: everything earlier was released already, or waits for more moves.
            self.collect(false, out);
            return;
        }
        let end = self.th.print_time();
        if threaded && !idle {
            let first = self.moves.first().map_or(end, |m| m.print_time);
            if self.moves.len() < self.opts.batch_moves && end - first < self.opts.batch_print_time {
                self.collect(false, out);
                return;
            }
        }
        let horizon = if idle {
            (end + self.settle) * self.clock_freq + 1.0
        } else {
            (end - COMPRESS_LOOKAHEAD_S) * self.clock_freq
        };
        let upto = if horizon > 0.0 { horizon as u64 } else { 0 };
        self.upto = self.upto.max(upto);
        if idle {
            self.dispatch(false, true, 0);
            self.collect(true, out);
            self.release(u64::MAX, out);
            // Later steps may be up to max_error early, and the steps up to `settle` after the
            // stop are final now while pressure advance moves the extruder up to `settle` before
            // the next move: start it that much later.
            let _ = self
                .th
                .dwell(2.0 * self.settle + self.max_err_ticks as f64 / self.clock_freq);
            self.planned_until = end + self.settle;
        } else {
            let bound = self.upto.saturating_sub(self.max_err_ticks as u64);
            self.dispatch(false, false, bound);
            self.collect(false, out);
        }
    }

    /// Flushes everything (end of the file): the toolhead stops after the last move.
    pub fn finish(&mut self, out: &mut Vec<(usize, StepCmd)>) {
        self.th.flush();
        self.th.take_moves(&mut self.moves);
        self.dispatch(true, true, 0);
        self.collect(true, out);
        self.release(u64::MAX, out);
        self.planned_until = self.planned_until.max(self.th.print_time() + self.settle);
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
        self.views.iter().map(|l| l.position).collect()
    }

    /// Counters so far.
    pub fn stats(&self) -> PipelineStats {
        let steps: Vec<u64> = self.views.iter().map(|l| l.steps).collect();
        let qs: Vec<u64> = self.views.iter().map(|l| l.queue_steps).collect();
        PipelineStats {
            moves: self.th.moves_total(),
            queue_steps: qs.iter().sum(),
            steps,
            queue_steps_per_stepper: qs,
            print_time_end: self.th.print_time(),
        }
    }

    /// A worker thread that stopped answering (its steps are missing from the output).
    pub fn worker_error(&self) -> Option<&str> {
        self.worker_error.as_deref()
    }

    /// Compression lookahead of every stepper (see [`StepCompressor::set_lookahead_backoff`]):
    /// 0 is fastest, the default gives the fewest commands.
    pub fn set_lookahead_backoff(&mut self, steps: usize) {
        match &mut self.backend {
            Backend::Inline(lanes, _) => lanes.iter_mut().for_each(|l| l.comp.set_lookahead_backoff(steps)),
            Backend::Threads(w, local, _) => {
                local
                    .iter_mut()
                    .for_each(|(_, l)| l.comp.set_lookahead_backoff(steps));
                if !w.broadcast(|| Msg::Backoff(steps)) {
                    self.worker_error = Some("a planner thread stopped".into());
                }
            }
        }
    }

    /// Whether every stepper's commands in a cruise line come from the line's formula (default)
    /// or from the per-step search (see [`StepCompressor::set_line_fit`]).
    pub fn set_line_fit(&mut self, on: bool) {
        match &mut self.backend {
            Backend::Inline(lanes, _) => lanes.iter_mut().for_each(|l| l.comp.set_line_fit(on)),
            Backend::Threads(w, local, _) => {
                local.iter_mut().for_each(|(_, l)| l.comp.set_line_fit(on));
                if !w.broadcast(|| Msg::LineFit(on)) {
                    self.worker_error = Some("a planner thread stopped".into());
                }
            }
        }
    }

    /// How every stepper's commands off the cruise lines are found (see
    /// [`crate::compress::SearchTuning`]; [`SearchTuning::SEARCH`](crate::compress::SearchTuning::SEARCH)
    /// is the per-step search the per-command design is measured against).
    pub fn set_tuning(&mut self, tuning: crate::compress::SearchTuning) {
        match &mut self.backend {
            Backend::Inline(lanes, _) => lanes.iter_mut().for_each(|l| l.comp.set_tuning(tuning)),
            Backend::Threads(w, local, _) => {
                local.iter_mut().for_each(|(_, l)| l.comp.set_tuning(tuning));
                if !w.broadcast(|| Msg::Tuning(tuning)) {
                    self.worker_error = Some("a planner thread stopped".into());
                }
            }
        }
    }

    /// Stepper `idx`'s MCU clock from the next batch of moves on (its clock-sync estimate was
    /// refreshed): only the map changes, the stepper keeps counting ticks at the rate it was
    /// made with (the moves are carried into its clock exactly, see `lanes`). Steps already
    /// generated keep their clocks; a step the new map would put before an earlier one is
    /// raised to it (time order holds).
    pub fn set_clock_map(&mut self, idx: usize, map: ClockMap) -> Result<(), PlanError> {
        let bad = |msg: String| PlanError {
            line: 0,
            kind: PlanErrorKind::Config(msg),
        };
        map.validate().map_err(|e| bad(format!("stepper {idx}: {e}")))?;
        if idx >= self.views.len() {
            return Err(bad(format!("clock map for unknown stepper index {idx}")));
        }
        match &mut self.backend {
            Backend::Inline(lanes, _) => {
                if let Some(l) = lanes.get_mut(idx) {
                    l.clock.map = map;
                }
            }
            Backend::Threads(w, local, _) => {
                if let Some((_, l)) = local.iter_mut().find(|(i, _)| *i == idx) {
                    l.clock.map = map;
                }
                if !w.broadcast(|| Msg::ClockMap(idx, map)) {
                    self.worker_error = Some("a planner thread stopped".into());
                }
            }
        }
        Ok(())
    }

    /// Maximum step error in ticks.
    pub fn max_error_ticks(&self) -> u32 {
        self.max_err_ticks
    }

    /// Modal G-code state (read-only).
    pub fn gcode_state(&self) -> &GcodeState {
        &self.state
    }

    /// Unknown G-code commands become errors naming the line (`true`, the default of
    /// [`PipelineOptions`]) instead of [`Applied::Unsupported`] (for callers that warn).
    pub fn set_unknown_commands_are_errors(&mut self, on: bool) {
        self.state.set_unknown_is_error(on);
    }

    /// Declares axes homed without G28 (printers without endstops, tests).
    pub fn set_homed(&mut self, homed: [bool; 3]) {
        self.state.set_homed(homed);
    }

    /// Records every generated step's ideal time, per stepper, for [`Self::take_ideal`].
    pub fn set_record_ideal(&mut self, on: bool) {
        match &mut self.backend {
            Backend::Inline(lanes, _) => lanes.iter_mut().for_each(|l| l.comp.set_record_ideal(on)),
            Backend::Threads(w, local, _) => {
                local.iter_mut().for_each(|(_, l)| l.comp.set_record_ideal(on));
                if !w.broadcast(|| Msg::RecordIdeal(on)) {
                    self.worker_error = Some("a planner thread stopped".into());
                }
            }
        }
    }

    /// Ideal steps generated for stepper `idx` whose commands were received since the last
    /// call (empty for a bad index).
    pub fn take_ideal(&mut self, idx: usize) -> Vec<IdealStep> {
        self.views
            .get_mut(idx)
            .map(|l| std::mem::take(&mut l.ideal))
            .unwrap_or_default()
    }

    /// Hands the final moves to every lane as one job whose commands may be released below
    /// `bound` once every lane has answered it (`all`: compress every pending step).
    fn dispatch(&mut self, all: bool, rest: bool, bound: u64) {
        let seq = self.next_seq;
        self.next_seq += 1;
        self.bounds.push_back((seq, bound));
        let upto = self.upto;
        // The pressure advance changes whose first move is in this job (all at the end).
        let end = self.dispatched + self.moves.len() as u64;
        let mut pa: Vec<PaChange> = Vec::new();
        while let Some(&(at, ev)) = self.pa_pending.front() {
            if at >= end && !all {
                break;
            }
            pa.push((at.saturating_sub(self.dispatched) as usize, ev));
            self.pa_pending.pop_front();
        }
        let mut shaper: Vec<ShaperChange> = Vec::new();
        while let Some(&(at, settings)) = self.shaper_pending.front() {
            if at >= end && !all {
                break;
            }
            shaper.push((at.saturating_sub(self.dispatched) as usize, settings));
            self.shaper_pending.pop_front();
        }
        self.dispatched = end;
        match &mut self.backend {
            Backend::Inline(lanes, outs) => {
                for (i, (lane, o)) in lanes.iter_mut().zip(outs.iter_mut()).enumerate() {
                    lane.run(&self.moves, &pa, &shaper, upto, all, rest, o);
                    absorb(&mut self.views[i], o);
                }
                self.done[0] = seq + 1;
            }
            Backend::Threads(w, local, o) => {
                let moves: Arc<[Move]> = Arc::from(self.moves.as_slice());
                let pa: Arc<[PaChange]> = Arc::from(pa);
                let shaper: Arc<[ShaperChange]> = Arc::from(shaper);
                if !w.broadcast(|| Msg::Job {
                    seq,
                    moves: moves.clone(),
                    pa: pa.clone(),
                    shaper: shaper.clone(),
                    upto,
                    all,
                    rest,
                }) {
                    self.worker_error = Some("a planner thread stopped".into());
                }
                // The caller's own lanes, while the workers run theirs.
                for (i, lane) in local.iter_mut() {
                    lane.run(&moves, &pa, &shaper, upto, all, rest, o);
                    absorb(&mut self.views[*i], o);
                }
            }
        }
        self.moves.clear();
    }

    /// Takes in the workers' answers (`wait`: until every job sent is answered) and releases
    /// the commands every lane is past.
    fn collect(&mut self, wait: bool, out: &mut Vec<(usize, StepCmd)>) {
        if let Backend::Threads(w, ..) = &self.backend {
            loop {
                let all_done = self.done.iter().all(|&d| d == self.next_seq);
                let reply = if wait && !all_done && self.worker_error.is_none() {
                    w.replies.recv().ok()
                } else {
                    w.replies.try_recv().ok()
                };
                let Some(r) = reply else {
                    if wait && !all_done && self.worker_error.is_none() {
                        self.worker_error = Some("a planner thread stopped".into());
                    }
                    break;
                };
                for (i, mut o) in r.lanes {
                    if let Some(v) = self.views.get_mut(i) {
                        absorb(v, &mut o);
                    }
                }
                if let Some(d) = self.done.get_mut(r.worker) {
                    *d = r.seq + 1;
                }
            }
        }
        let answered = self.done.iter().copied().min().unwrap_or(0);
        // The last job every lane answered decides the bound.
        let mut bound = None;
        while let Some(&(seq, b)) = self.bounds.front() {
            if seq >= answered {
                break;
            }
            bound = Some(b);
            self.bounds.pop_front();
        }
        if let Some(b) = bound {
            if b > 0 {
                self.release(b, out);
                self.planned_until = self.planned_until.max(b as f64 / self.clock_freq);
            }
        }
    }

    /// Moves every held command with key < `bound` to `out`, merged by key (ties by stepper).
    /// (Tried and not kept: a scan of the lanes' heads for the first and the runner-up, the
    /// first lane then giving out its commands while they sort before the runner-up's: 85 M
    /// instructions on the benchy where this heap takes 76 M, the runs being short.)
    fn release(&mut self, bound: u64, out: &mut Vec<(usize, StepCmd)>) {
        self.heap.clear();
        for (i, lane) in self.views.iter().enumerate() {
            self.cursor[i] = 0;
            if let Some(&(key, _)) = lane.held.first() {
                if key < bound || bound == u64::MAX {
                    self.heap.push(Reverse((key, i)));
                }
            }
        }
        while let Some(Reverse((_, i))) = self.heap.pop() {
            let lane = &self.views[i];
            let pos = self.cursor[i];
            out.push((i, lane.held[pos].1));
            self.cursor[i] = pos + 1;
            if let Some(&(key, _)) = lane.held.get(pos + 1) {
                if key < bound || bound == u64::MAX {
                    self.heap.push(Reverse((key, i)));
                }
            }
        }
        for (i, lane) in self.views.iter_mut().enumerate() {
            lane.held.drain(..self.cursor[i]);
        }
    }
}

/// Moves a lane's output into its view.
fn absorb(v: &mut LaneView, o: &mut LaneOut) {
    v.held.append(&mut o.cmds);
    v.ideal.append(&mut o.ideal);
    v.position = o.position;
    v.steps = o.steps;
    v.queue_steps = o.queue_steps;
}

#[cfg(test)]
mod tests;
