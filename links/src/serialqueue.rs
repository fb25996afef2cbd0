//! The reliable transport to one MCU: sequence numbers, ack/nak, retransmission, flow control
//! and scheduling of queued messages by MCU clock. A pure state machine: time comes in as an
//! argument (`now`, system seconds) and [`SerialQueue::poll_at`] says when it next needs to run,
//! so the whole link replays deterministically in virtual time.
//!
//! **Sequences.** Every host block carries the low 4 bits of a 64-bit send sequence. Every MCU
//! block carries the low 4 bits of the next sequence the MCU expects: that is the ack. The
//! 64-bit ack is rebuilt as the smallest value ≥ the previous ack with those low bits; a value
//! beyond what was sent is invalid. Sequences start at 16 (low bits 0, what a freshly booted
//! MCU expects). Before the first MCU block only one block is in flight; if that first answer
//! shows the MCU expects another sequence, the unacked blocks are renumbered and resent.
//! A valid block acking beyond what was sent is counted ([`SerialQueue::impossible_ack_run`]
//! counts them in a row: a reset MCU) and triggers an immediate resend; its payload is still
//! delivered.
//!
//! **Ack/nak.** An empty MCU block whose sequence is not newer than the previous empty block's
//! is a NAK: everything unacked is resent at once (one write starting with a sync byte that
//! flushes any partial block in the MCU's buffer). Further NAKs for the same loss are ignored
//! until the ack moves past the resent range, so a burst of NAKs costs one retransmit.
//!
//! **Retransmit timeout** (RFC 6298): on each RTT sample `r` (Karn: never from a resent block)
//! `rttvar = ¾·rttvar + ¼·|srtt − r|`, `srtt = ⅞·srtt + ⅛·r` (first: `srtt = r`,
//! `rttvar = r/2`), `rto = srtt + max(1 ms, 4·rttvar)` clamped to 25 ms ..= 5 s; each timeout
//! resends everything unacked and doubles `rto` (up to 5 s).
//!
//! **Flow control.** At most 12 blocks unacked, and never more unacked bytes than the MCU's
//! `RECEIVE_WINDOW` (one block is always allowed when nothing is in flight).
//!
//! **Scheduling.** Each message has `min_clock` and `req_clock` (64-bit MCU clock). It is not
//! sent before the estimated MCU clock reaches `min_clock`; among ready messages the smallest
//! `req_clock` goes first, ties in submission order. Messages with both at 0 ("plain") are
//! ready at once and, having the smallest `req_clock`, go first in submission order. Ordering
//! between messages of one stream (one stepper) is the caller's: give them non-decreasing
//! `min_clock` and `req_clock`. Ready messages are packed into blocks of up to 59 payload bytes.
//!
//! **Lead margin.** When a block is first written, each message in it with `req_clock > 0`
//! records `req_clock − estimated MCU clock now` (ticks); the minimum and count are kept and
//! an optional hook sees each value.
//!
//! **Memory.** All buffers and queues are allocated in [`SerialQueue::new`]; `push`, `poll`
//! and `receive` never allocate.

use std::cmp::Ordering;
use std::collections::{BinaryHeap, VecDeque};
use std::fmt;

use crate::clocksync::ClockEstimate;
use crate::dict::Cmd;
use crate::proto::block::block_payload;
use crate::proto::{
    encode_block, find_block, Frame, MESSAGE_MAX, MESSAGE_MIN, MESSAGE_PAYLOAD_MAX, MESSAGE_SYNC,
};

/// Most unacked blocks.
pub const MAX_PENDING_BLOCKS: usize = 12;
/// Smallest retransmit timeout, seconds.
pub const MIN_RTO: f64 = 0.025;
/// Largest retransmit timeout, seconds.
pub const MAX_RTO: f64 = 5.0;
/// RFC 6298 clock granularity `G`, seconds.
const RTO_GRANULARITY: f64 = 0.001;
/// The first sequence number (low bits 0).
pub const FIRST_SEQ: u64 = 16;
const SEQ_MASK: u64 = 0x0F;
/// Submission orders below this belong to urgent messages, so they sort before every other
/// ready message (2^48 urgent messages are never reached).
const URGENT_ORDERS: u64 = 1 << 48;
const RX_BUF: usize = 4096;
const TX_BUF: usize = 1 + MAX_PENDING_BLOCKS * MESSAGE_MAX;

/// Configuration of a [`SerialQueue`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct QueueConfig {
    /// Most messages queued and not yet sent.
    pub capacity: usize,
    /// The MCU's receive buffer (`RECEIVE_WINDOW`); `None` = limit by block count only.
    pub receive_window: Option<usize>,
}

/// Counters and timer state of a [`SerialQueue`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct QueueStats {
    /// Bytes of new blocks written.
    pub bytes_write: u64,
    /// Bytes of valid MCU blocks read.
    pub bytes_read: u64,
    /// Bytes written again by retransmits.
    pub bytes_retransmit: u64,
    /// Bytes received that were not valid blocks (or had impossible sequences).
    pub bytes_invalid: u64,
    /// Retransmit events (timeouts and NAKs).
    pub retransmits: u64,
    /// Smoothed round-trip time, seconds (0 before the first sample).
    pub srtt: f64,
    /// Round-trip time variation, seconds.
    pub rttvar: f64,
    /// Current retransmit timeout, seconds.
    pub rto: f64,
    /// Next sequence to send (64-bit).
    pub send_seq: u64,
    /// Next sequence the MCU expects, i.e. everything below is acked (64-bit).
    pub receive_seq: u64,
    /// Bytes of messages ready to send.
    pub ready_bytes: u64,
    /// Bytes of messages waiting for their `min_clock`.
    pub upcoming_bytes: u64,
    /// Messages queued (ready and upcoming).
    pub queued_msgs: u64,
    /// Blocks written and not yet acked.
    pub inflight_blocks: u64,
    /// Messages whose block has been acked.
    pub msgs_acked: u64,
    /// Messages with `req_clock > 0` written.
    pub clocked_sent: u64,
    /// Smallest lead margin seen (ticks), `None` before the first clocked message.
    pub min_lead_margin: Option<i64>,
}

#[derive(Debug, Clone, Copy)]
struct Queued {
    cmd: Cmd,
    min_clock: u64,
    req_clock: u64,
    order: u64,
    mark: bool,
}

/// Heap entry ordered so the max-heap pops the smallest `(min_clock, order)`.
#[derive(Debug)]
struct ByMinClock(Queued);
/// Heap entry ordered so the max-heap pops the smallest `(req_clock, order)`.
#[derive(Debug)]
struct ByReqClock(Queued);

macro_rules! heap_order {
    ($t:ident, $field:ident) => {
        impl Ord for $t {
            fn cmp(&self, other: &Self) -> Ordering {
                (other.0.$field, other.0.order).cmp(&(self.0.$field, self.0.order))
            }
        }
        impl PartialOrd for $t {
            fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
                Some(self.cmp(other))
            }
        }
        impl PartialEq for $t {
            fn eq(&self, other: &Self) -> bool {
                self.cmp(other) == Ordering::Equal
            }
        }
        impl Eq for $t {}
    };
}
heap_order!(ByMinClock, min_clock);
heap_order!(ByReqClock, req_clock);

/// A block written and not yet acked; the payload is kept so it can be renumbered.
#[derive(Debug, Clone, Copy)]
struct SentBlock {
    seq: u64,
    payload: [u8; MESSAGE_PAYLOAD_MAX],
    plen: u8,
    msgs: u16,
    first_sent: f64,
}

impl SentBlock {
    fn block_len(&self) -> usize {
        self.plen as usize + MESSAGE_MIN
    }
}

/// Callback for each lead margin: `(req_clock, margin ticks)`.
pub type MarginHook = Box<dyn FnMut(u64, i64) + Send>;

/// The reliable transport state machine of one MCU link.
pub struct SerialQueue {
    cfg: QueueConfig,
    est: ClockEstimate,
    upcoming: BinaryHeap<ByMinClock>,
    ready: BinaryHeap<ByReqClock>,
    next_order: u64,
    next_urgent_order: u64,
    synced: bool,
    inflight: VecDeque<SentBlock>,
    inflight_bytes: usize,
    last_ack_seq: u64,
    ignore_nak_seq: u64,
    retransmit_seq: u64,
    retransmit_now: bool,
    retransmit_at: Option<f64>,
    rtt_sample: Option<(u64, f64)>,
    last_ack_time: f64,
    last_now: f64,
    marked_sent: Option<f64>,
    rx: Box<[u8; RX_BUF]>,
    rx_len: usize,
    tx: Box<[u8; TX_BUF]>,
    tx_len: usize,
    margin_hook: Option<MarginHook>,
    impossible_run: u32,
    stats: QueueStats,
}

impl fmt::Debug for SerialQueue {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SerialQueue")
            .field("cfg", &self.cfg)
            .field("stats", &self.stats)
            .finish_non_exhaustive()
    }
}

impl SerialQueue {
    /// A queue with everything preallocated.
    pub fn new(cfg: QueueConfig) -> SerialQueue {
        let capacity = cfg.capacity.max(1);
        SerialQueue {
            cfg: QueueConfig { capacity, ..cfg },
            est: ClockEstimate::INVALID,
            upcoming: BinaryHeap::with_capacity(capacity),
            ready: BinaryHeap::with_capacity(capacity + 1),
            next_order: URGENT_ORDERS,
            next_urgent_order: 0,
            synced: false,
            inflight: VecDeque::with_capacity(MAX_PENDING_BLOCKS),
            inflight_bytes: 0,
            last_ack_seq: 0,
            ignore_nak_seq: 0,
            retransmit_seq: 0,
            retransmit_now: false,
            retransmit_at: None,
            rtt_sample: None,
            last_ack_time: 0.0,
            last_now: 0.0,
            marked_sent: None,
            rx: Box::new([0; RX_BUF]),
            rx_len: 0,
            tx: Box::new([0; TX_BUF]),
            tx_len: 0,
            margin_hook: None,
            impossible_run: 0,
            stats: QueueStats {
                rto: MIN_RTO,
                send_seq: FIRST_SEQ,
                receive_seq: FIRST_SEQ,
                ..QueueStats::default()
            },
        }
    }

    /// Sets the MCU's receive window (known once the dictionary is read).
    pub fn set_receive_window(&mut self, window: Option<usize>) {
        self.cfg.receive_window = window;
    }

    /// Sets the clock estimate used for `min_clock` and lead margins.
    pub fn set_clock_est(&mut self, est: ClockEstimate) {
        self.est = est;
    }

    /// Installs (or removes) the per-message lead margin callback.
    pub fn set_margin_hook(&mut self, hook: Option<MarginHook>) {
        self.margin_hook = hook;
    }

    /// Messages queued and not yet sent.
    pub fn len(&self) -> usize {
        self.ready.len() + self.upcoming.len()
    }

    /// True when no message is queued.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Free queue slots.
    pub fn space(&self) -> usize {
        self.cfg.capacity.saturating_sub(self.len())
    }

    /// True when nothing is queued and everything sent has been acked.
    pub fn is_idle(&self) -> bool {
        self.is_empty() && self.inflight.is_empty()
    }

    /// True when messages wait for their `min_clock`.
    pub fn has_upcoming(&self) -> bool {
        !self.upcoming.is_empty()
    }

    /// Queues `cmd`, to be sent once the MCU clock reaches `min_clock`, ordered by
    /// `req_clock`. Gives the message back when the queue is full.
    pub fn push(&mut self, cmd: Cmd, min_clock: u64, req_clock: u64) -> Result<(), Cmd> {
        self.push_inner(cmd, min_clock, req_clock, false)
    }

    /// Queues a plain message whose write time is recorded for [`Self::take_marked_sent`]
    /// (clock sync queries).
    pub fn push_marked(&mut self, cmd: Cmd) -> Result<(), Cmd> {
        self.push_inner(cmd, 0, 0, true)
    }

    /// Queues a plain message ahead of every ready message (a homing trigger). It may use one
    /// slot beyond the capacity; gives the message back when even that is taken.
    pub fn push_urgent(&mut self, cmd: Cmd) -> Result<(), Cmd> {
        if self.len() > self.cfg.capacity {
            return Err(cmd);
        }
        let order = self.next_urgent_order;
        self.next_urgent_order += 1;
        self.stats.ready_bytes += cmd.len() as u64;
        self.ready.push(ByReqClock(Queued {
            cmd,
            min_clock: 0,
            req_clock: 0,
            order,
            mark: false,
        }));
        Ok(())
    }

    fn push_inner(&mut self, cmd: Cmd, min_clock: u64, req_clock: u64, mark: bool) -> Result<(), Cmd> {
        if self.len() >= self.cfg.capacity {
            return Err(cmd);
        }
        let q = Queued {
            cmd,
            min_clock,
            req_clock,
            order: self.next_order,
            mark,
        };
        self.next_order += 1;
        if min_clock == 0 {
            self.stats.ready_bytes += cmd.len() as u64;
            self.ready.push(ByReqClock(q));
        } else {
            self.stats.upcoming_bytes += cmd.len() as u64;
            self.upcoming.push(ByMinClock(q));
        }
        Ok(())
    }

    /// The system time at which the last marked message was written, once.
    pub fn take_marked_sent(&mut self) -> Option<f64> {
        self.marked_sent.take()
    }

    /// Since when the link has been waiting for an ack: the later of the last ack progress
    /// and the first write of the oldest unacked block. `None` when nothing is unacked.
    pub fn ack_wait_since(&self) -> Option<f64> {
        self.inflight
            .front()
            .map(|b| b.first_sent.max(self.last_ack_time))
    }

    /// Valid MCU blocks in a row whose ack acknowledges blocks never sent: an MCU whose
    /// sequence restarted (it reset). Any block with a possible ack ends the run.
    pub fn impossible_ack_run(&self) -> u32 {
        self.impossible_run
    }

    /// Counters and timers.
    pub fn stats(&self) -> QueueStats {
        QueueStats {
            queued_msgs: self.len() as u64,
            inflight_blocks: self.inflight.len() as u64,
            ..self.stats
        }
    }

    /// When [`Self::poll`] next has something to do (system seconds; a time at or before the
    /// last `now` means "at once"), or `None` if only input can create work.
    pub fn poll_at(&self) -> Option<f64> {
        if self.retransmit_now || self.can_send_more() {
            return Some(self.last_now);
        }
        let mut at = self.retransmit_at.filter(|_| !self.inflight.is_empty());
        if let Some(top) = self.upcoming.peek() {
            if self.est.is_valid() {
                let t = self.est.system_time_at(top.0.min_clock as f64);
                at = Some(at.map_or(t, |a: f64| a.min(t)));
            }
        }
        at
    }

    /// Runs timers and scheduling at `now`; returns the bytes to write (retransmits and new
    /// blocks), valid until the next call.
    pub fn poll(&mut self, now: f64) -> &[u8] {
        self.last_now = now;
        self.tx_len = 0;
        let timed_out = !self.inflight.is_empty() && self.retransmit_at.is_some_and(|t| now >= t);
        if self.retransmit_now || timed_out {
            self.retransmit(now, !self.retransmit_now);
        }
        let clock = self.est.clock_at(now);
        while let Some(top) = self.upcoming.peek() {
            if !self.est.is_valid() || top.0.min_clock as f64 > clock {
                break;
            }
            if let Some(ByMinClock(q)) = self.upcoming.pop() {
                self.stats.upcoming_bytes -= q.cmd.len() as u64;
                self.stats.ready_bytes += q.cmd.len() as u64;
                self.ready.push(ByReqClock(q));
            }
        }
        while self.can_send_more() {
            if !self.send_block(now, clock) {
                break;
            }
        }
        &self.tx[..self.tx_len]
    }

    /// True when a new block could go out now.
    fn can_send_more(&self) -> bool {
        if self.ready.is_empty() {
            return false;
        }
        let limit = if self.synced { MAX_PENDING_BLOCKS } else { 1 };
        if self.inflight.len() >= limit {
            return false;
        }
        match (self.cfg.receive_window, self.ready.peek()) {
            (Some(w), Some(top)) if !self.inflight.is_empty() => {
                self.inflight_bytes + MESSAGE_MIN + top.0.cmd.len() <= w
            }
            _ => true,
        }
    }

    /// Packs ready messages into one block and writes it. Returns false if nothing fit.
    fn send_block(&mut self, now: f64, clock: f64) -> bool {
        let mut block = SentBlock {
            seq: self.stats.send_seq,
            payload: [0; MESSAGE_PAYLOAD_MAX],
            plen: 0,
            msgs: 0,
            first_sent: now,
        };
        let window = self.cfg.receive_window.unwrap_or(usize::MAX);
        while let Some(top) = self.ready.peek() {
            let len = top.0.cmd.len();
            let plen = block.plen as usize;
            if plen + len > MESSAGE_PAYLOAD_MAX {
                break;
            }
            let first_ever = self.inflight.is_empty() && block.msgs == 0;
            if !first_ever && self.inflight_bytes + MESSAGE_MIN + plen + len > window {
                break;
            }
            let Some(ByReqClock(q)) = self.ready.pop() else {
                break;
            };
            block.payload[plen..plen + len].copy_from_slice(q.cmd.as_bytes());
            block.plen += len as u8;
            block.msgs += 1;
            self.stats.ready_bytes -= len as u64;
            if q.mark {
                self.marked_sent = Some(now);
            }
            if q.req_clock > 0 {
                let margin = q.req_clock as i64 - clock as i64;
                self.stats.clocked_sent += 1;
                self.stats.min_lead_margin =
                    Some(self.stats.min_lead_margin.map_or(margin, |m| m.min(margin)));
                if let Some(hook) = self.margin_hook.as_mut() {
                    hook(q.req_clock, margin);
                }
            }
        }
        if block.msgs == 0 {
            return false;
        }
        let written = self.write_block(&block);
        self.stats.bytes_write += written as u64;
        if self.inflight.is_empty() {
            self.retransmit_at = Some(now + self.stats.rto);
        }
        if self.rtt_sample.is_none() {
            self.rtt_sample = Some((block.seq, now));
        }
        self.inflight_bytes += block.block_len();
        self.inflight.push_back(block);
        self.stats.send_seq += 1;
        true
    }

    /// Appends `block` to the output buffer; returns its length on the wire.
    fn write_block(&mut self, block: &SentBlock) -> usize {
        let dst = &mut self.tx[self.tx_len..];
        let n = encode_block(block.seq as u8, &block.payload[..block.plen as usize], dst).unwrap_or(0);
        debug_assert!(n > 0, "tx buffer sized for MAX_PENDING_BLOCKS blocks");
        self.tx_len += n;
        n
    }

    /// Resends everything unacked after a timeout (`timeout`) or a NAK.
    fn retransmit(&mut self, now: f64, timeout: bool) {
        self.retransmit_now = false;
        if self.inflight.is_empty() {
            return;
        }
        let start = self.tx_len;
        self.tx[self.tx_len] = MESSAGE_SYNC;
        self.tx_len += 1;
        for i in 0..self.inflight.len() {
            let block = self.inflight[i];
            self.write_block(&block);
        }
        self.stats.bytes_retransmit += (self.tx_len - start) as u64;
        self.stats.retransmits += 1;
        if timeout {
            self.stats.rto = (self.stats.rto * 2.0).min(MAX_RTO);
            self.ignore_nak_seq = self.stats.send_seq;
        } else {
            // One retransmit per NAKed ack level; if the previous retransmit is itself still
            // unacked, wait for its whole range (a third NAK-retransmit would only add load).
            self.ignore_nak_seq = self.stats.receive_seq.max(self.retransmit_seq);
        }
        self.retransmit_seq = self.stats.send_seq;
        self.rtt_sample = None;
        self.retransmit_at = Some(now + self.stats.rto);
    }

    /// Feeds bytes read from the MCU at `now`; each received non-empty payload goes to
    /// `on_payload` in order.
    pub fn receive(&mut self, now: f64, mut data: &[u8], on_payload: &mut dyn FnMut(&[u8])) {
        self.last_now = now;
        while !data.is_empty() {
            let n = data.len().min(RX_BUF - self.rx_len);
            self.rx[self.rx_len..self.rx_len + n].copy_from_slice(&data[..n]);
            self.rx_len += n;
            data = &data[n..];
            self.parse_rx(now, on_payload);
        }
    }

    fn parse_rx(&mut self, now: f64, on_payload: &mut dyn FnMut(&[u8])) {
        let mut pos = 0;
        while pos < self.rx_len {
            match find_block(&self.rx[pos..self.rx_len]) {
                Frame::Incomplete => break,
                Frame::Skip(n) => pos += n,
                Frame::Bad(n) => {
                    self.stats.bytes_invalid += n as u64;
                    pos += n;
                }
                Frame::Block { len, seq } => {
                    let mut block = [0u8; MESSAGE_MAX];
                    block[..len].copy_from_slice(&self.rx[pos..pos + len]);
                    pos += len;
                    self.handle_block(now, seq, &block[..len], on_payload);
                }
            }
        }
        let pos = pos.min(self.rx_len);
        self.rx.copy_within(pos..self.rx_len, 0);
        self.rx_len -= pos;
    }

    /// One valid MCU block with 4-bit sequence `nibble`.
    fn handle_block(&mut self, now: f64, nibble: u8, block: &[u8], on_payload: &mut dyn FnMut(&[u8])) {
        let nibble = nibble as u64 & SEQ_MASK;
        let receive_seq = self.stats.receive_seq;
        let rseq = if !self.synced {
            self.synced = true;
            let k = nibble.wrapping_sub(receive_seq) & SEQ_MASK;
            if self.inflight.is_empty() || k as usize > self.inflight.len() {
                // The MCU expects a sequence we have not used: adopt it.
                self.renumber(nibble);
                self.stats.receive_seq
            } else {
                receive_seq + k
            }
        } else {
            let mut r = (receive_seq & !SEQ_MASK) | nibble;
            if r < receive_seq {
                r += SEQ_MASK + 1;
            }
            if r > self.stats.send_seq {
                // An ack of blocks never sent: a stale duplicate, or an MCU whose sequence
                // restarted. Resend at once (as Klipper does) so a reset MCU shows itself
                // quickly; the payload is still the MCU's data (MCU → host data carries no
                // sequence of its own), so it is delivered.
                self.stats.bytes_invalid += block.len() as u64;
                self.impossible_run = self.impossible_run.saturating_add(1);
                if !self.inflight.is_empty() {
                    self.retransmit_now = true;
                }
                if block.len() > MESSAGE_MIN {
                    on_payload(block_payload(block));
                }
                return;
            }
            r
        };
        self.impossible_run = 0;
        if rseq != self.stats.receive_seq {
            self.ack_to(now, rseq);
        }
        self.stats.bytes_read += block.len() as u64;
        if block.len() == MESSAGE_MIN {
            if self.last_ack_seq < rseq {
                self.last_ack_seq = rseq;
            } else if rseq > self.ignore_nak_seq && !self.inflight.is_empty() {
                self.retransmit_now = true;
            }
        } else {
            on_payload(block_payload(block));
        }
    }

    /// Adopts the MCU's expected sequence (low bits `nibble`) and renumbers unacked blocks.
    fn renumber(&mut self, nibble: u64) {
        let send_seq = self.stats.send_seq;
        let base = send_seq + (nibble.wrapping_sub(send_seq) & SEQ_MASK);
        for (i, b) in self.inflight.iter_mut().enumerate() {
            b.seq = base + i as u64;
        }
        self.stats.receive_seq = base;
        self.stats.send_seq = base + self.inflight.len() as u64;
        self.last_ack_seq = base;
        self.ignore_nak_seq = 0;
        self.retransmit_seq = base;
        self.rtt_sample = None;
        if !self.inflight.is_empty() {
            self.retransmit_now = true;
        }
    }

    /// Everything below `rseq` is acked.
    fn ack_to(&mut self, now: f64, rseq: u64) {
        while let Some(front) = self.inflight.front() {
            if front.seq >= rseq {
                break;
            }
            self.inflight_bytes -= front.block_len();
            self.stats.msgs_acked += front.msgs as u64;
            self.inflight.pop_front();
        }
        self.stats.receive_seq = rseq;
        self.last_ack_time = now;
        if let Some((seq, sent)) = self.rtt_sample {
            if rseq > seq {
                self.rtt_sample = None;
                self.update_rtt((now - sent).max(0.0));
            }
        }
        self.retransmit_at = (!self.inflight.is_empty()).then_some(now + self.stats.rto);
    }

    fn update_rtt(&mut self, r: f64) {
        let s = &mut self.stats;
        if s.srtt == 0.0 {
            s.srtt = r;
            s.rttvar = r / 2.0;
        } else {
            s.rttvar = 0.75 * s.rttvar + 0.25 * (s.srtt - r).abs();
            s.srtt = 0.875 * s.srtt + 0.125 * r;
        }
        s.rto = (s.srtt + (4.0 * s.rttvar).max(RTO_GRANULARITY)).clamp(MIN_RTO, MAX_RTO);
    }
}

#[cfg(test)]
mod tests;
