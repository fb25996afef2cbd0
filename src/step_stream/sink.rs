//! Turns the planner's per-stepper step commands into MCU messages with the clocks that
//! govern when they may be sent, and hands them to a sink: the live MCU link or a batch file.
//!
//! Send rules (the live print keeps 1–2 s of print time buffered, see [`crate::planner_thread`]):
//! - `req_clock` of a message is the first step clock it concerns, so the link releases
//!   messages in step-time order and can measure each one's lead.
//! - `min_clock` keeps the MCU's move pool from overflowing: the k-th `queue_step` may only be
//!   sent once the (k − M)-th has started (its first step clock has passed), M being the pool
//!   size minus a margin. A `reset_step_clock` may only arrive once its stepper is idle (after
//!   its previous last step).

use links::dict::{Cmd, CmdEncoder, Dictionary};
use planner::stepgen::StepCmd;

use crate::hardware::StepperOut;

use super::StreamError;

/// Where encoded messages go.
pub trait Sink {
    /// A message with no timing constraint (configuration, queries).
    fn send(&mut self, cmd: Cmd) -> Result<(), StreamError>;
    /// A message not to be sent before `min_clock`, ordered and lead-checked by `req_clock`.
    fn send_clocked(&mut self, cmd: Cmd, min_clock: u64, req_clock: u64) -> Result<(), StreamError>;
    // homing: a sink that batches must hand its batch on when homing waits for the MCUs.
    /// Hands on whatever the sink holds back (default: it holds nothing back).
    fn flush(&mut self) -> Result<(), StreamError> {
        Ok(())
    }
}

/// Slots kept free in the MCU's move pool as a safety margin.
const POOL_MARGIN: usize = 32;

#[derive(Debug, Clone, Copy, Default)]
struct StepperState {
    /// Clock of the last step sent for this stepper.
    last_clock: u64,
    /// `min_clock` of the last message sent for this stepper (kept monotonic).
    min_clock: u64,
    /// Direction and reset waiting for the next queue_step's clock.
    pending_dir: Option<bool>,
    pending_reset: Option<u64>,
    /// Net steps sent (MCU sign convention).
    steps_sent: u64,
}

/// A driver enable pin on this MCU (configured off: see `crate::mcus::config_commands`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EnableOut {
    pub oid: u8,
    /// The pin's name, as the steppers' `enable_pin` gives it.
    pub pin: String,
    /// Active low (`!`).
    pub invert: bool,
}

/// An enable pin's state as the messages sent so far leave it.
#[derive(Debug, Clone)]
struct EnableState {
    out: EnableOut,
    on: bool,
    /// Clock of the last turn-off (a turn-on is scheduled after it).
    off_clock: u64,
}

/// Encodes step commands for one MCU.
#[derive(Debug)]
pub struct StepStreamer {
    steppers: Vec<StepperOut>,
    state: Vec<StepperState>,
    /// Driver enable pins, and per stepper the index of its own among them.
    enables: Vec<EnableState>,
    enable_of: Vec<Option<usize>>,
    /// First-step clocks of the last `pool` queue_step messages (a ring).
    ring: Vec<u64>,
    ring_pos: usize,
    queue_steps: u64,
    /// Largest step clock sent.
    pub last_step_clock: u64,
    /// Encoders looked up once in the MCU's dictionary (encoding then allocates nothing).
    enc: Encoders,
}

#[derive(Debug)]
struct Encoders {
    queue_step: CmdEncoder,
    set_dir: CmdEncoder,
    reset: CmdEncoder,
    /// `queue_digital_out` (absent from a firmware without outputs, which has no enables).
    digital_out: Option<CmdEncoder>,
}

impl StepStreamer {
    /// A streamer for `steppers` (driven through `enables`) on an MCU whose move pool holds
    /// `move_count` entries.
    pub fn new(
        dict: &Dictionary,
        steppers: &[StepperOut],
        enables: &[EnableOut],
        move_count: usize,
    ) -> Result<StepStreamer, links::dict::DictError> {
        let enc = |name: &str| dict.encoder(name);
        let pool = move_count.saturating_sub(POOL_MARGIN).max(1);
        let enable_of = steppers
            .iter()
            .map(|s| {
                let pin = s.enable_pin.as_ref()?;
                enables.iter().position(|e| e.pin == pin.pin)
            })
            .collect();
        Ok(StepStreamer {
            steppers: steppers.to_vec(),
            state: vec![StepperState::default(); steppers.len()],
            enables: enables
                .iter()
                .map(|out| EnableState {
                    out: out.clone(),
                    on: false,
                    off_clock: 0,
                })
                .collect(),
            enable_of,
            ring: vec![0; pool],
            ring_pos: 0,
            queue_steps: 0,
            last_step_clock: 0,
            enc: Encoders {
                queue_step: enc("queue_step")?,
                set_dir: enc("set_next_step_dir")?,
                reset: enc("reset_step_clock")?,
                digital_out: dict.encoder("queue_digital_out").ok(),
            },
        })
    }

    /// Number of queue_step messages handed to the sink.
    pub fn queue_steps(&self) -> u64 {
        self.queue_steps
    }

    /// Steps handed to the sink per stepper.
    pub fn steps_sent(&self) -> Vec<u64> {
        self.state.iter().map(|s| s.steps_sent).collect()
    }

    // homing: after a stop on trigger the MCU discarded the queued steps of these steppers.
    /// The MCU stopped stepper `idx` (homing): its queue is empty and it is idle by `now_clock`,
    /// so its next `reset_step_clock` may go at once, and the move-pool slots of its discarded
    /// `queue_step`s are free. Call once the steppers stopped and nothing else is moving.
    pub fn note_stopped(&mut self, idx: usize, now_clock: u64) {
        if let Some(st) = self.state.get_mut(idx) {
            st.last_clock = st.last_clock.min(now_clock);
            st.min_clock = st.min_clock.min(now_clock);
        }
        for slot in self.ring.iter_mut() {
            *slot = (*slot).min(now_clock);
        }
        self.last_step_clock = self.state.iter().map(|s| s.last_clock).max().unwrap_or(0);
    }

    /// Sets enable pin `e` to `on` at `clock` (sent in step order, as if a step at `clock`).
    fn set_enable(&mut self, e: usize, on: bool, clock: u64, sink: &mut dyn Sink) -> Result<(), StreamError> {
        let (Some(enc), Some(pin)) = (&self.enc.digital_out, self.enables.get_mut(e)) else {
            return Ok(());
        };
        let m = enc.encode(&[
            i64::from(pin.out.oid),
            clock as u32 as i64,
            i64::from(on != pin.out.invert),
        ])?;
        sink.send_clocked(m, 0, clock)?;
        pin.on = on;
        if !on {
            pin.off_clock = clock;
        }
        Ok(())
    }

    /// Klipper's M84/M18: every enable pin that is on goes off `stall_ticks` after the last
    /// step sent (the motors settle first), at `floor` at the earliest (the lead a message
    /// sent now needs); a later step turns its pin on again.
    pub fn motors_off(
        &mut self,
        stall_ticks: u64,
        floor: u64,
        sink: &mut dyn Sink,
    ) -> Result<(), StreamError> {
        let clock = (self.last_step_clock + stall_ticks).max(floor);
        for e in 0..self.enables.len() {
            if self.enables[e].on {
                self.set_enable(e, false, clock, sink)?;
            }
        }
        Ok(())
    }

    /// Encodes and sends one planner command for stepper `idx`.
    pub fn push(&mut self, idx: usize, cmd: StepCmd, sink: &mut dyn Sink) -> Result<(), StreamError> {
        // A stepper's driver is turned on before its first step (at its step clock's base).
        if let (StepCmd::QueueStep { first_clock, .. }, Some(Some(e))) = (&cmd, self.enable_of.get(idx)) {
            let e = *e;
            if !self.enables[e].on {
                let base = self.state[idx].pending_reset.unwrap_or(*first_clock);
                let clock = base.max(self.enables[e].off_clock + 1);
                self.set_enable(e, true, clock, sink)?;
            }
        }
        let Some(stepper) = self.steppers.get(idx) else {
            return Err(StreamError::UnknownStepper(idx));
        };
        let oid = stepper.oid as i64;
        let invert = stepper.dir_pin.invert;
        let st = &mut self.state[idx];
        match cmd {
            StepCmd::SetDir { dir } => st.pending_dir = Some(dir != invert),
            StepCmd::ResetClock { clock } => st.pending_reset = Some(clock),
            StepCmd::QueueStep {
                interval,
                count,
                add,
                first_clock,
                last_clock,
            } => {
                // Move-pool slot: free once the queue_step `pool` places back has started.
                let slot_clock = self.ring[self.ring_pos];
                let mut min_clock = st.min_clock.max(slot_clock);
                if let Some(clock) = st.pending_reset.take() {
                    // The stepper must be idle when the reset arrives.
                    min_clock = min_clock.max(st.last_clock + 1);
                    st.min_clock = min_clock;
                    let m = self.enc.reset.encode(&[oid, clock as u32 as i64])?;
                    sink.send_clocked(m, min_clock, first_clock)?;
                }
                if let Some(dir) = st.pending_dir.take() {
                    let m = self.enc.set_dir.encode(&[oid, dir as i64])?;
                    sink.send_clocked(m, min_clock, first_clock)?;
                }
                let m = self
                    .enc
                    .queue_step
                    .encode(&[oid, interval as i64, count as i64, add as i64])?;
                sink.send_clocked(m, min_clock, first_clock)?;
                st.min_clock = min_clock;
                st.last_clock = last_clock;
                st.steps_sent += count as u64;
                self.ring[self.ring_pos] = first_clock;
                self.ring_pos = (self.ring_pos + 1) % self.ring.len();
                self.queue_steps += 1;
                self.last_step_clock = self.last_step_clock.max(last_clock);
            }
        }
        Ok(())
    }
}

/// Writes the exact wire stream (message blocks with sequence numbers) to a file, packing
/// messages into blocks in the order given, as Klipper's batch mode does.
#[derive(Debug)]
pub struct BatchSink<W: std::io::Write> {
    out: W,
    seq: u64,
    payload: Vec<u8>,
    pub bytes: u64,
    pub blocks: u64,
}

impl<W: std::io::Write> BatchSink<W> {
    pub fn new(out: W) -> Self {
        BatchSink {
            out,
            seq: 0,
            payload: Vec::with_capacity(64),
            bytes: 0,
            blocks: 0,
        }
    }

    fn push_msg(&mut self, cmd: &Cmd) -> Result<(), StreamError> {
        let bytes = cmd.as_bytes();
        if self.payload.len() + bytes.len() > links::proto::MESSAGE_PAYLOAD_MAX {
            self.flush_block()?;
        }
        self.payload.extend_from_slice(bytes);
        Ok(())
    }

    fn flush_block(&mut self) -> Result<(), StreamError> {
        if self.payload.is_empty() {
            return Ok(());
        }
        let mut block = [0u8; links::proto::MESSAGE_MAX];
        let n = links::proto::encode_block(self.seq as u8, &self.payload, &mut block)
            .ok_or(StreamError::BlockTooLong)?;
        self.out.write_all(&block[..n]).map_err(StreamError::Write)?;
        self.seq += 1;
        self.bytes += n as u64;
        self.blocks += 1;
        self.payload.clear();
        Ok(())
    }

    /// Flushes the last block and the writer.
    pub fn finish(&mut self) -> Result<(), StreamError> {
        self.flush_block()?;
        self.out.flush().map_err(StreamError::Write)
    }
}

impl<W: std::io::Write> Sink for BatchSink<W> {
    fn send(&mut self, cmd: Cmd) -> Result<(), StreamError> {
        self.push_msg(&cmd)
    }
    fn send_clocked(&mut self, cmd: Cmd, _min_clock: u64, _req_clock: u64) -> Result<(), StreamError> {
        self.push_msg(&cmd)
    }
}

/// Hands messages straight to one MCU link (used while homing, when the planner thread talks to
/// the MCUs directly after the shared-memory hand-off has drained).
#[derive(Debug)]
pub struct LinkSink<'a> {
    pub link: &'a links::mcu::McuLink,
}

impl Sink for LinkSink<'_> {
    fn send(&mut self, cmd: Cmd) -> Result<(), StreamError> {
        Ok(self.link.send(cmd)?)
    }
    fn send_clocked(&mut self, cmd: Cmd, min_clock: u64, req_clock: u64) -> Result<(), StreamError> {
        Ok(self.link.send_clocked(cmd, min_clock, req_clock)?)
    }
}
