//! Homing trigger dispatch in the IO layer: a [`TriggerGroup`] ties one trsync object on each
//! of several MCUs together, and the IO thread that receives a member's
//! `trsync_state oid can_trigger trigger_reason clock` report acts on it at once, itself:
//! - `can_trigger=0` (the trsync fired): the first such report is recorded (MCU, reason,
//!   64-bit clock) and `trsync_trigger oid reason` with the same reason goes to every other
//!   member's link ahead of everything queued there;
//! - `can_trigger=1`: the member's expiry is pushed to `report clock + timeout ticks` with
//!   `trsync_set_timeout oid clock` (ticks = timeout · the link's estimated ticks per second).
//!
//! Timeout: 25 ms when several MCUs take part, 250 ms for one ([`TriggerGroup::default_timeout`]);
//! an MCU whose expiry passes triggers itself with reason 4 (communication timeout). The waiter
//! also treats a member that sent no report for a whole timeout as a communication timeout and
//! stops every member with reason 4 itself. Both end in [`TrsyncError::CommTimeout`], whose text
//! is exactly `Communication timeout during homing`.
//!
//! Timestamps (system time, `CLOCK_MONOTONIC` seconds like [`McuLink::system_now`]), for
//! per-hop latencies: when the host read the first trigger's report
//! ([`TriggerOutcome::received_at`]) and when the first `trsync_trigger` to each member was
//! written to that member's transport ([`TriggerGroup::trigger_written_at`]; the link's IO
//! thread notes it when the write that carried the message returns).
//!
//! Memory: everything is allocated by [`TriggerGroup::new`]; the IO-thread path
//! ([`on_state`]) takes a read lock, encodes into fixed-size [`Cmd`]s and pushes into
//! preallocated queues. Other IO threads read in ≤ 0.5 ms slices while a group is registered,
//! so a relayed trigger waits at most that long for its thread.

use std::sync::atomic::{AtomicU64, AtomicU8, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::dict::{Cmd, CmdEncoder, DictError};
use crate::mcu::shared::{read, write, RelayTag, Shared, Urgent, DEAD};
use crate::mcu::{LinkError, McuLink};

/// Trigger reason: the endstop was hit.
pub const REASON_ENDSTOP_HIT: u8 = 1;
/// Trigger reason: the host asked for a stop.
pub const REASON_HOST_REQUEST: u8 = 2;
/// Trigger reason: the homing move ended without a trigger.
pub const REASON_PAST_END_TIME: u8 = 3;
/// Trigger reason: a trsync's expiry passed (communication timeout).
pub const REASON_COMMS_TIMEOUT: u8 = 4;
/// The error text of a communication timeout during homing.
pub const COMM_TIMEOUT_MSG: &str = "Communication timeout during homing";

/// Timeout with several MCUs in the group, seconds.
pub const MULTI_MCU_TIMEOUT: f64 = 0.025;
/// Timeout with a single MCU, seconds.
pub const SINGLE_MCU_TIMEOUT: f64 = 0.250;
/// How often `wait` checks for silent members.
const WAIT_SLICE: Duration = Duration::from_millis(1);

/// Errors of a homing group.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TrsyncError {
    /// A member reported reason 4, or sent no report for a whole timeout (`mcu` names it;
    /// `detail` says which, for logs: the message itself stays exact).
    #[error("Communication timeout during homing")]
    CommTimeout { mcu: String, detail: String },
    /// `wait`'s deadline passed with no trigger.
    #[error("no trigger before the deadline")]
    NotTriggered,
    /// A member's dictionary lacks a trsync message.
    #[error("mcu '{mcu}': {detail}")]
    Dictionary { mcu: String, detail: String },
    /// The group is empty or names an MCU twice with one oid.
    #[error("bad homing group: {0}")]
    BadGroup(String),
    /// A member's link failed.
    #[error(transparent)]
    Link(#[from] LinkError),
}

/// The first trigger of a group.
#[derive(Debug, Clone, PartialEq)]
pub struct TriggerOutcome {
    /// The MCU whose trsync fired first.
    pub mcu: String,
    /// Its trigger reason (1 endstop, 2 host request, 3 past end time, 4 comms timeout).
    pub reason: u8,
    /// Its clock at the report (64-bit, that MCU's clock).
    pub trigger_clock: u64,
    /// System time (`CLOCK_MONOTONIC` seconds, [`McuLink::system_now`]) at which the host
    /// read the triggering `trsync_state` (taken right after the read that returned it); for
    /// a trigger the host decided itself (a silent member, [`TriggerGroup::trigger_all`]),
    /// the time of that decision.
    pub received_at: f64,
}

/// One member, as the IO threads see it.
#[derive(Debug)]
struct Member {
    name: String,
    oid: u8,
    shared: Arc<Shared>,
    trigger: CmdEncoder,
    set_timeout: CmdEncoder,
    timeout_ticks: u32,
    /// System time (f64 bits) of the last report.
    last_report: AtomicU64,
    /// System time (f64 bits; 0 = not yet) at which the first `trsync_trigger` to this member
    /// was written to its transport.
    trigger_written: AtomicU64,
}

const ARMED: u8 = 0;
const RECORDING: u8 = 1;
const DONE: u8 = 2;

/// The state a group shares with the IO threads of its members.
#[derive(Debug)]
pub(crate) struct GroupState {
    /// Unique in the process (tags the relayed triggers, see [`relay_written`]).
    id: u64,
    members: Vec<Member>,
    /// ARMED → RECORDING (the winner writes the fields) → DONE (Release: fields visible).
    state: AtomicU8,
    first_member: AtomicU64,
    first_reason: AtomicU8,
    first_clock: AtomicU64,
    /// System time (f64 bits) at which the first trigger's report was read.
    first_received: AtomicU64,
}

impl GroupState {
    /// Records the first trigger; returns true for the first caller.
    fn record(&self, member: usize, reason: u8, clock: u64, received_at: f64) -> bool {
        if self
            .state
            .compare_exchange(ARMED, RECORDING, Ordering::AcqRel, Ordering::Acquire)
            .is_err()
        {
            return false;
        }
        self.first_member.store(member as u64, Ordering::Relaxed);
        self.first_reason.store(reason, Ordering::Relaxed);
        self.first_clock.store(clock, Ordering::Relaxed);
        self.first_received
            .store(received_at.to_bits(), Ordering::Relaxed);
        // Pairs with the Acquire load in `outcome`.
        self.state.store(DONE, Ordering::Release);
        true
    }

    fn outcome(&self) -> Option<TriggerOutcome> {
        if self.state.load(Ordering::Acquire) != DONE {
            return None;
        }
        let m = self
            .members
            .get(self.first_member.load(Ordering::Relaxed) as usize)?;
        Some(TriggerOutcome {
            mcu: m.name.clone(),
            reason: self.first_reason.load(Ordering::Relaxed),
            trigger_clock: self.first_clock.load(Ordering::Relaxed),
            received_at: f64::from_bits(self.first_received.load(Ordering::Relaxed)),
        })
    }

    /// Queues `trsync_trigger` with `reason` on every member except `except`.
    fn trigger_others(&self, except: Option<usize>, reason: u8) {
        for (i, m) in self.members.iter().enumerate() {
            if Some(i) == except {
                continue;
            }
            if let Ok(cmd) = m.trigger.encode(&[m.oid as i64, reason as i64]) {
                let tag = RelayTag {
                    group: self.id,
                    member: i,
                };
                push_urgent(&m.shared, cmd, Some(tag));
            }
        }
    }
}

/// Hands `cmd` to a link's IO thread ahead of everything queued there (`relay`: the member a
/// `trsync_trigger` is for, whose write time the IO thread then reports).
fn push_urgent(shared: &Shared, cmd: Cmd, relay: Option<RelayTag>) {
    let item = Urgent { cmd, relay };
    if shared.urgent.push(item).is_err() {
        shared.urgent_dropped.fetch_add(1, Ordering::Relaxed);
    }
    shared.wake_io();
}

/// A trsync registered with one link's IO thread.
#[derive(Debug, Clone)]
pub(crate) struct Registration {
    oid: u8,
    group: Arc<GroupState>,
    member: usize,
}

/// Called by the IO thread of `shared` for each `trsync_state` (allocation-free).
pub(crate) fn on_state(shared: &Shared, now: f64, oid: i64, can_trigger: bool, reason: i64, clock: u64) {
    if shared.armed.load(Ordering::Acquire) == 0 {
        return;
    }
    let regs = read(&shared.trsyncs);
    for r in regs.iter().filter(|r| r.oid as i64 == oid) {
        let g = &*r.group;
        let Some(m) = g.members.get(r.member) else {
            continue;
        };
        m.last_report.store(now.to_bits(), Ordering::Release);
        if !can_trigger {
            let reason = u8::try_from(reason).unwrap_or(REASON_COMMS_TIMEOUT);
            if g.record(r.member, reason, clock, now) {
                g.trigger_others(Some(r.member), reason);
            }
        } else if g.state.load(Ordering::Acquire) == ARMED {
            let expire = (clock as u32).wrapping_add(m.timeout_ticks);
            if let Ok(cmd) = m.set_timeout.encode(&[oid, expire as i64]) {
                push_urgent(shared, cmd, None);
            }
        }
    }
}

/// Called by the IO thread of `shared` when the write that carried the relayed trigger
/// `tag` returned at system time `at`: the member keeps the first such time (allocation-free;
/// nothing happens if the group was closed meanwhile).
pub(crate) fn relay_written(shared: &Shared, tag: RelayTag, at: f64) {
    let regs = read(&shared.trsyncs);
    for r in regs
        .iter()
        .filter(|r| r.group.id == tag.group && r.member == tag.member)
    {
        if let Some(m) = r.group.members.get(r.member) {
            // Only the first write counts (later ones repeat the stop).
            let _ = m
                .trigger_written
                .compare_exchange(0, at.to_bits(), Ordering::AcqRel, Ordering::Acquire);
        }
    }
}

/// Source of [`GroupState::id`].
static NEXT_GROUP_ID: AtomicU64 = AtomicU64::new(1);

/// A homing group: one trsync per MCU link, relayed by the links' IO threads.
#[derive(Debug)]
pub struct TriggerGroup {
    state: Arc<GroupState>,
    timeout: f64,
    closed: bool,
}

impl TriggerGroup {
    /// The protocol's timeout for a group of `mcus` MCUs: 25 ms for several, 250 ms for one.
    pub fn default_timeout(mcus: usize) -> f64 {
        if mcus > 1 {
            MULTI_MCU_TIMEOUT
        } else {
            SINGLE_MCU_TIMEOUT
        }
    }

    /// Registers trsync `oid` on each link (the trsyncs themselves are configured and
    /// started by the caller) with a report timeout of `timeout_s` seconds.
    pub fn new(members: &[(&McuLink, u8)], timeout_s: f64) -> Result<TriggerGroup, TrsyncError> {
        if members.is_empty() {
            return Err(TrsyncError::BadGroup("no members".into()));
        }
        let now = McuLink::system_now();
        let mut list = Vec::with_capacity(members.len());
        for (i, (link, oid)) in members.iter().enumerate() {
            if members[..i]
                .iter()
                .any(|(l, o)| std::ptr::eq(*l, *link) && o == oid)
            {
                return Err(TrsyncError::BadGroup(format!(
                    "mcu '{}' trsync oid {oid} listed twice",
                    link.name()
                )));
            }
            if let Some(e) = link.error() {
                return Err(e.into());
            }
            let dict = link.dictionary();
            let de = |e: DictError| TrsyncError::Dictionary {
                mcu: link.name().to_owned(),
                detail: e.to_string(),
            };
            dict.response("trsync_state").map_err(de)?;
            let est = link.clock();
            let freq = if est.is_valid() {
                est.freq()
            } else {
                dict.clock_freq().map_err(de)?
            };
            list.push(Member {
                name: link.name().to_owned(),
                oid: *oid,
                shared: link.shared().clone(),
                trigger: dict.encoder("trsync_trigger").map_err(de)?,
                set_timeout: dict.encoder("trsync_set_timeout").map_err(de)?,
                timeout_ticks: (timeout_s * freq).clamp(1.0, (1u64 << 31) as f64) as u32,
                last_report: AtomicU64::new(now.to_bits()),
                trigger_written: AtomicU64::new(0),
            });
        }
        let state = Arc::new(GroupState {
            id: NEXT_GROUP_ID.fetch_add(1, Ordering::Relaxed),
            members: list,
            state: AtomicU8::new(ARMED),
            first_member: AtomicU64::new(0),
            first_reason: AtomicU8::new(0),
            first_clock: AtomicU64::new(0),
            first_received: AtomicU64::new(0),
        });
        for (i, m) in state.members.iter().enumerate() {
            write(&m.shared.trsyncs).push(Registration {
                oid: m.oid,
                group: state.clone(),
                member: i,
            });
            m.shared.armed.fetch_add(1, Ordering::AcqRel);
        }
        Ok(TriggerGroup {
            state,
            timeout: timeout_s,
            closed: false,
        })
    }

    /// The first trigger, once there is one.
    pub fn outcome(&self) -> Option<TriggerOutcome> {
        self.state.outcome()
    }

    /// System time (`CLOCK_MONOTONIC` seconds, [`McuLink::system_now`]) at which the first
    /// `trsync_trigger` to member `member` (its index in the list given to [`Self::new`]) was
    /// written to that link's transport: taken by the link's IO thread when the write that
    /// carried it returned. `None` until then (and for the member that triggered first: it
    /// is told nothing unless [`Self::trigger_all`] runs).
    ///
    /// For the relay of an MCU's trigger, this minus [`TriggerOutcome::received_at`] is the
    /// host's part: processing, the other IO thread's wake-up, its serial queue and the write.
    pub fn trigger_written_at(&self, member: usize) -> Option<f64> {
        let bits = self
            .state
            .members
            .get(member)?
            .trigger_written
            .load(Ordering::Acquire);
        (bits != 0).then(|| f64::from_bits(bits))
    }

    /// Waits for the first trigger until `deadline`. A reason-4 trigger, or a member silent for
    /// a whole timeout, is [`TrsyncError::CommTimeout`] (every member is then told to stop);
    /// no trigger by the deadline is [`TrsyncError::NotTriggered`]; a dead link is
    /// [`TrsyncError::Link`].
    pub fn wait(&self, deadline: Instant) -> Result<TriggerOutcome, TrsyncError> {
        let mut silence: Option<String> = None;
        loop {
            if let Some(o) = self.state.outcome() {
                if o.reason == REASON_COMMS_TIMEOUT {
                    let detail = silence.take().unwrap_or_else(|| {
                        format!(
                            "'{}' stopped with reason 4: its trsync expiry passed first",
                            o.mcu
                        )
                    });
                    return Err(TrsyncError::CommTimeout { mcu: o.mcu, detail });
                }
                return Ok(o);
            }
            let now = McuLink::system_now();
            for (i, m) in self.state.members.iter().enumerate() {
                if m.shared.state.load(Ordering::Acquire) == DEAD {
                    if let Some(e) = m.shared.dead_error() {
                        self.trigger_all(REASON_COMMS_TIMEOUT);
                        return Err(e.into());
                    }
                }
                let last = f64::from_bits(m.last_report.load(Ordering::Acquire));
                if now - last > self.timeout {
                    let clock = m.shared.clock.load().clock_at(now).max(0.0) as u64;
                    if self.state.record(i, REASON_COMMS_TIMEOUT, clock, now) {
                        // Every member silent at once points at the host (or its VM) stalling.
                        let silent = (self.state.members.iter())
                            .filter(|m| {
                                now - f64::from_bits(m.last_report.load(Ordering::Acquire)) > self.timeout
                            })
                            .count();
                        silence = Some(format!(
                            "no report from '{}' for {:.1} ms ({silent} of {} members silent)",
                            m.shared.name,
                            (now - last) * 1e3,
                            self.state.members.len()
                        ));
                        self.state.trigger_others(None, REASON_COMMS_TIMEOUT);
                    }
                }
            }
            if self.state.outcome().is_some() {
                continue;
            }
            if Instant::now() >= deadline {
                return Err(TrsyncError::NotTriggered);
            }
            std::thread::sleep(WAIT_SLICE.min(deadline.saturating_duration_since(Instant::now())));
        }
    }

    /// Stops every member with `reason` (e.g. [`REASON_HOST_REQUEST`] or
    /// [`REASON_PAST_END_TIME`]) and records it as the outcome if nothing triggered yet.
    pub fn trigger_all(&self, reason: u8) {
        if self.state.state.load(Ordering::Acquire) == ARMED {
            // The host is the trigger source: record it under the first member's name.
            let m = &self.state.members[0];
            let now = McuLink::system_now();
            let clock = m.shared.clock.load().clock_at(now).max(0.0) as u64;
            self.state.record(0, reason, clock, now);
        }
        self.state.trigger_others(None, reason);
    }

    /// Unregisters the group from every link.
    pub fn close(mut self) {
        self.unregister();
    }

    fn unregister(&mut self) {
        if std::mem::replace(&mut self.closed, true) {
            return;
        }
        for m in &self.state.members {
            write(&m.shared.trsyncs).retain(|r| !Arc::ptr_eq(&r.group, &self.state));
            m.shared.armed.fetch_sub(1, Ordering::AcqRel);
        }
    }
}

impl Drop for TriggerGroup {
    fn drop(&mut self) {
        self.unregister();
    }
}

#[cfg(test)]
mod tests;
