//! State shared between an [`super::McuLink`] handle (any thread) and its IO thread.
//!
//! Hot hand-off never waits: outgoing messages go through a preallocated [`HandoffQueue`]
//! (neither side ever waits for the other: safe under SCHED_FIFO on one core; its per-slot
//! locks are never contended), the clock estimate through a seqlock, counters through atomics.
//! Other mutexes guard only rare things (query waiters, the death/shutdown reason, stats
//! snapshots); the IO thread never holds one while doing IO.

use std::sync::atomic::{fence, AtomicBool, AtomicU64, AtomicU8, AtomicUsize, Ordering};
use std::sync::{Condvar, Mutex, MutexGuard, OnceLock, RwLock, RwLockReadGuard, RwLockWriteGuard};
use std::time::{Duration, Instant};

use super::{LinkError, LinkStats};
use crate::clocksync::ClockShared;
use crate::dict::{Cmd, Dictionary, Message};
use rt_core::handoff::HandoffQueue;
use std::sync::Arc;

/// A message on its way from a caller to the IO thread.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Outgoing {
    pub cmd: Cmd,
    pub min_clock: u64,
    pub req_clock: u64,
}

/// A message for the IO thread to send ahead of everything queued (see [`Shared::urgent`]).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Urgent {
    pub cmd: Cmd,
    /// Set for a `trsync_trigger` of a homing group: the IO thread reports the moment it
    /// wrote the message to the transport (`crate::trsync::relay_written`).
    pub relay: Option<RelayTag>,
}

/// Names the homing group member a relayed `trsync_trigger` is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct RelayTag {
    /// The group's id (unique in the process).
    pub group: u64,
    /// The member's index in the group.
    pub member: usize,
}

/// Link states.
pub(crate) const CONNECTING: u8 = 0;
pub(crate) const RUNNING: u8 = 1;
pub(crate) const DEAD: u8 = 2;

/// Why the IO thread stopped (turned into a [`LinkError`] with the MCU's name).
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Death {
    IdentifyTimeout(f64),
    Dictionary(String),
    Handshake(String),
    ConnectionLost(String),
    NoAck(f64),
    Reset(String),
    Closed,
}

impl Death {
    pub(crate) fn to_error(&self, mcu: &str) -> LinkError {
        let mcu = mcu.to_owned();
        match self.clone() {
            Death::IdentifyTimeout(secs) => LinkError::IdentifyTimeout { mcu, secs },
            Death::Dictionary(detail) => LinkError::Dictionary { mcu, detail },
            Death::Handshake(detail) => LinkError::Handshake { mcu, detail },
            Death::ConnectionLost(detail) => LinkError::ConnectionLost { mcu, detail },
            Death::NoAck(secs) => LinkError::NoAck { mcu, secs },
            Death::Reset(detail) => LinkError::Reset { mcu, detail },
            Death::Closed => LinkError::Closed { mcu },
        }
    }
}

/// Why a query waiter was released without its response.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum WaitFail {
    Shutdown(String),
}

/// A caller waiting for a response.
#[derive(Debug)]
pub(crate) struct Waiter {
    pub id: u64,
    pub response: String,
    pub matcher: Option<(String, i64)>,
    pub result: Option<Result<Message, WaitFail>>,
}

/// Responses the MCU still sends while shut down: waiters for these are not failed by a
/// shutdown.
pub(crate) const ANSWERED_WHEN_SHUT_DOWN: [&str; 6] = [
    "identify_response",
    "config",
    "clock",
    "uptime",
    "shutdown",
    "is_shutdown",
];

/// Wakes callers blocked on the link; costs one atomic load when nobody waits.
#[derive(Debug, Default)]
pub(crate) struct Notifier {
    lock: Mutex<()>,
    cv: Condvar,
    waiters: AtomicUsize,
}

/// Longest single sleep of a waiter: a missed wake-up only costs this much latency.
const MAX_SLEEP: Duration = Duration::from_millis(50);

impl Notifier {
    /// Wakes every waiter (call after changing the state they wait on).
    pub(crate) fn notify(&self) {
        // SeqCst fence pairs with the waiter's SeqCst increment: either we see the waiter, or
        // the waiter's condition check (after its increment) sees our state change.
        fence(Ordering::SeqCst);
        if self.waiters.load(Ordering::SeqCst) > 0 {
            let _g = lock(&self.lock);
            self.cv.notify_all();
        }
    }

    /// Blocks until `done()` is true (returns true) or `deadline` passes (returns false).
    pub(crate) fn wait_until(&self, deadline: Instant, mut done: impl FnMut() -> bool) -> bool {
        self.waiters.fetch_add(1, Ordering::SeqCst);
        let mut g = lock(&self.lock);
        let result = loop {
            if done() {
                break true;
            }
            let now = Instant::now();
            if now >= deadline {
                break false;
            }
            let sleep = (deadline - now).min(MAX_SLEEP);
            g = self
                .cv
                .wait_timeout(g, sleep)
                .map(|(g, _)| g)
                .unwrap_or_else(|e| e.into_inner().0);
        };
        drop(g);
        self.waiters.fetch_sub(1, Ordering::SeqCst);
        result
    }
}

/// Slots of the urgent queue.
pub(crate) const URGENT_CAPACITY: usize = 64;

/// Read-locks an `RwLock`, ignoring poisoning.
pub(crate) fn read<T>(m: &RwLock<T>) -> RwLockReadGuard<'_, T> {
    m.read().unwrap_or_else(|e| e.into_inner())
}

/// Write-locks an `RwLock`, ignoring poisoning.
pub(crate) fn write<T>(m: &RwLock<T>) -> RwLockWriteGuard<'_, T> {
    m.write().unwrap_or_else(|e| e.into_inner())
}

/// Locks a mutex, ignoring poisoning (a panicked holder leaves plain data behind).
pub(crate) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Everything the handle and the IO thread share.
#[derive(Debug)]
pub(crate) struct Shared {
    pub name: String,
    pub outgoing: HandoffQueue<Outgoing>,
    pub clock: ClockShared,
    pub dict: OnceLock<Arc<Dictionary>>,
    pub stop: AtomicBool,
    pub state: AtomicU8,
    pub death: Mutex<Option<Death>>,
    pub shutdown: Mutex<Option<String>>,
    pub is_shutdown: AtomicBool,
    pub waiters: Mutex<Vec<Waiter>>,
    pub waiter_count: AtomicUsize,
    pub next_waiter: AtomicU64,
    /// Caller messages pushed into `outgoing`.
    pub submitted: AtomicU64,
    /// Caller messages the IO thread has taken from `outgoing`.
    pub taken: AtomicU64,
    /// `taken` at the last moment the serial queue was idle (all sent and acked).
    pub idle_upto: AtomicU64,
    pub stats: Mutex<LinkStats>,
    pub notify: Notifier,
    /// Messages that go ahead of everything queued (homing triggers, trsync timeouts).
    pub urgent: HandoffQueue<Urgent>,
    /// Urgent messages lost because `urgent` was full.
    pub urgent_dropped: AtomicU64,
    /// Trsyncs of homing groups on this MCU (written on register/unregister only).
    pub trsyncs: RwLock<Vec<crate::trsync::Registration>>,
    /// Number of registered trsyncs: while > 0 the IO thread reads with a short timeout
    /// (only when its transport cannot be woken).
    pub armed: AtomicUsize,
    /// Ends the IO thread's read wait when another thread hands it work (`None` if the
    /// eventfd could not be made: the IO thread then reads in short slices).
    pub wake: Option<crate::transport::Wake>,
    /// The latest `analog_in_state` of oids `0..ANALOG_SLOTS`: `(next_clock << 32) |
    /// (reports mod 2^16) << 16 | value`, 0 before the first (see `McuLink::analog_report`).
    pub analog: [AtomicU64; ANALOG_SLOTS],
    /// The latest `counter_state` of oids `0..ANALOG_SLOTS`.
    pub counters: [super::counter::CounterSlot; ANALOG_SLOTS],
    /// The latest `thermocouple_result` of oids `0..ANALOG_SLOTS`, in a counter's three-word
    /// slot: `next_clock`, `value`, `fault` (see `McuLink::thermocouple_report`).
    pub thermocouples: [super::counter::CounterSlot; ANALOG_SLOTS],
}

/// Oids whose `analog_in_state` reports the link keeps (the latest of each).
pub const ANALOG_SLOTS: usize = 64;

impl Shared {
    pub(crate) fn new(name: &str, capacity: usize) -> Shared {
        Shared {
            name: name.to_owned(),
            outgoing: HandoffQueue::new(capacity.max(1)),
            clock: ClockShared::default(),
            dict: OnceLock::new(),
            stop: AtomicBool::new(false),
            state: AtomicU8::new(CONNECTING),
            death: Mutex::new(None),
            shutdown: Mutex::new(None),
            is_shutdown: AtomicBool::new(false),
            waiters: Mutex::new(Vec::new()),
            waiter_count: AtomicUsize::new(0),
            next_waiter: AtomicU64::new(1),
            submitted: AtomicU64::new(0),
            taken: AtomicU64::new(0),
            idle_upto: AtomicU64::new(0),
            stats: Mutex::new(LinkStats::default()),
            notify: Notifier::default(),
            urgent: HandoffQueue::new(URGENT_CAPACITY),
            urgent_dropped: AtomicU64::new(0),
            trsyncs: RwLock::new(Vec::with_capacity(8)),
            armed: AtomicUsize::new(0),
            wake: crate::transport::Wake::new().ok(),
            analog: std::array::from_fn(|_| AtomicU64::new(0)),
            counters: std::array::from_fn(|_| super::counter::CounterSlot::default()),
            thermocouples: std::array::from_fn(|_| super::counter::CounterSlot::default()),
        }
    }

    /// Wakes the IO thread if it is blocked reading (after pushing work for it).
    pub(crate) fn wake_io(&self) {
        if let Some(w) = &self.wake {
            w.wake();
        }
    }

    /// Records why the link died (the first reason wins) and wakes everyone.
    pub(crate) fn die(&self, death: Death) {
        {
            let mut d = lock(&self.death);
            if d.is_none() {
                *d = Some(death);
            }
        }
        self.state.store(DEAD, Ordering::Release);
        self.notify.notify();
    }

    /// The error for a dead link, if it is dead.
    pub(crate) fn dead_error(&self) -> Option<LinkError> {
        if self.state.load(Ordering::Acquire) != DEAD {
            return None;
        }
        Some(
            lock(&self.death)
                .as_ref()
                .unwrap_or(&Death::Closed)
                .to_error(&self.name),
        )
    }

    /// The shutdown error, if the MCU has shut down.
    pub(crate) fn shutdown_error(&self) -> Option<LinkError> {
        if !self.is_shutdown.load(Ordering::Acquire) {
            return None;
        }
        let reason = lock(&self.shutdown).clone().unwrap_or_default();
        Some(LinkError::Shutdown {
            mcu: self.name.clone(),
            reason,
        })
    }
}
