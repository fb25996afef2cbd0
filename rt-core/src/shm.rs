//! Shared-memory hand-off between processes (or threads) on iceoryx2 0.10 publish-subscribe,
//! with an iceoryx2 event service beside each channel for wake-ups (no busy loop).
//!
//! # Services (the contract for outside processes)
//!
//! | service name | pattern | payload | config |
//! |---|---|---|---|
//! | `cadence/<instance>/mcu/<mcu>/steps` | publish-subscribe | [`StepBatch`] | [`ChannelConfig::steps`] |
//! | `cadence/<instance>/mcu/<mcu>/steps` | event | — (notify after each send) | default |
//! | `cadence/<instance>/telemetry` | publish-subscribe | [`Telemetry`] | [`ChannelConfig::telemetry`] |
//! | `cadence/<instance>/telemetry` | event | — | default |
//!
//! The services that let the IO stage run in another process (MCU info, clock snapshots, IO
//! status and control) are the `cadence` library's (`cadence::io_process::payloads`), on these
//! channels with [`ChannelConfig::info`], [`ChannelConfig::latest`] and [`ChannelConfig::control`].
//!
//! Every process must open a service with the same settings (the `ChannelConfig` constructors)
//! and the same payload type names (`cadence::StepBatch.v2`, `cadence::Telemetry.v1`).
//!
//! # Payload layouts (`#[repr(C)]`, native endian, sizes asserted in tests)
//!
//! - [`WireMsg`] (80 bytes, align 8): `min_clock: u64` @0, `req_clock: u64` @8, `len: u8` @16,
//!   `data: [u8; 59]` @17 (one encoded MCU message, like `links::dict::Cmd`), 4 bytes padding.
//! - [`StepBatch`] (24 + 80·[`BATCH_MSGS`] = 5144 bytes, align 8): `seq: u64` @0,
//!   `mcu: u32` @8, `count: u32` @12, `t_ns: u64` @16 (CLOCK_MONOTONIC ns at hand-off),
//!   `msgs: [WireMsg; 64]` @24 (first `count` valid).
//! - [`Telemetry`] (160 bytes, align 8): `seq: u64` @0, `kind: u32` @8, `source: u32` @12,
//!   `t_ns: u64` @16, `count: u32` @24, 4 bytes padding, `values: [f64; 16]` @32.
//!
//! # No loss
//!
//! iceoryx2's safe overflow silently replaces the oldest unread sample when a subscriber's
//! buffer is full. Step channels turn it off: the publisher then retries (back-pressure) until
//! the subscriber has room, for at most `ChannelConfig::backpressure_timeout`, after which
//! [`ShmPublisher::send_with`] fails with [`ShmError::Backpressure`] (a stalled IO stage is a
//! fatal print error, never a silent loss). Each payload carries a sequence number the
//! publisher assigns (0, 1, 2, ...); [`ShmSubscriber`] checks it and reports a gap as
//! [`ShmError::Gap`]. Telemetry keeps safe overflow on (an outside monitor must never stall the
//! printer); its gaps are reported the same way and may be ignored.
//!
//! Stale resources of crashed processes are removed when a node is created ([`open_node`]),
//! including the half-created ones iceoryx2 itself would wait on for ever ([`stale`]).
//!
//! # No heap allocation per sample
//!
//! iceoryx2 0.10 allocates a small reference-counted bookkeeping object on the heap for every
//! loan (`Publisher::loan`, hence every [`ShmPublisher::send_with`]) with its stock service
//! types; the payload itself is in shared memory. Real-time publishers (the planner's step
//! channel) therefore use [`pooled::Ipc`]: `ipc::Service` with that bookkeeping taken from a
//! per-thread pool, so a publisher allocates only for its first loans and never again; it
//! interoperates with plain `ipc::Service` ports (same shared-memory layout). Receiving
//! (`Subscriber::receive`) does not allocate with either. rt-core's `tests/alloc_free.rs`
//! checks both facts.

use std::fmt::Debug;
use std::time::Duration;

use iceoryx2::node::Node;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::port::{BackpressureAction, BackpressureInfo};
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe;

/// Payload bytes of one MCU message (a block's payload: 64 - 5 bytes of framing).
pub const WIRE_MSG_DATA: usize = 59;
/// Messages per [`StepBatch`].
pub const BATCH_MSGS: usize = 64;
/// Values per [`Telemetry`] record.
pub const TELEMETRY_VALUES: usize = 16;

/// One encoded MCU message with its scheduling clocks (as Klipper's serialqueue keeps them).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("cadence::WireMsg.v1")]
pub struct WireMsg {
    /// Do not send before the MCU has this clock (0 = any time).
    pub min_clock: u64,
    /// The clock the message is for (its first step); the lead margin is measured against it.
    pub req_clock: u64,
    /// Valid bytes in `data`.
    pub len: u8,
    pub data: [u8; WIRE_MSG_DATA],
}

impl Default for WireMsg {
    fn default() -> Self {
        WireMsg {
            min_clock: 0,
            req_clock: 0,
            len: 0,
            data: [0; WIRE_MSG_DATA],
        }
    }
}

impl WireMsg {
    /// Wraps encoded bytes; `None` if longer than [`WIRE_MSG_DATA`].
    pub fn new(min_clock: u64, req_clock: u64, bytes: &[u8]) -> Option<WireMsg> {
        let mut m = WireMsg {
            min_clock,
            req_clock,
            len: u8::try_from(bytes.len()).ok()?,
            data: [0; WIRE_MSG_DATA],
        };
        m.data.get_mut(..bytes.len())?.copy_from_slice(bytes);
        Some(m)
    }

    /// The valid bytes (empty if `len` is corrupt).
    pub fn bytes(&self) -> &[u8] {
        self.data.get(..self.len as usize).unwrap_or(&[])
    }
}

/// A batch of messages for one MCU, planner side → that MCU's IO stage.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("cadence::StepBatch.v2")]
pub struct StepBatch {
    /// Assigned by the publisher: 0, 1, 2, ... per channel.
    pub seq: u64,
    /// MCU index (for logs; the channel already names the MCU).
    pub mcu: u32,
    /// Valid entries in `msgs`.
    pub count: u32,
    /// CLOCK_MONOTONIC ns when the publisher handed the batch over (hand-off latency).
    pub t_ns: u64,
    pub msgs: [WireMsg; BATCH_MSGS],
}

impl Default for StepBatch {
    fn default() -> Self {
        StepBatch {
            seq: 0,
            mcu: 0,
            count: 0,
            t_ns: 0,
            msgs: [WireMsg::default(); BATCH_MSGS],
        }
    }
}

impl StepBatch {
    /// The valid messages (clamped to the array if `count` is corrupt).
    pub fn messages(&self) -> &[WireMsg] {
        &self.msgs[..(self.count as usize).min(BATCH_MSGS)]
    }

    /// Appends a message; `false` when the batch is full.
    pub fn push(&mut self, m: WireMsg) -> bool {
        match self.msgs.get_mut(self.count as usize) {
            Some(slot) => {
                *slot = m;
                self.count += 1;
                true
            }
            None => false,
        }
    }
}

/// What a [`Telemetry`] record's values mean.
pub mod telemetry_kind {
    /// A histogram summary: values = [count, negative, min, p0.1, p1, p50, p99, p99.9, max,
    /// mean, ns_per_unit]; `source` names the histogram (see the binary's table).
    pub const HIST_SUMMARY: u32 = 1;
    /// Toolhead position: values = [print_time, x, y, z, e].
    pub const POSITION: u32 = 2;
    /// Counters: values = stage-defined statistics.
    pub const STATS: u32 = 3;
}

/// One telemetry record (histogram snapshot, statistics, position).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("cadence::Telemetry.v1")]
pub struct Telemetry {
    pub seq: u64,
    /// One of [`telemetry_kind`].
    pub kind: u32,
    /// Which stage/histogram/MCU produced it.
    pub source: u32,
    /// Nanoseconds of the host's monotonic clock since the print started.
    pub t_ns: u64,
    /// Valid entries in `values`.
    pub count: u32,
    pub values: [f64; TELEMETRY_VALUES],
}

impl Default for Telemetry {
    fn default() -> Self {
        Telemetry {
            seq: 0,
            kind: 0,
            source: 0,
            t_ns: 0,
            count: 0,
            values: [0.0; TELEMETRY_VALUES],
        }
    }
}

/// A payload with a publisher-assigned sequence number.
pub trait Sequenced: Debug + Default + ZeroCopySend + Copy + 'static {
    fn seq(&self) -> u64;
    fn set_seq(&mut self, seq: u64);
}

impl Sequenced for StepBatch {
    fn seq(&self) -> u64 {
        self.seq
    }
    fn set_seq(&mut self, seq: u64) {
        self.seq = seq;
    }
}

impl Sequenced for Telemetry {
    fn seq(&self) -> u64 {
        self.seq
    }
    fn set_seq(&mut self, seq: u64) {
        self.seq = seq;
    }
}

/// Errors of the shared-memory layer. iceoryx2's own error types are kept as text.
#[derive(Debug, thiserror::Error)]
pub enum ShmError {
    /// A service name that iceoryx2 rejects (too long, bad characters).
    #[error("invalid service name '{name}': {reason}")]
    Name { name: String, reason: String },
    /// Creating the node, service or a port failed (e.g. /dev/shm not writable, or another
    /// process opened the service with different settings).
    #[error("{op} '{service}': {reason}")]
    Setup {
        op: &'static str,
        service: String,
        reason: String,
    },
    /// The subscriber did not make room within the back-pressure bound.
    #[error("'{service}': subscriber did not take batch {seq} within {waited:?} (IO stage stalled)")]
    Backpressure {
        service: String,
        seq: u64,
        waited: Duration,
    },
    /// Loaning, sending, receiving or waiting failed.
    #[error("{op} on '{service}': {reason}")]
    Io {
        op: &'static str,
        service: String,
        reason: String,
    },
    /// A payload reached fewer subscribers than required: the subscriber is gone, or it had
    /// not connected yet (it connects on its first receive) and its buffer was full.
    #[error("'{service}': batch {seq} reached {got} of at least {need} subscribers")]
    Undelivered {
        service: String,
        seq: u64,
        got: usize,
        need: usize,
    },
    /// A sequence number was skipped: payloads were lost.
    #[error("'{service}': sequence gap: expected {expected}, got {got} ({} lost)", got.wrapping_sub(*expected))]
    Gap {
        service: String,
        expected: u64,
        got: u64,
    },
}

/// `cadence/<instance>/mcu/<mcu>/steps`.
pub fn steps_service_name(instance: &str, mcu: &str) -> String {
    format!("cadence/{instance}/mcu/{mcu}/steps")
}

/// `cadence/<instance>/telemetry`.
pub fn telemetry_service_name(instance: &str) -> String {
    format!("cadence/{instance}/telemetry")
}

/// Settings every process must open a channel with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ChannelConfig {
    /// Samples a subscriber can hold unread.
    pub buffer: usize,
    /// Samples kept for subscribers that connect later (0 for streams).
    pub history: usize,
    /// Overwrite the oldest unread sample when full (false = back-pressure).
    pub safe_overflow: bool,
    /// Longest a publisher waits for room before failing.
    pub backpressure_timeout: Duration,
    pub max_publishers: usize,
    pub max_subscribers: usize,
    /// A send that reaches fewer subscribers fails with [`ShmError::Undelivered`].
    pub min_receivers: usize,
}

impl ChannelConfig {
    /// MCU info: published once, kept as history for late subscribers ([`Self::latest`] with
    /// a smaller buffer).
    pub const fn info() -> ChannelConfig {
        ChannelConfig {
            buffer: 2,
            ..ChannelConfig::latest()
        }
    }

    /// A value whose newest sample is all that matters (clock snapshots, IO status): overflow
    /// allowed, history 1.
    pub const fn latest() -> ChannelConfig {
        ChannelConfig {
            buffer: 8,
            history: 1,
            safe_overflow: true,
            backpressure_timeout: Duration::ZERO,
            max_publishers: 1,
            max_subscribers: 4,
            min_receivers: 0,
        }
    }

    /// Planner → IO commands: lossless, one receiver required.
    pub const fn control() -> ChannelConfig {
        ChannelConfig {
            buffer: 8,
            history: 0,
            safe_overflow: false,
            backpressure_timeout: Duration::from_secs(2),
            max_publishers: 1,
            max_subscribers: 1,
            min_receivers: 1,
        }
    }

    /// Step batches: no overflow, 16 batches in flight, 1 publisher, 2 subscribers (the IO
    /// stage and a recorder), 2 s back-pressure bound.
    pub const fn steps() -> ChannelConfig {
        ChannelConfig {
            buffer: 16,
            history: 0,
            safe_overflow: false,
            backpressure_timeout: Duration::from_secs(2),
            max_publishers: 1,
            max_subscribers: 2,
            min_receivers: 1,
        }
    }

    /// Telemetry: overflow allowed (monitors never stall the printer), 4 publishers, 8
    /// subscribers.
    pub const fn telemetry() -> ChannelConfig {
        ChannelConfig {
            buffer: 256,
            history: 0,
            safe_overflow: true,
            backpressure_timeout: Duration::ZERO,
            max_publishers: 4,
            max_subscribers: 8,
            min_receivers: 0,
        }
    }
}

/// Creates a node and removes the stale resources of dead nodes (crashed processes), with the
/// half-created storages iceoryx2 would wait on for ever swept away ([`stale`]). Returns the
/// node and how many dead nodes were cleaned up.
/// iceoryx2's own log level defaults to Error (it warns on stdout that no config file exists);
/// `IOX2_LOG_LEVEL` overrides it.
pub fn open_node<S: Service>(name: &str) -> Result<(Node<S>, u64), ShmError> {
    set_log_level_from_env_or(LogLevel::Error);
    stale::ensure_sweeper();
    let node_name = NodeName::new(name).map_err(|e| ShmError::Name {
        name: name.to_string(),
        reason: format!("{e:?}"),
    })?;
    let node = NodeBuilder::new()
        .name(&node_name)
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<S>()
        .map_err(|e| match access_hint(std::path::Path::new(ICEORYX2_ROOT)) {
            Some(hint) => setup("creating node", name, format_args!("{e:?} ({hint})")),
            None => setup("creating node", name, e),
        })?;
    let cleaned = node.try_cleanup_dead_nodes();
    Ok((node, cleaned.cleanups))
}

/// Where iceoryx2 (default configuration) keeps its nodes and services.
pub const ICEORYX2_ROOT: &str = "/tmp/iceoryx2";

/// The usual reason iceoryx2 cannot create a node: its directories under `root` exist but this
/// process may not write to them (another user made them, e.g. an earlier run under sudo).
/// `None` when they are writable or missing (iceoryx2 then creates them).
pub fn access_hint(root: &std::path::Path) -> Option<String> {
    use std::os::unix::fs::MetadataExt;
    for dir in [root.to_path_buf(), root.join("nodes"), root.join("services")] {
        let Ok(meta) = std::fs::metadata(&dir) else {
            continue;
        };
        let probe = dir.join(format!(".cadence-access-{}", std::process::id()));
        match std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&probe)
        {
            Ok(_) => {
                let _ = std::fs::remove_file(&probe);
            }
            Err(e) if e.kind() == std::io::ErrorKind::PermissionDenied => {
                let me = std::fs::metadata("/proc/self").map(|m| m.uid()).ok();
                return Some(format!(
                    "{} belongs to uid {} (mode {:o}) and this user{} may not write to it: \
                     remove {} (it is recreated) or run as that user",
                    dir.display(),
                    meta.uid(),
                    meta.mode() & 0o7777,
                    me.map_or(String::new(), |u| format!(" (uid {u})")),
                    root.display()
                ));
            }
            Err(_) => {}
        }
    }
    None
}

fn setup(op: &'static str, service: &str, e: impl Debug) -> ShmError {
    ShmError::Setup {
        op,
        service: service.to_string(),
        reason: format!("{e:?}"),
    }
}

fn io(op: &'static str, service: &str, e: impl Debug) -> ShmError {
    ShmError::Io {
        op,
        service: service.to_string(),
        reason: format!("{e:?}"),
    }
}

fn service_name(name: &str) -> Result<ServiceName, ShmError> {
    ServiceName::new(name).map_err(|e| ShmError::Name {
        name: name.to_string(),
        reason: format!("{e:?}"),
    })
}

fn open_pubsub<S: Service, T: Sequenced>(
    node: &Node<S>,
    name: &str,
    cfg: &ChannelConfig,
) -> Result<publish_subscribe::PortFactory<S, T, ()>, ShmError> {
    node.service_builder(&service_name(name)?)
        .publish_subscribe::<T>()
        .enable_safe_overflow(cfg.safe_overflow)
        .subscriber_max_buffer_size(cfg.buffer)
        .history_size(cfg.history)
        .max_publishers(cfg.max_publishers)
        .max_subscribers(cfg.max_subscribers)
        .open_or_create()
        .map_err(|e| setup("opening publish-subscribe service", name, e))
}

fn open_event<S: Service>(
    node: &Node<S>,
    name: &str,
) -> Result<iceoryx2::service::port_factory::event::PortFactory<S>, ShmError> {
    node.service_builder(&service_name(name)?)
        .event()
        .open_or_create()
        .map_err(|e| setup("opening event service", name, e))
}

/// Sending side of a channel: fills a loaned sample in place, assigns the sequence number,
/// sends with back-pressure, then notifies the listeners.
#[derive(Debug)]
pub struct ShmPublisher<S: Service, T: Sequenced> {
    name: String,
    service: publish_subscribe::PortFactory<S, T, ()>,
    publisher: Publisher<S, T, ()>,
    notifier: Notifier<S>,
    next_seq: u64,
    timeout: Duration,
    min_receivers: usize,
}

impl<S: Service, T: Sequenced> ShmPublisher<S, T> {
    /// Opens (or creates) the channel `name` and its event service.
    pub fn open(node: &Node<S>, name: &str, cfg: &ChannelConfig) -> Result<Self, ShmError> {
        let service = open_pubsub::<S, T>(node, name, cfg)?;
        let bound = cfg.backpressure_timeout;
        let publisher = service
            .publisher_builder()
            .max_loaned_samples(2)
            .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
            .set_backpressure_handler(move |info: &BackpressureInfo| {
                if info.elapsed_time < bound {
                    BackpressureAction::Retry
                } else {
                    BackpressureAction::DiscardDataAndFail
                }
            })
            .create()
            .map_err(|e| setup("creating publisher", name, e))?;
        let notifier = open_event(node, name)?
            .notifier_builder()
            .create()
            .map_err(|e| setup("creating notifier", name, e))?;
        Ok(ShmPublisher {
            name: name.to_string(),
            service,
            publisher,
            notifier,
            next_seq: 0,
            timeout: bound,
            min_receivers: cfg.min_receivers,
        })
    }

    /// Connects to subscribers that appeared since the last send and returns how many
    /// subscribers the service has (a planner waits for its IO stage with this before the
    /// first batch: with no history, a batch sent before the subscriber connects is lost).
    pub fn connect(&self) -> Result<usize, ShmError> {
        self.publisher
            .update_connections()
            .map_err(|e| io("connecting", &self.name, e))?;
        Ok(self.service.dynamic_config().number_of_subscribers())
    }

    /// The sequence number the next payload gets.
    pub fn next_seq(&self) -> u64 {
        self.next_seq
    }

    /// Loans a sample (initialised to `T::default()`), lets `fill` write it in shared memory,
    /// stamps the sequence number, sends it and wakes the listeners. Returns the number of
    /// subscribers that got it. Blocks at most `backpressure_timeout` while a subscriber's
    /// buffer is full; then fails (the payload is not delivered to that subscriber).
    ///
    /// A subscriber that has not yet connected to this publisher's data segment (it connects on
    /// its next receive) makes iceoryx2 report 0 receivers instead of applying back-pressure;
    /// when fewer than `min_receivers` got nothing at all, the same payload (same sequence
    /// number) is sent again until the bound, so nobody sees it twice.
    pub fn send_with(&mut self, fill: impl FnOnce(&mut T)) -> Result<usize, ShmError> {
        let mut sample = self.publisher.loan().map_err(|e| io("loan", &self.name, e))?;
        let payload = sample.payload_mut();
        fill(payload);
        payload.set_seq(self.next_seq);
        let copy = *payload;
        let started = std::time::Instant::now();
        let mut result = sample.send();
        while matches!(result, Ok(0)) && self.min_receivers > 0 && started.elapsed() < self.timeout {
            std::thread::sleep(Duration::from_micros(200));
            let mut again = self.publisher.loan().map_err(|e| io("loan", &self.name, e))?;
            *again.payload_mut() = copy;
            result = again.send();
        }
        match result {
            Ok(n) if n < self.min_receivers => Err(ShmError::Undelivered {
                service: self.name.clone(),
                seq: self.next_seq,
                got: n,
                need: self.min_receivers,
            }),
            Ok(n) => {
                self.next_seq += 1;
                self.notifier.notify().map_err(|e| io("notify", &self.name, e))?;
                Ok(n)
            }
            Err(iceoryx2::port::SendError::UnableToDeliver) => Err(ShmError::Backpressure {
                service: self.name.clone(),
                seq: self.next_seq,
                waited: started.elapsed().max(self.timeout),
            }),
            Err(e) => Err(io("send", &self.name, e)),
        }
    }
}

/// Receiving side: checks sequence numbers and waits on the event service.
#[derive(Debug)]
pub struct ShmSubscriber<S: Service, T: Sequenced> {
    name: String,
    subscriber: Subscriber<S, T, ()>,
    listener: Listener<S>,
    expected: Option<u64>,
}

impl<S: Service, T: Sequenced> ShmSubscriber<S, T> {
    /// Opens (or creates) the channel `name`; expects the first payload to carry sequence 0.
    pub fn open(node: &Node<S>, name: &str, cfg: &ChannelConfig) -> Result<Self, ShmError> {
        let service = open_pubsub::<S, T>(node, name, cfg)?;
        let subscriber = service
            .subscriber_builder()
            .buffer_size(cfg.buffer)
            .create()
            .map_err(|e| setup("creating subscriber", name, e))?;
        subscriber
            .update_connections()
            .map_err(|e| setup("connecting subscriber", name, e))?;
        let listener = open_event(node, name)?
            .listener_builder()
            .create()
            .map_err(|e| setup("creating listener", name, e))?;
        Ok(ShmSubscriber {
            name: name.to_string(),
            subscriber,
            listener,
            expected: Some(0),
        })
    }

    /// Connects to publishers that appeared since the last receive (receiving does this too;
    /// call it after a publisher starts if the first receive may come late).
    pub fn connect(&self) -> Result<(), ShmError> {
        self.subscriber
            .update_connections()
            .map_err(|e| io("connecting", &self.name, e))
    }

    /// Accept whatever sequence number comes first (a monitor that joins late).
    pub fn accept_any_start(mut self) -> Self {
        self.expected = None;
        self
    }

    /// Takes one payload if there is one and hands it to `f` in place (zero-copy). A skipped
    /// sequence number is reported as [`ShmError::Gap`] (once; the payload is then dropped and
    /// counting resumes after it).
    pub fn try_recv_with<R>(&mut self, f: impl FnOnce(&T) -> R) -> Result<Option<R>, ShmError> {
        let sample = match self.subscriber.receive() {
            Ok(Some(s)) => s,
            Ok(None) => return Ok(None),
            Err(e) => return Err(io("receive", &self.name, e)),
        };
        let got = sample.payload().seq();
        let expected = self.expected.unwrap_or(got);
        self.expected = Some(got.wrapping_add(1));
        if got != expected {
            return Err(ShmError::Gap {
                service: self.name.clone(),
                expected,
                got,
            });
        }
        Ok(Some(f(sample.payload())))
    }

    /// Like [`Self::try_recv_with`], but when nothing is queued, sleeps on the event service
    /// for at most `timeout` (no busy loop). `Ok(None)` = timed out.
    pub fn recv_timeout_with<R>(
        &mut self,
        timeout: Duration,
        f: impl FnOnce(&T) -> R,
    ) -> Result<Option<R>, ShmError> {
        let mut f = Some(f);
        let mut call = |t: &T| f.take().map(|f| f(t));
        if let Some(r) = self.try_recv_with(&mut call)? {
            return Ok(r);
        }
        self.listener
            .timed_wait(|_| {}, timeout)
            .map_err(|e| io("wait", &self.name, e))?;
        Ok(self.try_recv_with(&mut call)?.flatten())
    }

    /// Drains every queued payload and returns a copy of the newest (`Ok(None)` when nothing
    /// was queued). Sequence gaps are expected here (an overflowing "newest value" channel)
    /// and not reported.
    pub fn latest(&mut self) -> Result<Option<T>, ShmError> {
        let mut last = None;
        loop {
            match self.subscriber.receive() {
                Ok(Some(s)) => {
                    let v = *s.payload();
                    self.expected = Some(v.seq().wrapping_add(1));
                    last = Some(v);
                }
                Ok(None) => return Ok(last),
                Err(e) => return Err(io("receive", &self.name, e)),
            }
        }
    }

    /// Waits on the event service for at most `timeout` (or until a publisher notifies), without
    /// taking anything.
    pub fn wait(&self, timeout: Duration) -> Result<(), ShmError> {
        self.listener
            .timed_wait(|_| {}, timeout)
            .map(|_| ())
            .map_err(|e| io("wait", &self.name, e))
    }

    /// The listener, for attaching to a `WaitSet` next to other sources.
    pub fn listener(&self) -> &Listener<S> {
        &self.listener
    }

    /// Drains pending wake-ups without blocking (after a `WaitSet` woke the thread).
    pub fn clear_events(&self) -> Result<(), ShmError> {
        self.listener
            .try_wait(|_| {})
            .map(|_| ())
            .map_err(|e| io("wait", &self.name, e))
    }
}

pub mod pooled;
pub mod stale;

#[cfg(test)]
mod tests;
