//! The per-stepper step paths ("lanes") and where they run: inline on the caller's thread, or
//! spread over worker threads fed by a bounded queue of jobs, the caller's thread running some
//! lanes too (see [`place`]: balanced by each lane's expected share of the work).
//!
//! A job is a batch of final moves, shared by every lane, plus the compression horizon; each
//! lane generates the batch's steps, compresses those before the horizon and returns the
//! commands with their sort keys (a `queue_step`'s first clock; `reset_step_clock` and
//! `set_next_step_dir` take the key of the `queue_step` they precede, which the compressor emits
//! in the same batch). Replies carry the job's sequence number so the merger knows how far every
//! lane has got. Lanes are independent: the threads share nothing but the moves (read-only).
//!
//! A lane on another MCU than the main one ([`LaneClock`]): its compressor counts ticks at
//! the rate `f₀` its clock map had when the lane was made, and its map `c(t) = a + b·t` may
//! change between batches (clock drift). Each move is carried into that clock before its steps
//! are generated: with `k = b / f₀`, the move starting at print time `t₀` becomes the move
//! starting at `c(t₀) / f₀` with its phase durations × k, speeds ÷ k and acceleration ÷ k²
//! (the same distances), so a step at `t₀ + τ` on the original lands at clock
//! `f₀ · (c(t₀)/f₀ + k·τ) = c(t₀ + τ)`: exact for the whole batch. The horizon goes the same
//! way (print ticks → its clock), command keys the other way (its clock → print ticks).

use std::sync::mpsc::{channel, sync_channel, Receiver, Sender, SyncSender};
use std::sync::Arc;
use std::thread::JoinHandle;

use super::ClockMap;
use crate::compress::{CompressorSink, StepCompressor};
use crate::kinematics::StepperKin;
use crate::pressure_advance::{PaGen, PressureAdvance};
use crate::shaped::{shapes, ShapedGen};
use crate::shaper::InputShaper;
use crate::stepgen::{IdealStep, StepCmd};
use crate::toolhead::Move;

/// Jobs queued per worker before the producer waits.
const JOB_QUEUE: usize = 4;
/// Commands a lane's output (and the merger's view of it) holds before growing: reserved up
/// front so the planner thread does not allocate in steady state (a job yields well under this
/// on the reference printers).
pub(crate) const CMDS_CAPACITY: usize = 4096;

/// A lane's MCU clock against print time (see the module doc).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct LaneClock {
    /// Ticks per second the compressor counts in (the map's `freq` when the lane was made).
    pub freq: f64,
    /// The print clock's ticks per print second (horizon and keys are in those ticks).
    pub print_freq: f64,
    /// Print time → this lane's MCU clock, now.
    pub map: ClockMap,
}

impl LaneClock {
    /// A lane whose clock is `map` now, in a pipeline counting print time at `print_freq`.
    pub fn new(map: ClockMap, print_freq: f64) -> LaneClock {
        LaneClock {
            freq: map.freq,
            print_freq,
            map,
        }
    }

    /// The lane counts print ticks (the main MCU's): nothing to convert.
    fn is_print_clock(&self) -> bool {
        self.map.offset == 0.0 && self.map.freq == self.freq && self.freq == self.print_freq
    }

    /// `mv` carried into this clock: steps generated at `freq` from it land at `map`'s clocks.
    fn carry(&self, mv: &Move) -> Move {
        let k = self.map.freq / self.freq;
        let mut m = *mv;
        m.print_time = self.map.clock(mv.print_time) / self.freq;
        if k != 1.0 {
            m.accel_t *= k;
            m.cruise_t *= k;
            m.decel_t *= k;
            m.start_v /= k;
            m.cruise_v /= k;
            m.end_v /= k;
            m.accel /= k * k;
        }
        m
    }

    /// A horizon in print ticks as this lane's clock (`u64::MAX` stays).
    fn lane_clock_of(&self, print_ticks: u64) -> u64 {
        if print_ticks == u64::MAX {
            return u64::MAX;
        }
        let c = self.map.clock(print_ticks as f64 / self.print_freq);
        if c > 0.0 {
            c as u64
        } else {
            0
        }
    }

    /// A clock of this lane as print ticks (for the merge order).
    fn print_ticks_of(&self, clock: u64) -> u64 {
        let t = self.map.print_time(clock as f64) * self.print_freq;
        if t > 0.0 {
            t as u64
        } else {
            0
        }
    }
}

/// One stepper's step generation and compression.
#[derive(Debug)]
pub(crate) struct LaneState {
    pub kin: StepperKin,
    pub comp: StepCompressor,
    /// The extruder's generator when pressure advance is on.
    pub pa: Option<PaGen>,
    /// The generator of a stepper that follows a shaped axis (X or Y with `[input_shaper]`).
    pub shaped: Option<ShapedGen>,
    /// For the extruder's lane: (smooth_time, clock_freq) to start pressure advance with when
    /// SET_PRESSURE_ADVANCE turns it on during the print.
    pub extruder: Option<(f64, f64)>,
    /// This stepper's MCU clock (the print clock unless its MCU is another one).
    pub clock: LaneClock,
    /// This lane's stepper index (the one [`LaneEvent`]s name).
    pub index: usize,
    /// For an extruder lane: the extruder whose motion it follows (`None`: it stands still).
    pub queue: Option<usize>,
    /// The active extruder (whose motion the toolhead's E moves are).
    active: usize,
    /// The E position this lane last followed (toolhead coordinates of its extruder): it
    /// holds it while its extruder is not active.
    held_e: f64,
    fresh: Vec<StepCmd>,
}

/// A change to extruder lanes from move `at` of a job on: (at, change).
pub(crate) type PaChange = (usize, LaneEvent);

/// What changes in extruder lanes between two moves (see [`crate::extruders`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum LaneEvent {
    /// A new pressure advance (advance, smooth_time) for lane `Some(i)`, or every extruder
    /// lane (`None`).
    Advance(Option<usize>, f64, f64),
    /// Extruder `.0` is the active one: the toolhead's E moves go to its motion.
    Active(usize),
    /// Lane `.0` follows extruder `.1`'s motion (or none).
    Follow(usize, Option<usize>),
    /// Lane `.0`'s step distance (mm) and whether its direction is inverted against the
    /// config (the toolhead is at rest).
    StepDist(usize, f64, bool),
    /// FORCE_MOVE of lane `.0`: from print time `.1`, distance `.2` mm at velocity `.3` with
    /// acceleration `.4` (see [`crate::force_move`]; the toolhead is at rest meanwhile).
    ForceMove(usize, f64, f64, f64, f64),
}

/// New input shaper settings from move `at` of a job on, the toolhead at rest before it:
/// (at, settings).
pub(crate) type ShaperChange = (usize, InputShaper);

/// What a lane produced for one job.
#[derive(Debug, Default)]
pub(crate) struct LaneOut {
    pub cmds: Vec<(u64, StepCmd)>,
    pub ideal: Vec<IdealStep>,
    pub position: i64,
    pub steps: u64,
    pub queue_steps: u64,
}

impl LaneOut {
    /// An output with room for [`CMDS_CAPACITY`] commands (reused job after job inline).
    pub fn with_capacity() -> LaneOut {
        LaneOut {
            cmds: Vec::with_capacity(CMDS_CAPACITY),
            ..LaneOut::default()
        }
    }
}

impl LaneState {
    /// A lane counting print ticks at 1 Hz until its `clock` is set.
    pub fn new(kin: StepperKin, comp: StepCompressor, pa: Option<PaGen>) -> LaneState {
        LaneState {
            kin,
            comp,
            pa,
            shaped: None,
            extruder: None,
            clock: LaneClock::new(ClockMap::identity(1.0), 1.0),
            index: 0,
            queue: None,
            active: 0,
            held_e: 0.0,
            fresh: Vec::with_capacity(1024),
        }
    }

    /// Pressure advance `advance` with `smooth_time` for the moves from now on (extruder lane
    /// only). Turning it on hands step generation to the iterative generator, which starts at
    /// the commanded position; advance 0 keeps that generator (it then follows E exactly). A
    /// new smooth_time comes with the toolhead at rest (the pipeline stops it first): the
    /// generator finishes the old window's steps and a new one starts at the next move.
    fn set_advance(&mut self, advance: f64, smooth_time: f64) {
        let Some((current, clock_freq)) = self.extruder else {
            return;
        };
        let pa = PressureAdvance { advance, smooth_time };
        if pa.validate().is_err() {
            return;
        }
        if smooth_time != current {
            self.extruder = Some((smooth_time, clock_freq));
            if let Some(mut old) = self.pa.take() {
                let comp = &mut self.comp;
                old.generate(true, |clock, dir| comp.push_step(clock, dir));
                self.pa = Some(PaGen::new(pa, self.comp.step_dist(), clock_freq));
                return;
            }
        }
        match &mut self.pa {
            Some(g) => g.set_advance(advance),
            None if advance > 0.0 => {
                self.pa = Some(PaGen::new(pa, self.comp.step_dist(), clock_freq));
            }
            None => {}
        }
    }

    /// An extruder change for the moves from now on (lanes it does not name ignore it).
    fn event(&mut self, ev: LaneEvent) {
        match ev {
            LaneEvent::Advance(lane, advance, smooth) if lane.is_none_or(|l| l == self.index) => {
                self.set_advance(advance, smooth)
            }
            LaneEvent::Active(q) => self.active = q,
            LaneEvent::Follow(lane, q) if lane == self.index => self.queue = q,
            LaneEvent::StepDist(lane, step_dist, inverted) if lane == self.index => {
                self.set_step_dist(step_dist, inverted)
            }
            LaneEvent::ForceMove(lane, t0, distance, velocity, accel) if lane == self.index => {
                self.force_move(t0, distance, velocity, accel)
            }
            _ => {}
        }
    }

    /// FORCE_MOVE: the generators finish what they hold, then the stepper alone moves
    /// `distance` from where it is (its commanded position is left as it was).
    fn force_move(&mut self, t0: f64, distance: f64, velocity: f64, accel: f64) {
        let comp = &mut self.comp;
        if let Some(g) = &mut self.pa {
            g.generate(true, |clock, dir| comp.push_step(clock, dir));
        }
        if let Some(g) = &mut self.shaped {
            g.generate(true, CompressorSink(comp));
        }
        let from = self.comp.commanded_position();
        let mv = crate::force_move::forced_move(t0, from, distance, velocity, accel);
        let mv = match self.clock.is_print_clock() {
            true => mv,
            false => self.clock.carry(&mv),
        };
        self.comp
            .push_move(&mv, &StepperKin::axis(0, self.comp.step_dist()));
    }

    /// An extruder lane's view of `mv`: as it is while the lane follows the active extruder,
    /// else with E standing still at the position the lane last followed.
    fn follow(&mut self, mv: &Move) -> Move {
        let mut m = *mv;
        if self.queue == Some(self.active) {
            self.held_e = mv.end_pos[3];
        } else {
            m.start_pos[3] = self.held_e;
            m.end_pos[3] = self.held_e;
            m.axes_r[3] = 0.0;
        }
        m
    }

    /// A new step distance (the toolhead is at rest): the generators keep the stepper where
    /// it is and count steps of the new size from there; `inverted` turns its direction.
    fn set_step_dist(&mut self, step_dist: f64, inverted: bool) {
        if !(step_dist.is_finite() && step_dist > 1e-9) {
            return;
        }
        let sign = if inverted { -1.0 } else { 1.0 };
        self.kin = StepperKin::axis(3, step_dist);
        if let crate::kinematics::StepperMap::Linear(c) = &mut self.kin.map {
            c[3] = sign;
        }
        let comp = &mut self.comp;
        if let Some(g) = &mut self.pa {
            g.generate(true, |clock, dir| comp.push_step(clock, dir));
            g.set_step_dist(step_dist, sign);
        }
        self.comp.set_step_dist(step_dist);
    }

    /// Input shaper settings for the moves from now on (the toolhead is at rest): the shaped
    /// generator finishes the old shaping's steps and goes on with the new one; a stepper not
    /// shaped so far gets one when the new settings shape its axes (it starts at the commanded
    /// position, like the plain generator re-anchoring).
    pub fn set_shaper(&mut self, shaper: &InputShaper) {
        let comp = &mut self.comp;
        match &mut self.shaped {
            Some(g) => {
                g.generate(true, CompressorSink(comp));
                g.set_shaper(shaper);
            }
            None => {
                if let Some(c) = self.kin.linear_coeffs().filter(|c| shapes(c, shaper)) {
                    if self.pa.is_none() {
                        self.shaped = Some(ShapedGen::new(c, shaper, comp.step_dist(), self.clock.freq));
                    }
                }
            }
        }
    }

    /// Generates and compresses one batch; appends keyed commands to `out.cmds`. `rest`: the
    /// toolhead stops after these moves (steps that depend on later times can be generated).
    /// `pa`: pressure advance changes (move index in `moves`, advance), in order; `shaper`:
    /// input shaper changes, in order.
    #[allow(clippy::too_many_arguments)]
    pub fn run(
        &mut self,
        moves: &[Move],
        pa: &[PaChange],
        shaper: &[ShaperChange],
        upto: u64,
        all: bool,
        rest: bool,
        out: &mut LaneOut,
    ) {
        let mut changes = pa.iter().peekable();
        let mut shaper_changes = shaper.iter().peekable();
        let print_clock = self.clock.is_print_clock();
        for (i, mv) in moves.iter().enumerate() {
            while let Some(&(_, ev)) = changes.next_if(|c| c.0 <= i) {
                self.event(ev);
            }
            while let Some((_, s)) = shaper_changes.next_if(|c| c.0 <= i) {
                self.set_shaper(s);
            }
            let held;
            let mv = match self.extruder.is_some() {
                true => {
                    held = self.follow(mv);
                    &held
                }
                false => mv,
            };
            let carried;
            let mv = if print_clock {
                mv
            } else {
                carried = self.clock.carry(mv);
                &carried
            };
            match (&mut self.pa, &mut self.shaped) {
                (Some(pa), _) => pa.push_move(mv),
                (None, Some(g)) => g.push_move(mv),
                (None, None) => self.comp.push_move(mv, &self.kin),
            }
        }
        for &(_, ev) in changes {
            self.event(ev);
        }
        for (_, s) in shaper_changes {
            self.set_shaper(s);
        }
        if let Some(pa) = &mut self.pa {
            let comp = &mut self.comp;
            pa.generate(all || rest, |clock, dir| comp.push_step(clock, dir));
        }
        if let Some(g) = &mut self.shaped {
            g.generate(all || rest, CompressorSink(&mut self.comp));
        }
        self.fresh.clear();
        if all {
            self.comp.finish(&mut self.fresh);
        } else if print_clock {
            self.comp.flush(upto, &mut self.fresh);
        } else {
            self.comp.flush(self.clock.lane_clock_of(upto), &mut self.fresh);
        }
        let start = out.cmds.len();
        out.cmds.extend(self.fresh.iter().map(|&c| (u64::MAX, c)));
        let mut key = u64::MAX;
        for h in out.cmds[start..].iter_mut().rev() {
            if let StepCmd::QueueStep { first_clock, .. } = h.1 {
                key = if print_clock {
                    first_clock
                } else {
                    self.clock.print_ticks_of(first_clock)
                };
            }
            h.0 = key;
        }
        out.ideal.extend(self.comp.take_ideal());
        out.position = self.comp.position_steps();
        out.steps = self.comp.step_count();
        out.queue_steps = self.comp.queue_step_count();
    }
}

/// A message to a worker.
#[derive(Debug)]
pub(crate) enum Msg {
    Job {
        seq: u64,
        moves: Arc<[Move]>,
        pa: Arc<[PaChange]>,
        shaper: Arc<[ShaperChange]>,
        upto: u64,
        all: bool,
        rest: bool,
    },
    Backoff(usize),
    /// Commands in cruise lines from the line's formula (see `StepCompressor::set_line_fit`).
    LineFit(bool),
    /// How commands off the lines are found (see `StepCompressor::set_tuning`).
    Tuning(crate::compress::SearchTuning),
    RecordIdeal(bool),
    /// A new clock map for the lane of this stepper index.
    ClockMap(usize, ClockMap),
}

/// A worker's answer to one job: (lane index, output) for each of its lanes.
#[derive(Debug)]
pub(crate) struct Reply {
    pub worker: usize,
    pub seq: u64,
    pub lanes: Vec<(usize, LaneOut)>,
}

/// Weight of the caller's own work (parsing, planning, merging) against a lane that follows X
/// or Y (benchy, cartesian: 0.06 s against 0.125 s for X and for Y).
const CALLER_WEIGHT: f64 = 0.5;

/// A lane's expected share of the work: 1 when its stepper follows X or Y (or is not linear),
/// 0.2 for the extruder, 0.05 for one that follows Z alone (benchy, cartesian: X and Y 0.125 s
/// each, the extruder 0.025 s, Z 0.003 s).
fn weight(l: &LaneState) -> f64 {
    match l.kin.linear_coeffs() {
        Some(c) if c[0] == 0.0 && c[1] == 0.0 => {
            if c[3] != 0.0 {
                0.2
            } else {
                0.05
            }
        }
        _ => 1.0,
    }
}

/// Which lanes run on which worker, and which on the caller's thread (returned apart), for
/// `threads` threads running lanes, the caller's included, with at least one worker: so two
/// threads on two cores are two busy threads, one a core. (With a worker per thread besides the
/// caller, three busy threads on two cores, the scheduler runs two of them on one core: benchy
/// wall 0.19–0.21 s by which two, for 0.33 s of CPU.) The heaviest lane first goes to the
/// least loaded thread, the caller starting at [`CALLER_WEIGHT`]: benchy cartesian with two
/// threads, X, Z and the extruder on the worker and Y on the caller (perf: 0.18 s and 0.19 s of
/// CPU, wall 0.17–0.19 s). Tried and not kept: a worker each for X and Y, Z and the extruder on
/// the caller (0.125, 0.125 and 0.09 s: three busy threads again, wall 0.21 s).
#[allow(clippy::type_complexity)]
pub(crate) fn place(
    lanes: Vec<LaneState>,
    threads: usize,
) -> (Vec<Vec<(usize, LaneState)>>, Vec<(usize, LaneState)>) {
    let workers = threads.saturating_sub(1).clamp(1, lanes.len().max(1));
    let mut order: Vec<(usize, f64, LaneState)> = lanes
        .into_iter()
        .enumerate()
        .map(|(i, l)| (i, weight(&l), l))
        .collect();
    // Heaviest first; equal weights in stepper order.
    order.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    let mut load = vec![0.0; workers];
    let mut caller_load = CALLER_WEIGHT;
    let mut groups: Vec<Vec<(usize, LaneState)>> = (0..workers).map(|_| Vec::new()).collect();
    let mut local = Vec::new();
    for (i, w, l) in order {
        // The least loaded worker (the first of equals); a worker before the caller on a tie.
        let (k, least) =
            load.iter().copied().enumerate().fold(
                (0, f64::INFINITY),
                |best, (k, v)| if v < best.1 { (k, v) } else { best },
            );
        if caller_load < least {
            caller_load += w;
            local.push((i, l));
        } else {
            load[k] += w;
            groups[k].push((i, l));
        }
    }
    groups.iter_mut().for_each(|g| g.sort_by_key(|(i, _)| *i));
    local.sort_by_key(|(i, _)| *i);
    (groups, local)
}

/// Worker threads owning the lanes.
#[derive(Debug)]
pub(crate) struct Workers {
    senders: Vec<SyncSender<Msg>>,
    pub replies: Receiver<Reply>,
    handles: Vec<JoinHandle<()>>,
}

impl Workers {
    /// Starts one worker thread per group of (lane index, lane) (see [`place`]).
    pub fn spawn(groups: Vec<Vec<(usize, LaneState)>>) -> std::io::Result<Workers> {
        let threads = groups.len();
        let (reply_tx, replies) = channel();
        let mut senders = Vec::with_capacity(threads);
        let mut handles = Vec::with_capacity(threads);
        for (w, group) in groups.into_iter().enumerate() {
            let (tx, rx) = sync_channel(JOB_QUEUE);
            let reply_tx = reply_tx.clone();
            let h = std::thread::Builder::new()
                .name(format!("planner-lanes-{w}"))
                .spawn(move || worker(w, group, rx, reply_tx))?;
            senders.push(tx);
            handles.push(h);
        }
        Ok(Workers {
            senders,
            replies,
            handles,
        })
    }

    pub fn count(&self) -> usize {
        self.senders.len()
    }

    /// Sends `msg` (cloned) to every worker; false when a worker is gone.
    pub fn broadcast(&self, msg: impl Fn() -> Msg) -> bool {
        self.senders.iter().all(|s| s.send(msg()).is_ok())
    }
}

impl Drop for Workers {
    fn drop(&mut self) {
        self.senders.clear();
        for h in self.handles.drain(..) {
            let _ = h.join();
        }
    }
}

fn worker(w: usize, mut lanes: Vec<(usize, LaneState)>, rx: Receiver<Msg>, tx: Sender<Reply>) {
    while let Ok(msg) = rx.recv() {
        match msg {
            Msg::Job {
                seq,
                moves,
                pa,
                shaper,
                upto,
                all,
                rest,
            } => {
                let mut out = Vec::with_capacity(lanes.len());
                for (i, lane) in &mut lanes {
                    let mut o = LaneOut::default();
                    lane.run(&moves, &pa, &shaper, upto, all, rest, &mut o);
                    out.push((*i, o));
                }
                if tx
                    .send(Reply {
                        worker: w,
                        seq,
                        lanes: out,
                    })
                    .is_err()
                {
                    return;
                }
            }
            Msg::Backoff(n) => lanes
                .iter_mut()
                .for_each(|(_, l)| l.comp.set_lookahead_backoff(n)),
            Msg::LineFit(on) => lanes.iter_mut().for_each(|(_, l)| l.comp.set_line_fit(on)),
            Msg::Tuning(t) => lanes.iter_mut().for_each(|(_, l)| l.comp.set_tuning(t)),
            Msg::RecordIdeal(on) => lanes.iter_mut().for_each(|(_, l)| l.comp.set_record_ideal(on)),
            Msg::ClockMap(idx, map) => {
                if let Some((_, l)) = lanes.iter_mut().find(|(i, _)| *i == idx) {
                    l.clock.map = map;
                }
            }
        }
    }
}
