//! The IO thread of one MCU: owns the transport, runs the serial queue, the handshake and the
//! clock sync, and dispatches responses.
//!
//! Loop: take caller messages → run handshake/clock timers → `poll` the serial queue and write
//! what it releases → read with a timeout (until the next deadline, ≤ 1 ms while messages wait
//! for their `min_clock`, ≤ 5 ms otherwise) → feed the serial queue → dispatch payloads →
//! check the ack deadline → publish counters and wake waiters.
//!
//! Handshake phases: `Identify` (chunks of 40 bytes until an empty one; resent when the link is
//! idle and unanswered for a while, which covers a first block the MCU dropped) → `Uptime`
//! (64-bit clock) → `InitialClock` (8 `get_clock` 50 ms apart) → `Running`.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use super::shared::{lock, Death, Outgoing, RelayTag, Shared, WaitFail, ANSWERED_WHEN_SHUT_DOWN, RUNNING};
use super::{LinkOptions, LinkStats, LinkTuning};
use crate::clocksync::{ClockSync, Sample};
use crate::dict::message::decode_params_into;
use crate::dict::{Cmd, Dictionary};
use crate::proto::format::Value;
use crate::serialqueue::{QueueConfig, SerialQueue};
use crate::transport::Transport;

/// Bytes asked for per `identify`.
const IDENTIFY_CHUNK: i64 = 40;
/// Largest read per loop iteration.
const READ_BUF: usize = 4096;
/// Serial queue slots kept for the link's own messages.
const INTERNAL_SLOTS: usize = 8;
/// Valid MCU blocks in a row with an impossible ack that mean the MCU restarted (a single
/// one could be a stale duplicate; a reset MCU NAKs every block of each immediate resend).
const RESET_ACK_RUN: u32 = 4;
/// Longest read wait while a homing group is registered, seconds: bounds how late a trigger
/// relayed by another IO thread is written.
const ARMED_READ_WAIT: f64 = 0.000_5;
/// Most parameters decoded on the stack.
const MAX_STACK_PARAMS: usize = 16;
/// Relayed triggers tracked at once between the serial queue and the wire (more are sent
/// untracked: their write time is not reported).
const RELAY_SLOTS: usize = 16;

/// `CLOCK_MONOTONIC` in seconds.
pub(crate) fn system_now() -> f64 {
    nix::time::clock_gettime(nix::time::ClockId::CLOCK_MONOTONIC)
        .map(|t| t.tv_sec() as f64 + t.tv_nsec() as f64 * 1e-9)
        .unwrap_or(0.0)
}

/// The urgent messages this thread moved into the serial queue, and which of them were
/// relayed homing triggers. Urgent messages leave the serial queue before every other one and
/// in their order, so the number of messages a `poll` released tells exactly which urgent
/// ones went out with that write, even when flow control held them back for a while.
#[derive(Debug)]
pub(crate) struct UrgentTrack {
    /// Urgent messages pushed into the serial queue.
    pushed: u64,
    /// Of those, written to the transport.
    written: u64,
    /// Ring of `(urgent sequence number, tag)` of the relayed triggers not yet written.
    tags: [(u64, RelayTag); RELAY_SLOTS],
    head: usize,
    len: usize,
}

impl UrgentTrack {
    pub(crate) fn new() -> UrgentTrack {
        UrgentTrack {
            pushed: 0,
            written: 0,
            tags: [(0, RelayTag { group: 0, member: 0 }); RELAY_SLOTS],
            head: 0,
            len: 0,
        }
    }

    /// An urgent message went into the serial queue (`relay`: its tag, if it is a trigger).
    pub(crate) fn pushed(&mut self, relay: Option<RelayTag>) {
        if let Some(tag) = relay {
            if self.len < RELAY_SLOTS {
                self.tags[(self.head + self.len) % RELAY_SLOTS] = (self.pushed, tag);
                self.len += 1;
            }
        }
        self.pushed += 1;
    }

    /// `sent` messages left the serial queue with one write (urgent ones first). Returns true
    /// when a tracked trigger was among them ([`Self::pop_written`] then yields it).
    pub(crate) fn sent(&mut self, sent: u64) -> bool {
        self.written += sent.min(self.pushed - self.written);
        self.len > 0 && self.tags[self.head].0 < self.written
    }

    /// The next tracked trigger that has been written, oldest first.
    pub(crate) fn pop_written(&mut self) -> Option<RelayTag> {
        let (seq, tag) = self.tags[self.head];
        if self.len == 0 || seq >= self.written {
            return None;
        }
        self.head = (self.head + 1) % RELAY_SLOTS;
        self.len -= 1;
        Some(tag)
    }
}

/// Marks the link dead if the IO thread unwinds, so no caller waits for a thread that is gone.
struct PanicGuard(Arc<Shared>);

impl Drop for PanicGuard {
    fn drop(&mut self) {
        if std::thread::panicking() {
            self.0.die(Death::ConnectionLost("IO thread panicked".into()));
        }
    }
}

/// Ids and commands the IO thread itself uses, looked up once.
#[derive(Debug, Clone, Copy, Default)]
struct Known {
    get_clock: Option<Cmd>,
    clock: Option<u32>,
    uptime: Option<u32>,
    shutdown: Option<u32>,
    is_shutdown: Option<u32>,
    starting: Option<u32>,
    trsync_state: Option<u32>,
    analog_in_state: Option<u32>,
    counter_state: Option<u32>,
    thermocouple_result: Option<u32>,
    stats: Option<u32>,
}

#[derive(Debug)]
enum Phase {
    Identify {
        offset: i64,
        data: Vec<u8>,
        deadline: f64,
        last_sent: f64,
        answered: bool,
    },
    Uptime {
        deadline: f64,
        get_uptime: Cmd,
    },
    InitialClock {
        /// Samples used by the clock regression.
        count: u32,
        /// Answers received (slow or outlying ones included).
        answers: u32,
        deadline: f64,
    },
    Running,
}

/// A `get_clock` in flight.
#[derive(Debug, Clone, Copy)]
struct ClockQuery {
    queued_at: f64,
    sent_at: Option<f64>,
}

pub(crate) struct IoThread {
    shared: Arc<Shared>,
    transport: Box<dyn Transport>,
    sq: SerialQueue,
    dict: Arc<Dictionary>,
    known: Known,
    sync: ClockSync,
    phase: Phase,
    clock_query: Option<ClockQuery>,
    next_clock_at: f64,
    /// Until this system time, `get_clock` keeps the initial spacing.
    fast_clock_until: f64,
    tuning: LinkTuning,
    identify_timeout: f64,
    response_timeout: f64,
    held: Option<Outgoing>,
    urgent: UrgentTrack,
    user_capacity: usize,
    taken: u64,
    payloads: Vec<u8>,
    undecodable: u64,
    nominal_freq: f64,
    sumsq_base: f64,
    mcu_stats_reports: u64,
    mcu_awake: f64,
    mcu_task_avg: f64,
    mcu_task_stddev: f64,
}

impl IoThread {
    pub(crate) fn new(
        shared: Arc<Shared>,
        transport: Box<dyn Transport>,
        opts: &LinkOptions,
        mut tuning: LinkTuning,
    ) -> IoThread {
        let user_capacity = opts.queue_capacity.max(16);
        let mut sq = SerialQueue::new(QueueConfig {
            // Room kept free for the link's own messages (identify, get_clock).
            capacity: user_capacity + INTERNAL_SLOTS,
            receive_window: None,
        });
        sq.set_margin_hook(tuning.margin_hook.take());
        IoThread {
            shared,
            transport,
            sq,
            dict: Arc::new(Dictionary::bootstrap()),
            known: Known::default(),
            sync: ClockSync::new(1.0),
            phase: Phase::Identify {
                offset: 0,
                data: Vec::with_capacity(8192),
                deadline: 0.0,
                last_sent: f64::NEG_INFINITY,
                answered: false,
            },
            clock_query: None,
            next_clock_at: 0.0,
            fast_clock_until: 0.0,
            tuning,
            identify_timeout: opts.identify_timeout.as_secs_f64(),
            response_timeout: opts.response_timeout.as_secs_f64(),
            held: None,
            urgent: UrgentTrack::new(),
            user_capacity,
            taken: 0,
            payloads: Vec::with_capacity(READ_BUF * 2),
            undecodable: 0,
            nominal_freq: 1.0,
            sumsq_base: 256.0,
            mcu_stats_reports: 0,
            mcu_awake: 0.0,
            mcu_task_avg: 0.0,
            mcu_task_stddev: 0.0,
        }
    }

    /// Runs until stopped or dead.
    pub(crate) fn run(mut self) {
        let _guard = PanicGuard(self.shared.clone());
        let mut buf = [0u8; READ_BUF];
        let start = system_now();
        if let Phase::Identify { deadline, .. } = &mut self.phase {
            *deadline = start + self.identify_timeout;
        }
        while !self.shared.stop.load(Ordering::Acquire) {
            if let Err(death) = self.iterate(&mut buf) {
                self.shared.die(death);
                break;
            }
        }
        self.publish_stats();
        self.shared.notify.notify();
    }

    fn iterate(&mut self, buf: &mut [u8; READ_BUF]) -> Result<(), Death> {
        let now = system_now();
        self.take_outgoing();
        self.run_timers(now)?;
        let queued = self.sq.len();
        let out = self.sq.poll(now);
        if !out.is_empty() {
            self.transport
                .write_all(out)
                .map_err(|e| Death::ConnectionLost(format!("write to {}: {e}", self.transport.describe())))?;
        }
        // Messages only leave the serial queue in `poll`: the difference is what was written.
        if self.urgent.sent(queued.saturating_sub(self.sq.len()) as u64) {
            let written_at = system_now();
            while let Some(tag) = self.urgent.pop_written() {
                crate::trsync::relay_written(&self.shared, tag, written_at);
            }
        }
        if let Some(t) = self.sq.take_marked_sent() {
            if let Some(q) = self.clock_query.as_mut() {
                q.sent_at.get_or_insert(t);
            }
        }
        let n = match &self.shared.wake {
            Some(wake) if self.transport.supports_wake() => {
                // Announce the sleep first, then look at the queues: a hand-off after this
                // point either is seen by `read_wait` or wakes the read below.
                wake.sleeping();
                let wait = self.read_wait(now);
                let n = self.transport.read_wake(buf, wait, wake);
                wake.awake();
                n
            }
            _ => {
                let wait = self.read_wait(now);
                self.transport.read(buf, wait)
            }
        }
        .map_err(|e| Death::ConnectionLost(format!("read from {}: {e}", self.transport.describe())))?;
        if n > 0 {
            let now = system_now();
            let mut payloads = std::mem::take(&mut self.payloads);
            payloads.clear();
            self.sq.receive(now, &buf[..n], &mut |p| {
                payloads.push(p.len() as u8);
                payloads.extend_from_slice(p);
            });
            let mut rest = &payloads[..];
            while let Some((&len, tail)) = rest.split_first() {
                let (p, tail) = tail.split_at((len as usize).min(tail.len()));
                self.dispatch(now, p)?;
                rest = tail;
            }
            self.payloads = payloads;
        }
        let run = self.sq.impossible_ack_run();
        if run >= RESET_ACK_RUN && !matches!(self.phase, Phase::Identify { answered: false, .. }) {
            return Err(Death::Reset(format!(
                "{run} blocks in a row acked sequence numbers never sent: its sequence restarted"
            )));
        }
        let now = system_now();
        if let Some(since) = self.sq.ack_wait_since() {
            let limit = self.tuning.no_ack_timeout.as_secs_f64();
            if now - since > limit {
                // Silence from the very start is best described as an unanswered identify.
                if matches!(self.phase, Phase::Identify { answered: false, .. }) {
                    return Err(Death::IdentifyTimeout(self.identify_timeout));
                }
                return Err(Death::NoAck(limit));
            }
        }
        if self.sq.is_idle() && self.held.is_none() {
            self.shared.idle_upto.store(self.taken, Ordering::Release);
        }
        self.publish_stats();
        self.shared.notify.notify();
        Ok(())
    }

    /// Moves caller messages into the serial queue while it has room.
    fn take_outgoing(&mut self) {
        if !matches!(self.phase, Phase::Running) {
            return;
        }
        while let Some(item) = self.shared.urgent.pop() {
            if self.sq.push_urgent(item.cmd).is_err() {
                self.shared.urgent_dropped.fetch_add(1, Ordering::Relaxed);
            } else {
                self.urgent.pushed(item.relay);
            }
        }
        while self.sq.len() < self.user_capacity {
            let Some(item) = self.held.take().or_else(|| self.shared.outgoing.pop()) else {
                break;
            };
            if let Err(cmd) = self.sq.push(item.cmd, item.min_clock, item.req_clock) {
                self.held = Some(Outgoing { cmd, ..item });
                break;
            }
            self.taken += 1;
        }
        self.shared.taken.store(self.taken, Ordering::Release);
    }

    /// How long the next read may wait.
    fn read_wait(&self, now: f64) -> Duration {
        let mut wait = self.tuning.max_read_wait.as_secs_f64();
        if let Some(at) = self.sq.poll_at() {
            wait = wait.min(at - now);
        }
        if self.sq.has_upcoming() {
            wait = wait.min(self.tuning.upcoming_read_wait.as_secs_f64());
        }
        if !matches!(self.phase, Phase::Identify { .. } | Phase::Uptime { .. }) && self.clock_query.is_none()
        {
            wait = wait.min(self.next_clock_at - now);
        }
        if self.shared.armed.load(Ordering::Acquire) > 0 {
            // A homing group relies on this thread: read in short slices while one is
            // registered. (Relayed triggers also wake it at once; without the slices, homing
            // across two MCUs ended in communication timeouts every time — not understood yet.)
            wait = wait.min(ARMED_READ_WAIT);
        }
        // Work waiting to be taken: don't sleep — unless the serial queue is full (then a
        // zero wait would spin until the MCU frees room). Only published items count: one whose
        // producer was interrupted mid-push is published when that producer runs again, which
        // (SCHED_FIFO, same core, lower priority) needs this thread to block; a waking producer
        // (`send`, urgent) then ends the wait at once, a clocked one is taken within the slice.
        let room = self.sq.len() < self.user_capacity;
        if matches!(self.phase, Phase::Running)
            && (self.shared.urgent.has_ready()
                || (room && self.held.is_none() && self.shared.outgoing.has_ready()))
        {
            wait = 0.0;
        }
        Duration::try_from_secs_f64(wait.max(0.0)).unwrap_or(Duration::ZERO)
    }

    /// Handshake steps, clock queries and their deadlines. Requests whose block was acked
    /// but whose answer did not come within `identify_retry` are sent again: MCU → host
    /// traffic is not retransmitted, so a lost answer is only recovered this way.
    fn run_timers(&mut self, now: f64) -> Result<(), Death> {
        let retry = self.tuning.identify_retry.as_secs_f64();
        let idle = self.sq.is_idle();
        // Written `retry` ago and still unanswered: the block or its answer was lost (a block
        // lost on the way out is resent by the serial queue well within that time).
        let query_lost = self
            .clock_query
            .is_some_and(|q| q.sent_at.is_some_and(|t| now - t >= retry));
        match &mut self.phase {
            Phase::Identify {
                offset,
                deadline,
                last_sent,
                answered,
                ..
            } => {
                if now > *deadline {
                    return Err(if *answered {
                        Death::Handshake(format!(
                            "identify stopped answering at offset {offset} (no answer within {} s)",
                            self.response_timeout
                        ))
                    } else {
                        Death::IdentifyTimeout(self.identify_timeout)
                    });
                }
                if now - *last_sent >= retry && idle {
                    *last_sent = now;
                    let cmd = self
                        .dict
                        .encode("identify", &[*offset, IDENTIFY_CHUNK])
                        .map_err(|e| Death::Handshake(e.to_string()))?;
                    // The queue is idle here, so there is room.
                    let _ = self.sq.push(cmd, 0, 0);
                }
                Ok(())
            }
            Phase::Uptime { deadline, get_uptime } => {
                if now > *deadline {
                    return Err(Death::Handshake(format!(
                        "no answer to get_uptime within {} s",
                        self.response_timeout
                    )));
                }
                if query_lost {
                    let cmd = *get_uptime;
                    self.query_clock(now, cmd);
                }
                Ok(())
            }
            Phase::InitialClock { deadline, .. } => {
                if now > *deadline {
                    return Err(Death::Handshake(format!(
                        "no answer to get_clock within {} s",
                        self.response_timeout
                    )));
                }
                self.clock_timer(now, query_lost);
                Ok(())
            }
            Phase::Running => {
                self.clock_timer(now, query_lost);
                Ok(())
            }
        }
    }

    /// Sends `cmd` (get_uptime or get_clock) with its write time recorded.
    fn query_clock(&mut self, now: f64, cmd: Cmd) {
        self.sq.take_marked_sent();
        if self.sq.push_marked(cmd).is_ok() {
            self.clock_query = Some(ClockQuery {
                queued_at: now,
                sent_at: None,
            });
        }
    }

    fn clock_timer(&mut self, now: f64, query_lost: bool) {
        if let Some(q) = self.clock_query {
            if !query_lost && now - q.queued_at <= self.response_timeout {
                return;
            }
            // Lost (or answered to someone else's query): ask again.
            self.clock_query = None;
            self.next_clock_at = now;
        }
        if now >= self.next_clock_at {
            if let Some(cmd) = self.known.get_clock {
                self.query_clock(now, cmd);
            }
        }
    }

    /// Handles one received payload (one or more messages).
    fn dispatch(&mut self, now: f64, payload: &[u8]) -> Result<(), Death> {
        let dict = self.dict.clone();
        let mut rest = payload;
        while !rest.is_empty() {
            let Some((id, id_len)) = Dictionary::peek_id(rest) else {
                self.undecodable += 1;
                break;
            };
            let Some((_, def)) = dict.message_by_id(id) else {
                // Unknown length: the rest of the payload cannot be split.
                self.undecodable += 1;
                break;
            };
            let mut vals = [Value::Int(0); MAX_STACK_PARAMS];
            let used = match decode_params_into(&def.params, &rest[id_len..], &mut vals) {
                Some((_, used)) => used,
                None => match dict.decode_one(rest) {
                    Ok((_, total)) => total - id_len,
                    Err(_) => {
                        self.undecodable += 1;
                        break;
                    }
                },
            };
            let msg = &rest[..id_len + used];
            rest = &rest[id_len + used..];
            self.handle(now, id, &vals, &dict)?;
            if self.shared.waiter_count.load(Ordering::Acquire) > 0 {
                self.offer_to_waiters(&dict, msg);
            }
        }
        Ok(())
    }

    /// The IO thread's own use of a message.
    fn handle(&mut self, now: f64, id: u32, vals: &[Value<'_>], dict: &Arc<Dictionary>) -> Result<(), Death> {
        let int = |i: usize| vals.get(i).map_or(0, |v| v.int());
        if id == crate::proto::ID_IDENTIFY_RESPONSE {
            let chunk = match vals.get(1) {
                Some(Value::Bytes(b)) => *b,
                _ => &[],
            };
            return self.identify_chunk(now, int(0), chunk);
        }
        let k = self.known;
        if Some(id) == k.clock {
            self.clock_reply(now, int(0) as u32);
        } else if Some(id) == k.uptime {
            if let Phase::Uptime { .. } = self.phase {
                let clock = ((int(0) as u64) << 32) | (int(1) as u64 & 0xFFFF_FFFF);
                let sent = self.clock_query.take().and_then(|q| q.sent_at);
                self.sync.start(clock, sent.unwrap_or(now), now);
                self.publish_clock();
                self.next_clock_at = sent.unwrap_or(now) + self.tuning.initial_clock_spacing.as_secs_f64();
                self.phase = Phase::InitialClock {
                    count: 0,
                    answers: 0,
                    deadline: now + self.response_timeout,
                };
            }
        } else if Some(id) == k.stats {
            self.mcu_stats(int(0), int(1), int(2));
        } else if Some(id) == k.trsync_state {
            let clock = self.shared.clock.load().extend(int(3) as u32, now);
            crate::trsync::on_state(&self.shared, now, int(0), int(1) != 0, int(2), clock);
        } else if Some(id) == k.analog_in_state {
            if let Some(slot) = usize::try_from(int(0))
                .ok()
                .and_then(|o| self.shared.analog.get(o))
            {
                let count = (((slot.load(Ordering::Relaxed) >> 16) & 0xFFFF) % 0xFFFF) + 1;
                let packed = ((int(1) as u64 & 0xFFFF_FFFF) << 32) | (count << 16) | (int(2) as u64 & 0xFFFF);
                slot.store(packed, Ordering::Release);
            }
        } else if Some(id) == k.counter_state {
            if let Some(slot) = usize::try_from(int(0))
                .ok()
                .and_then(|o| self.shared.counters.get(o))
            {
                slot.store(int(1) as u32, int(2) as u32, int(3) as u32);
            }
        } else if Some(id) == k.thermocouple_result {
            if let Some(slot) = usize::try_from(int(0))
                .ok()
                .and_then(|o| self.shared.thermocouples.get(o))
            {
                slot.store(int(1) as u32, int(2) as u32, int(3) as u32);
            }
        } else if Some(id) == k.starting && matches!(self.phase, Phase::Running) {
            // Sent once by a freshly booted MCU: after the handshake it means a restart.
            return Err(Death::Reset("it sent 'starting'".into()));
        } else if Some(id) == k.shutdown || Some(id) == k.is_shutdown {
            let sid = if Some(id) == k.shutdown { int(1) } else { int(0) };
            let reason = u32::try_from(sid)
                .ok()
                .and_then(|s| dict.static_string(s))
                .map_or_else(|| format!("static_string_id {sid}"), str::to_owned);
            self.record_shutdown(reason);
        }
        Ok(())
    }

    fn identify_chunk(&mut self, now: f64, chunk_offset: i64, chunk: &[u8]) -> Result<(), Death> {
        let Phase::Identify {
            offset,
            data,
            deadline,
            last_sent,
            answered,
        } = &mut self.phase
        else {
            return Ok(());
        };
        if chunk_offset != *offset {
            return Ok(()); // a duplicate answer to a resent request
        }
        *answered = true;
        if !chunk.is_empty() {
            if data.len() + chunk.len() > crate::dict::MAX_DICT_JSON {
                return Err(Death::Dictionary(format!(
                    "identify data larger than {} bytes",
                    crate::dict::MAX_DICT_JSON
                )));
            }
            data.extend_from_slice(chunk);
            *offset += chunk.len() as i64;
            *deadline = now + self.response_timeout;
            *last_sent = now;
            let cmd = self
                .dict
                .encode("identify", &[*offset, IDENTIFY_CHUNK])
                .map_err(|e| Death::Handshake(e.to_string()))?;
            let _ = self.sq.push(cmd, 0, 0);
            return Ok(());
        }
        let dict = Dictionary::from_compressed(data).map_err(|e| Death::Dictionary(e.to_string()))?;
        self.start_with_dictionary(now, dict)
    }

    /// The dictionary is complete: look up what the link needs and ask for the uptime.
    fn start_with_dictionary(&mut self, now: f64, dict: Dictionary) -> Result<(), Death> {
        let hs = |e: crate::dict::DictError| Death::Handshake(e.to_string());
        let freq = dict.clock_freq().map_err(|e| Death::Dictionary(e.to_string()))?;
        let get_uptime = dict.encode("get_uptime", &[]).map_err(hs)?;
        self.known = Known {
            get_clock: Some(dict.encode("get_clock", &[]).map_err(hs)?),
            clock: Some(dict.response("clock").map_err(hs)?.id),
            uptime: Some(dict.response("uptime").map_err(hs)?.id),
            shutdown: dict.response("shutdown").ok().map(|d| d.id),
            is_shutdown: dict.response("is_shutdown").ok().map(|d| d.id),
            starting: dict.response("starting").ok().map(|d| d.id),
            trsync_state: dict.response("trsync_state").ok().map(|d| d.id),
            analog_in_state: dict.response("analog_in_state").ok().map(|d| d.id),
            counter_state: dict.response("counter_state").ok().map(|d| d.id),
            thermocouple_result: dict.response("thermocouple_result").ok().map(|d| d.id),
            stats: dict.response("stats").ok().map(|d| d.id),
        };
        self.sq.set_receive_window(dict.receive_window());
        self.nominal_freq = freq;
        self.sumsq_base = dict.config_f64("STATS_SUMSQ_BASE").unwrap_or(256.0);
        self.sync = ClockSync::new(freq);
        let dict = Arc::new(dict);
        self.dict = dict.clone();
        let _ = self.shared.dict.set(dict);
        self.query_clock(now, get_uptime);
        self.phase = Phase::Uptime {
            deadline: now + self.response_timeout,
            get_uptime,
        };
        Ok(())
    }

    fn clock_reply(&mut self, now: f64, wire: u32) {
        if !matches!(self.phase, Phase::InitialClock { .. } | Phase::Running) {
            return; // the pending query is get_uptime
        }
        let Some(ClockQuery {
            sent_at: Some(sent), ..
        }) = self.clock_query
        else {
            return; // an answer to someone else's get_clock
        };
        self.clock_query = None;
        let used = matches!(
            self.sync.handle_clock(wire, sent, now),
            Sample::Accepted | Sample::Reset
        );
        self.publish_clock();
        let spacing = self.tuning.initial_clock_spacing.as_secs_f64();
        match &mut self.phase {
            Phase::InitialClock {
                count,
                answers,
                deadline,
            } => {
                *count += u32::from(used);
                *answers += 1;
                *deadline = now + self.response_timeout;
                self.next_clock_at = sent + spacing;
                let wanted = self.tuning.initial_clock_queries;
                // Slow answers are asked again, but a link that is always slow still connects.
                if *count >= wanted || *answers >= 3 * wanted {
                    self.phase = Phase::Running;
                    self.fast_clock_until = sent + self.tuning.fast_clock_duration.as_secs_f64();
                    self.shared.state.store(RUNNING, Ordering::Release);
                }
            }
            _ if sent < self.fast_clock_until => self.next_clock_at = sent + spacing,
            _ => self.next_clock_at = sent + self.tuning.clock_interval.as_secs_f64(),
        }
    }

    /// Klipper's reading of `stats count sum sumsq` (sums of main-loop task ticks; `sumsq` is
    /// in units of `STATS_SUMSQ_BASE` ticks²).
    fn mcu_stats(&mut self, count: i64, sum: i64, sumsq: i64) {
        let (count, sum, sumsq) = (count as u32 as f64, sum as u32 as f64, sumsq as u32 as f64);
        let freq = self.nominal_freq;
        self.mcu_stats_reports += 1;
        self.mcu_awake = sum / freq;
        if count > 0.0 {
            let c = 1.0 / (count * freq);
            self.mcu_task_avg = sum * c;
            let diff = count * sumsq * self.sumsq_base - sum * sum;
            self.mcu_task_stddev = c * diff.max(0.0).sqrt();
        }
    }

    fn publish_clock(&mut self) {
        let est = self.sync.estimate();
        self.sq.set_clock_est(est);
        self.shared.clock.store(est);
    }

    fn record_shutdown(&mut self, reason: String) {
        {
            let mut s = lock(&self.shared.shutdown);
            if s.is_none() {
                *s = Some(reason.clone());
            }
        }
        self.shared.is_shutdown.store(true, Ordering::Release);
        let mut w = lock(&self.shared.waiters);
        for waiter in w.iter_mut() {
            if waiter.result.is_none() && !ANSWERED_WHEN_SHUT_DOWN.contains(&waiter.response.as_str()) {
                waiter.result = Some(Err(WaitFail::Shutdown(reason.clone())));
            }
        }
    }

    /// Gives a decoded copy of `msg` to the first waiter it matches (allocates).
    fn offer_to_waiters(&mut self, dict: &Dictionary, msg: &[u8]) {
        let Ok((decoded, _)) = dict.decode_one(msg) else {
            return;
        };
        let mut w = lock(&self.shared.waiters);
        let found = w.iter_mut().find(|x| {
            x.result.is_none()
                && x.response == decoded.name
                && x.matcher.as_ref().is_none_or(|(f, v)| decoded.get(f) == Some(*v))
        });
        if let Some(waiter) = found {
            waiter.result = Some(Ok(decoded));
        }
    }

    fn publish_stats(&self) {
        let q = self.sq.stats();
        let est = self.sync.estimate();
        let stats = LinkStats {
            queue: q,
            min_lead_margin_ticks: q.min_lead_margin,
            clocked_msgs: q.clocked_sent,
            clock_residual_us: est.residual_us(),
            clock_freq: est.freq(),
            clock_samples: self.sync.samples(),
            clock_outliers: self.sync.outliers(),
            clock_slow: self.sync.slow(),
            undecodable_msgs: self.undecodable,
            mcu_awake: self.mcu_awake,
            mcu_task_avg: self.mcu_task_avg,
            mcu_task_stddev: self.mcu_task_stddev,
            mcu_stats_reports: self.mcu_stats_reports,
            urgent_dropped: self.shared.urgent_dropped.load(Ordering::Relaxed),
        };
        *lock(&self.shared.stats) = stats;
    }
}
