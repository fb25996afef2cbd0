//! The per-stepper step paths ("lanes") and where they run: inline on the caller's thread, or
//! spread over worker threads (lane i on worker i mod threads) fed by a bounded queue of jobs.
//!
//! A job is a batch of final moves, shared by every lane, plus the compression horizon; each
//! lane generates the batch's steps, compresses those before the horizon and returns the
//! commands with their sort keys (a `queue_step`'s first clock; `reset_step_clock` and
//! `set_next_step_dir` take the key of the `queue_step` they precede, which the compressor emits
//! in the same batch). Replies carry the job's sequence number so the merger knows how far every
//! lane has got. Lanes are independent: the threads share nothing but the moves (read-only).

use std::sync::mpsc::{channel, sync_channel, Receiver, Sender, SyncSender};
use std::sync::Arc;
use std::thread::JoinHandle;

use crate::compress::StepCompressor;
use crate::kinematics::StepperKin;
use crate::pressure_advance::{PaGen, PressureAdvance};
use crate::stepgen::{IdealStep, StepCmd};
use crate::toolhead::Move;

/// Jobs queued per worker before the producer waits.
const JOB_QUEUE: usize = 4;
/// Commands a lane's output (and the merger's view of it) holds before growing: reserved up
/// front so the planner thread does not allocate in steady state (a job yields well under this
/// on the reference printers).
pub(crate) const CMDS_CAPACITY: usize = 4096;

/// One stepper's step generation and compression.
#[derive(Debug)]
pub(crate) struct LaneState {
    pub kin: StepperKin,
    pub comp: StepCompressor,
    /// The extruder's generator when pressure advance is on.
    pub pa: Option<PaGen>,
    /// For the extruder's lane: (smooth_time, clock_freq) to start pressure advance with when
    /// SET_PRESSURE_ADVANCE turns it on during the print.
    pub extruder: Option<(f64, f64)>,
    fresh: Vec<StepCmd>,
}

/// A new pressure advance for the extruder, from move `at` of a job on: (at, advance,
/// smooth_time).
pub(crate) type PaChange = (usize, f64, f64);

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
    pub fn new(kin: StepperKin, comp: StepCompressor, pa: Option<PaGen>) -> LaneState {
        LaneState {
            kin,
            comp,
            pa,
            extruder: None,
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

    /// Generates and compresses one batch; appends keyed commands to `out.cmds`. `rest`: the
    /// toolhead stops after these moves (steps that depend on later times can be generated).
    /// `pa`: pressure advance changes (move index in `moves`, advance), in order.
    pub fn run(
        &mut self,
        moves: &[Move],
        pa: &[PaChange],
        upto: u64,
        all: bool,
        rest: bool,
        out: &mut LaneOut,
    ) {
        let mut changes = pa.iter().peekable();
        for (i, mv) in moves.iter().enumerate() {
            while let Some(&(_, advance, smooth)) = changes.next_if(|c| c.0 <= i) {
                self.set_advance(advance, smooth);
            }
            match &mut self.pa {
                Some(pa) => pa.push_move(mv),
                None => self.comp.push_move(mv, &self.kin),
            }
        }
        for &(_, advance, smooth) in changes {
            self.set_advance(advance, smooth);
        }
        if let Some(pa) = &mut self.pa {
            let comp = &mut self.comp;
            pa.generate(all || rest, |clock, dir| comp.push_step(clock, dir));
        }
        self.fresh.clear();
        if all {
            self.comp.finish(&mut self.fresh);
        } else {
            self.comp.flush(upto, &mut self.fresh);
        }
        let start = out.cmds.len();
        out.cmds.extend(self.fresh.iter().map(|&c| (u64::MAX, c)));
        let mut key = u64::MAX;
        for h in out.cmds[start..].iter_mut().rev() {
            if let StepCmd::QueueStep { first_clock, .. } = h.1 {
                key = first_clock;
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
        upto: u64,
        all: bool,
        rest: bool,
    },
    Backoff(usize),
    RecordIdeal(bool),
}

/// A worker's answer to one job: (lane index, output) for each of its lanes.
#[derive(Debug)]
pub(crate) struct Reply {
    pub worker: usize,
    pub seq: u64,
    pub lanes: Vec<(usize, LaneOut)>,
}

/// Worker threads owning the lanes.
#[derive(Debug)]
pub(crate) struct Workers {
    senders: Vec<SyncSender<Msg>>,
    pub replies: Receiver<Reply>,
    handles: Vec<JoinHandle<()>>,
}

impl Workers {
    /// Moves `lanes` onto `threads` (≥ 1) worker threads.
    pub fn spawn(lanes: Vec<LaneState>, threads: usize) -> std::io::Result<Workers> {
        let threads = threads.clamp(1, lanes.len().max(1));
        let mut groups: Vec<Vec<(usize, LaneState)>> = (0..threads).map(|_| Vec::new()).collect();
        for (i, l) in lanes.into_iter().enumerate() {
            groups[i % threads].push((i, l));
        }
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
                upto,
                all,
                rest,
            } => {
                let mut out = Vec::with_capacity(lanes.len());
                for (i, lane) in &mut lanes {
                    let mut o = LaneOut::default();
                    lane.run(&moves, &pa, upto, all, rest, &mut o);
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
            Msg::RecordIdeal(on) => lanes.iter_mut().for_each(|(_, l)| l.comp.set_record_ideal(on)),
        }
    }
}
