//! One MCU connection: an IO thread that owns the transport, and the [`McuLink`] handle the
//! rest of the host uses.
//!
//! The IO thread (module `io`) connects (dictionary through `identify`, 64-bit clock through
//! `get_uptime`, eight `get_clock` 50 ms apart for the first fit), then loops: read with a
//! short timeout, feed the [`crate::serialqueue::SerialQueue`], write what it releases, query
//! `get_clock` about every 0.98 s, dispatch responses. Callers hand messages over through a
//! bounded, preallocated queue that never spins on another thread (`rt_core::handoff`); the clock
//! estimate comes back through a seqlock.
//!
//! Every wait is bounded: connect by the identify/response timeouts, `send_clocked` on a full
//! queue by a stall timeout, `query` and `wait_idle` by their argument, and the link itself
//! dies when no ack arrives for [`LinkTuning::no_ack_timeout`].
//!
//! Allocation in the IO thread's steady state: none for sending, acks, retransmits and `clock`
//! replies; decoding a response into a [`Message`] allocates, which happens only for responses
//! some `query` waits for, for `shutdown`/`is_shutdown`, and during the handshake.

pub mod counter;
pub use counter::ThermocoupleReport;
mod io;
pub(crate) mod shared;

#[cfg(test)]
pub(crate) mod fake;
#[cfg(test)]
mod tests;

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crate::clocksync::ClockEstimate;
use crate::dict::{Cmd, Dictionary, Message};
use crate::serialqueue::{MarginHook, QueueStats};
use crate::transport::Transport;
use shared::{lock, Outgoing, Shared, WaitFail, Waiter, ANSWERED_WHEN_SHUT_DOWN, DEAD, RUNNING};

/// What every link needs to know.
#[derive(Debug, Clone, PartialEq)]
pub struct LinkOptions {
    /// The MCU's name in messages, e.g. `mcu`.
    pub name: String,
    /// How long to wait for the first `identify` answer.
    pub identify_timeout: Duration,
    /// How long to wait for any other handshake answer.
    pub response_timeout: Duration,
    /// Messages that can wait in the hand-off queue (and again in the serial queue).
    pub queue_capacity: usize,
}

impl Default for LinkOptions {
    fn default() -> Self {
        LinkOptions {
            name: "mcu".into(),
            identify_timeout: Duration::from_secs(5),
            response_timeout: Duration::from_secs(2),
            queue_capacity: 4096,
        }
    }
}

/// Less common knobs, with defaults from the protocol (see [`McuLink::connect_with`]).
pub struct LinkTuning {
    /// The link dies when unacked data has waited this long for an ack.
    pub no_ack_timeout: Duration,
    /// `send_clocked` fails when the queue stayed full without progress this long.
    pub queue_stall_timeout: Duration,
    /// Period of `get_clock` queries once connected (0.98 s: off the beat of 1 s work).
    pub clock_interval: Duration,
    /// Spacing of the initial `get_clock` queries.
    pub initial_clock_spacing: Duration,
    /// Number of initial `get_clock` samples before the link is ready (slow answers are
    /// asked again, up to three times this many queries).
    pub initial_clock_queries: u32,
    /// After the link is ready, `get_clock` keeps the initial spacing for this long, so the
    /// frequency is known to a few ppm before the first moves are planned in this clock (a
    /// few hundred bytes a second; then every `clock_interval`).
    pub fast_clock_duration: Duration,
    /// Resend `identify` after this long without an answer (covers a lost first block).
    pub identify_retry: Duration,
    /// Longest read wait of the IO thread (bounds the latency of a new message).
    pub max_read_wait: Duration,
    /// Read wait while messages wait for their `min_clock`.
    pub upcoming_read_wait: Duration,
    /// Called by the IO thread with `(req_clock, lead margin ticks)` for each clocked message.
    pub margin_hook: Option<MarginHook>,
    /// Run first inside the IO thread (e.g. pinning it and giving it a real-time priority).
    pub thread_setup: Option<Box<dyn FnOnce() + Send>>,
}

impl Default for LinkTuning {
    fn default() -> Self {
        LinkTuning {
            no_ack_timeout: Duration::from_secs(5),
            queue_stall_timeout: Duration::from_secs(10),
            clock_interval: Duration::from_secs_f64(0.9839),
            initial_clock_spacing: Duration::from_millis(50),
            initial_clock_queries: 8,
            fast_clock_duration: Duration::from_secs(3),
            identify_retry: Duration::from_millis(250),
            max_read_wait: Duration::from_millis(5),
            upcoming_read_wait: Duration::from_millis(1),
            margin_hook: None,
            thread_setup: None,
        }
    }
}

impl std::fmt::Debug for LinkTuning {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LinkTuning")
            .field("no_ack_timeout", &self.no_ack_timeout)
            .field("queue_stall_timeout", &self.queue_stall_timeout)
            .field("clock_interval", &self.clock_interval)
            .field("margin_hook", &self.margin_hook.is_some())
            .finish_non_exhaustive()
    }
}

/// Errors of a link; each names the MCU and what happened.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LinkError {
    /// The MCU never answered the first `identify`.
    #[error("mcu '{mcu}': no answer to identify within {secs} s")]
    IdentifyTimeout { mcu: String, secs: f64 },
    /// The dictionary it served is unusable.
    #[error("mcu '{mcu}': bad data dictionary: {detail}")]
    Dictionary { mcu: String, detail: String },
    /// Another handshake step failed (a missing command, no answer to `get_clock`, …).
    #[error("mcu '{mcu}': {detail}")]
    Handshake { mcu: String, detail: String },
    /// The transport failed or the peer hung up.
    #[error("mcu '{mcu}': connection lost ({detail})")]
    ConnectionLost { mcu: String, detail: String },
    /// The MCU reported a shutdown.
    #[error("mcu '{mcu}': shut down: {reason}")]
    Shutdown { mcu: String, reason: String },
    /// The MCU restarted while connected (it sent `starting`, its sequence numbers restarted,
    /// or `get_config` reported it unconfigured); `detail` says which.
    #[error("mcu '{mcu}': MCU reset during the print ({detail})")]
    Reset { mcu: String, detail: String },
    /// Data stayed unacked too long.
    #[error("mcu '{mcu}': no ack for {secs:.1} s")]
    NoAck { mcu: String, secs: f64 },
    /// A query got no matching response in time.
    #[error("mcu '{mcu}': no '{response}' response within {secs} s")]
    Timeout {
        mcu: String,
        response: String,
        secs: f64,
    },
    /// `wait_idle` ran out of time.
    #[error("mcu '{mcu}': queued messages not all acked within {secs} s")]
    NotIdle { mcu: String, secs: f64 },
    /// The send queue stayed full without progress.
    #[error("mcu '{mcu}': send queue full and not moving for {secs} s")]
    QueueStalled { mcu: String, secs: f64 },
    /// The link was closed.
    #[error("mcu '{mcu}': link closed")]
    Closed { mcu: String },
    /// The IO thread could not be started.
    #[error("mcu '{mcu}': cannot start IO thread: {detail}")]
    Spawn { mcu: String, detail: String },
}

/// A snapshot of a link's counters.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct LinkStats {
    /// The serial queue's counters.
    pub queue: QueueStats,
    /// Smallest lead margin of a clocked message (ticks), `None` before the first.
    pub min_lead_margin_ticks: Option<i64>,
    /// Clocked messages (`req_clock > 0`) written.
    pub clocked_msgs: u64,
    /// Clock fit residual, µs.
    pub clock_residual_us: f64,
    /// Estimated MCU ticks per system second.
    pub clock_freq: f64,
    /// Clock samples used in the fit.
    pub clock_samples: u64,
    /// Clock samples dropped as outliers.
    pub clock_outliers: u64,
    /// Clock samples skipped for a slow round trip.
    pub clock_slow: u64,
    /// Received messages the dictionary could not decode.
    pub undecodable_msgs: u64,
    /// From the MCU's last `stats` report: seconds of MCU time its main loop was busy in the
    /// report period (`sum / CLOCK_FREQ`).
    pub mcu_awake: f64,
    /// Mean main-loop task time, seconds (`sum / (count · CLOCK_FREQ)`).
    pub mcu_task_avg: f64,
    /// Standard deviation of the task time, seconds
    /// (`√(count · sumsq · STATS_SUMSQ_BASE − sum²) / (count · CLOCK_FREQ)`).
    pub mcu_task_stddev: f64,
    /// `stats` reports received.
    pub mcu_stats_reports: u64,
    /// Urgent (homing) messages lost because their queue was full (should stay 0).
    pub urgent_dropped: u64,
}

/// One line in the manner of Klipper's periodic stats (`name: key=value …`; the caller adds
/// the MCU's name).
impl std::fmt::Display for LinkStats {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let q = &self.queue;
        write!(
            f,
            "mcu_awake={:.3} mcu_task_avg={:.6} mcu_task_stddev={:.6} bytes_write={} bytes_read={} \
             bytes_retransmit={} bytes_invalid={} retransmits={} send_seq={} receive_seq={} \
             srtt={:.3} rttvar={:.3} rto={:.3} ready_bytes={} upcoming_bytes={} freq={:.0} \
             clock_residual_us={:.1} clock_outliers={} clock_slow={}",
            self.mcu_awake,
            self.mcu_task_avg,
            self.mcu_task_stddev,
            q.bytes_write,
            q.bytes_read,
            q.bytes_retransmit,
            q.bytes_invalid,
            q.retransmits,
            q.send_seq,
            q.receive_seq,
            q.srtt,
            q.rttvar,
            q.rto,
            q.ready_bytes,
            q.upcoming_bytes,
            self.clock_freq,
            self.clock_residual_us,
            self.clock_outliers,
            self.clock_slow,
        )?;
        match self.min_lead_margin_ticks {
            Some(m) => write!(f, " min_lead_margin_ticks={m}"),
            None => Ok(()),
        }
    }
}

/// The handle of one MCU connection.
#[derive(Debug)]
pub struct McuLink {
    shared: Arc<Shared>,
    dict: Arc<Dictionary>,
    thread: Option<JoinHandle<()>>,
    opts: LinkOptions,
    stall_timeout: Duration,
}

impl McuLink {
    /// Connects over `transport` with default tuning: spawns the IO thread `io-<name>`, reads
    /// the dictionary and synchronises the clock. Returns once the link is ready.
    pub fn connect(transport: Box<dyn Transport>, opts: LinkOptions) -> Result<McuLink, LinkError> {
        McuLink::connect_with(transport, opts, LinkTuning::default())
    }

    /// [`Self::connect`] with explicit tuning.
    pub fn connect_with(
        transport: Box<dyn Transport>,
        opts: LinkOptions,
        tuning: LinkTuning,
    ) -> Result<McuLink, LinkError> {
        let shared = Arc::new(Shared::new(&opts.name, opts.queue_capacity));
        let stall_timeout = tuning.queue_stall_timeout;
        let mut tuning = tuning;
        let setup = tuning.thread_setup.take();
        let io = io::IoThread::new(shared.clone(), transport, &opts, tuning);
        let thread = std::thread::Builder::new()
            .name(format!("io-{}", opts.name))
            .spawn(move || {
                if let Some(setup) = setup {
                    setup();
                }
                io.run()
            })
            .map_err(|e| LinkError::Spawn {
                mcu: opts.name.clone(),
                detail: e.to_string(),
            })?;
        let mut link = McuLink {
            shared,
            dict: Arc::new(Dictionary::bootstrap()),
            thread: Some(thread),
            opts,
            stall_timeout,
        };
        // The IO thread enforces every handshake deadline itself; this bound only guards
        // against a bug there.
        let guard = link.opts.identify_timeout + link.opts.response_timeout * 64 + Duration::from_secs(10);
        let sh = link.shared.clone();
        let ready = sh.notify.wait_until(Instant::now() + guard, || {
            sh.state.load(Ordering::Acquire) != shared::CONNECTING
        });
        if let Some(e) = link.shared.dead_error() {
            link.stop_and_join();
            return Err(e);
        }
        match (ready, link.shared.dict.get()) {
            (true, Some(dict)) => {
                link.dict = dict.clone();
                Ok(link)
            }
            _ => {
                link.shared
                    .die(shared::Death::Handshake("connect did not finish".into()));
                link.stop_and_join();
                Err(link.shared.dead_error().unwrap_or(LinkError::Closed {
                    mcu: link.opts.name.clone(),
                }))
            }
        }
    }

    /// The state shared with the IO thread.
    pub(crate) fn shared(&self) -> &Arc<Shared> {
        &self.shared
    }

    /// The MCU's name.
    pub fn name(&self) -> &str {
        &self.opts.name
    }

    /// The MCU's data dictionary.
    pub fn dictionary(&self) -> &Dictionary {
        &self.dict
    }

    /// The MCU's dictionary, shareable with other threads.
    pub fn dictionary_arc(&self) -> Arc<Dictionary> {
        self.dict.clone()
    }

    /// The latest clock estimate (lock-free).
    pub fn clock(&self) -> ClockEstimate {
        self.shared.clock.load()
    }

    /// Seconds of `CLOCK_MONOTONIC`: the system time clock sync works in.
    pub fn system_now() -> f64 {
        io::system_now()
    }

    /// Queues a plain message (sent as soon as possible, in order with other plain ones).
    /// Allowed after an MCU shutdown (e.g. `clear_shutdown`); fails if the link died.
    pub fn send(&self, cmd: Cmd) -> Result<(), LinkError> {
        self.enqueue(Outgoing {
            cmd,
            min_clock: 0,
            req_clock: 0,
        })?;
        // Plain messages are wanted now (homing set-up, queries): end the IO thread's read
        // wait. Clocked ones (steps, ≥ 100 ms ahead) are picked up within its read slice,
        // which lets it pack them into full blocks.
        self.shared.wake_io();
        Ok(())
    }

    /// Queues a message not to be sent before the MCU clock reaches `min_clock`, ordered by
    /// `req_clock`. Blocks (sleeping, bounded) while the queue is full. Fails if the link died
    /// or the MCU shut down.
    pub fn send_clocked(&self, cmd: Cmd, min_clock: u64, req_clock: u64) -> Result<(), LinkError> {
        if let Some(e) = self.shared.shutdown_error() {
            return Err(e);
        }
        self.enqueue(Outgoing {
            cmd,
            min_clock,
            req_clock,
        })
    }

    fn enqueue(&self, mut item: Outgoing) -> Result<(), LinkError> {
        let sh = &*self.shared;
        let mut last_taken = sh.taken.load(Ordering::Acquire);
        let mut last_progress = Instant::now();
        loop {
            if let Some(e) = sh.dead_error() {
                return Err(e);
            }
            match sh.outgoing.push(item) {
                Ok(()) => {
                    sh.submitted.fetch_add(1, Ordering::AcqRel);
                    return Ok(());
                }
                Err(back) => item = back,
            }
            sh.notify
                .wait_until(Instant::now() + Duration::from_millis(20), || {
                    !sh.outgoing.is_full() || sh.state.load(Ordering::Acquire) == DEAD
                });
            let taken = sh.taken.load(Ordering::Acquire);
            if taken != last_taken {
                last_taken = taken;
                last_progress = Instant::now();
            } else if last_progress.elapsed() > self.stall_timeout {
                return Err(LinkError::QueueStalled {
                    mcu: self.opts.name.clone(),
                    secs: self.stall_timeout.as_secs_f64(),
                });
            }
        }
    }

    /// Sends `cmd` and waits for the first response named `response` (whose field
    /// `matcher.0` equals `matcher.1`, if given) that arrives after the call started.
    pub fn query(
        &self,
        cmd: Cmd,
        response: &str,
        matcher: Option<(&str, i64)>,
        timeout: Duration,
    ) -> Result<Message, LinkError> {
        let sh = &*self.shared;
        let deadline = Instant::now() + timeout;
        let id = sh.next_waiter.fetch_add(1, Ordering::Relaxed);
        {
            let mut w = lock(&sh.waiters);
            w.push(Waiter {
                id,
                response: response.to_owned(),
                matcher: matcher.map(|(f, v)| (f.to_owned(), v)),
                result: None,
            });
            sh.waiter_count.store(w.len(), Ordering::Release);
        }
        let sent = self.send(cmd);
        let take = |sh: &Shared| -> Option<Result<Message, WaitFail>> {
            let mut w = lock(&sh.waiters);
            let i = w.iter().position(|x| x.id == id)?;
            w[i].result.as_ref()?;
            let r = w.remove(i).result;
            sh.waiter_count.store(w.len(), Ordering::Release);
            r
        };
        let mut result = None;
        if sent.is_ok() {
            sh.notify.wait_until(deadline, || {
                result = take(sh);
                result.is_some() || sh.state.load(Ordering::Acquire) == DEAD
            });
        }
        // Remove the waiter whatever happened.
        {
            let mut w = lock(&sh.waiters);
            if let Some(i) = w.iter().position(|x| x.id == id) {
                if result.is_none() {
                    result = w[i].result.take();
                }
                w.remove(i);
            }
            sh.waiter_count.store(w.len(), Ordering::Release);
        }
        sent?;
        match result {
            Some(Ok(msg)) => Ok(msg),
            Some(Err(WaitFail::Shutdown(reason))) => Err(LinkError::Shutdown {
                mcu: self.opts.name.clone(),
                reason,
            }),
            None => Err(sh
                .dead_error()
                .or_else(|| {
                    (!ANSWERED_WHEN_SHUT_DOWN.contains(&response))
                        .then(|| sh.shutdown_error())
                        .flatten()
                })
                .unwrap_or(LinkError::Timeout {
                    mcu: self.opts.name.clone(),
                    response: response.to_owned(),
                    secs: timeout.as_secs_f64(),
                })),
        }
    }

    /// Asks `get_config` and checks the MCU is still configured: `is_config=0` from an MCU the
    /// host configured means it reset, and the link dies with [`LinkError::Reset`] (so every
    /// later send fails too). Call only after `finalize_config`.
    pub fn expect_configured(&self, timeout: Duration) -> Result<Message, LinkError> {
        let cmd = self
            .dict
            .encode("get_config", &[])
            .map_err(|e| LinkError::Handshake {
                mcu: self.opts.name.clone(),
                detail: e.to_string(),
            })?;
        let msg = self.query(cmd, "config", None, timeout)?;
        if msg.get("is_config") == Some(0) {
            let detail = "get_config reports is_config=0".to_owned();
            self.shared.die(shared::Death::Reset(detail.clone()));
            return Err(LinkError::Reset {
                mcu: self.opts.name.clone(),
                detail,
            });
        }
        Ok(msg)
    }

    /// Waits until every message queued before this call has been sent and acked.
    pub fn wait_idle(&self, timeout: Duration) -> Result<(), LinkError> {
        let sh = &*self.shared;
        let target = sh.submitted.load(Ordering::Acquire);
        let done = sh.notify.wait_until(Instant::now() + timeout, || {
            sh.idle_upto.load(Ordering::Acquire) >= target || sh.state.load(Ordering::Acquire) == DEAD
        });
        if let Some(e) = sh.dead_error() {
            return Err(e);
        }
        if done {
            Ok(())
        } else {
            Err(LinkError::NotIdle {
                mcu: self.opts.name.clone(),
                secs: timeout.as_secs_f64(),
            })
        }
    }

    /// Counters of the link.
    pub fn stats(&self) -> LinkStats {
        *lock(&self.shared.stats)
    }

    /// The latest `analog_in_state` report of analog input `oid` (< 64): `(count, next_clock,
    /// value)`, where `count` (mod 2^16, from 1) tells a new report from the one seen before;
    /// `None` before the first. Lock-free: the IO thread overwrites one slot per oid.
    pub fn analog_report(&self, oid: u8) -> Option<(u16, u32, u16)> {
        let v = self.shared.analog.get(usize::from(oid))?.load(Ordering::Acquire);
        let count = ((v >> 16) & 0xFFFF) as u16;
        (count != 0).then_some((count, (v >> 32) as u32, (v & 0xFFFF) as u16))
    }

    /// The latest `counter_state` report of pulse counter `oid` (< 64), `None` before the
    /// first. Lock-free (a seqlock the IO thread writes).
    pub fn counter_report(&self, oid: u8) -> Option<counter::CounterReport> {
        self.shared.counters.get(usize::from(oid))?.load()
    }

    /// The latest `thermocouple_result` of SPI temperature chip `oid` (< 64), `None` before
    /// the first. Lock-free (a seqlock the IO thread writes).
    pub fn thermocouple_report(&self, oid: u8) -> Option<ThermocoupleReport> {
        let r = self.shared.thermocouples.get(usize::from(oid))?.load()?;
        Some(ThermocoupleReport {
            serial: r.serial,
            next_clock: r.next_clock,
            value: r.count,
            fault: r.count_clock as u8,
        })
    }

    /// The MCU's shutdown reason, once it sent `shutdown` or `is_shutdown`.
    pub fn shutdown_reason(&self) -> Option<String> {
        lock(&self.shared.shutdown).clone()
    }

    /// Forgets the MCU's shutdown once it has left it (a `config_reset` brings a Klipper-style
    /// MCU back to the unconfigured, running state): clocked sends work again, and a later
    /// shutdown is recorded with its own reason.
    pub fn clear_shutdown(&self) {
        *lock(&self.shared.shutdown) = None;
        self.shared.is_shutdown.store(false, Ordering::Release);
    }

    /// Why the link died, if it did.
    pub fn error(&self) -> Option<LinkError> {
        self.shared.dead_error()
    }

    /// Stops the IO thread (without waiting for queued messages: call [`Self::wait_idle`]
    /// first to flush) and returns the final counters.
    pub fn close(mut self) -> LinkStats {
        self.stop_and_join();
        self.stats()
    }

    fn stop_and_join(&mut self) {
        self.shared.stop.store(true, Ordering::Release);
        self.shared.wake_io();
        if let Some(t) = self.thread.take() {
            // A panic in the IO thread has already marked the link dead (or will be seen as
            // closed); there is nothing more to report here.
            let _ = t.join();
        }
        if self.shared.state.load(Ordering::Acquire) == RUNNING {
            self.shared.die(shared::Death::Closed);
        }
    }
}

impl Drop for McuLink {
    fn drop(&mut self) {
        self.stop_and_join();
    }
}
