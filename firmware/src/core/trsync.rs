//! A trsync (trigger synchronisation) object: the one-shot "stop now" signal of homing.
//!
//! `trsync_start` arms it (`can_trigger` = 1, reason 0) and optionally starts periodic reports at
//! `report_clock`, `report_clock + report_ticks`, …; `trsync_set_timeout` sets the expiry clock.
//! Whichever comes first of an endstop, a `trsync_trigger` from the host, or the expiry clock
//! passing without renewal (reason = `expire_reason`, 4 = communication timeout) triggers it:
//! `can_trigger` drops to 0, the reason and clock are kept, the expiry is cancelled. The caller
//! stops the attached steppers and reports at once. Periodic reports go on after an endstop or
//! expiry trigger, as on Klipper's MCU, until the host's `trsync_trigger` ends the homing:
//! [`Trsync::stop`] then silences it until the next `trsync_start`. Klipper's host takes any
//! `can_trigger=0` report as the trigger of the pass it is waiting for, so a report left over
//! from the previous pass would end the next one at once.
//!
//! Both periodic events share the oid's one timer: its wake time is the earlier of the next
//! report and the expiry ([`Trsync::next_wake`]); [`Trsync::event`] says which of them were due.
//! All clocks are 32-bit wrapping clocks compared with `is_before`.

use rt_core::WireClock;

/// Trigger reason: an endstop hit.
pub const REASON_ENDSTOP_HIT: u8 = 1;
/// Trigger reason: the host asked.
pub const REASON_HOST_REQUEST: u8 = 2;
/// Trigger reason: the homing move ended.
pub const REASON_PAST_END_TIME: u8 = 3;
/// Trigger reason: no renewal of the timeout (communication timeout).
pub const REASON_COMMS_TIMEOUT: u8 = 4;

/// The state of one trsync.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Trsync {
    can_trigger: bool,
    trigger_reason: u8,
    trigger_clock: Option<WireClock>,
    expire_reason: u8,
    report_ticks: u32,
    report_at: Option<WireClock>,
    expire_at: Option<WireClock>,
}

/// What a timer event of a trsync found due.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TrsyncEvent {
    /// The expiry passed: trigger with this reason (the `expire_reason`).
    pub expired: Option<u8>,
    /// A periodic report is due now.
    pub report: bool,
}

impl Trsync {
    /// A configured, idle trsync (cannot trigger until started).
    pub const fn new() -> Trsync {
        Trsync {
            can_trigger: false,
            trigger_reason: 0,
            trigger_clock: None,
            expire_reason: 0,
            report_ticks: 0,
            report_at: None,
            expire_at: None,
        }
    }

    /// `trsync_start`.
    pub fn start(&mut self, report_clock: WireClock, report_ticks: u32, expire_reason: u8) {
        *self = Trsync {
            can_trigger: true,
            expire_reason,
            report_ticks,
            report_at: (report_ticks > 0).then_some(report_clock),
            ..Trsync::new()
        };
    }

    /// `trsync_set_timeout`: trigger with the expire reason once `clock` has passed.
    pub fn set_timeout(&mut self, clock: WireClock) {
        if self.can_trigger {
            self.expire_at = Some(clock);
        }
    }

    /// Triggers at `clock` with `reason`. Returns false (and changes nothing) if it could not
    /// trigger (not started, or already triggered).
    pub fn trigger(&mut self, reason: u8, clock: WireClock) -> bool {
        if !self.can_trigger {
            return false;
        }
        self.can_trigger = false;
        self.trigger_reason = reason;
        self.trigger_clock = Some(clock);
        self.expire_at = None;
        true
    }

    /// True while armed and not triggered.
    pub const fn can_trigger(&self) -> bool {
        self.can_trigger
    }

    /// The reason of the last trigger (0 = none since the start).
    pub const fn trigger_reason(&self) -> u8 {
        self.trigger_reason
    }

    /// The `clock` a `trsync_state` report made at `at` carries: the trigger clock once
    /// triggered, else `at`.
    pub fn report_clock(&self, at: WireClock) -> WireClock {
        self.trigger_clock.unwrap_or(at)
    }

    /// When the timer must fire next.
    pub fn next_wake(&self) -> Option<WireClock> {
        match (self.report_at, self.expire_at) {
            (Some(r), Some(e)) => Some(if e.is_before(r) { e } else { r }),
            (r, e) => r.or(e),
        }
    }

    /// The timer fired at `at`: which events were due (a due periodic report advances to the
    /// next period).
    pub fn event(&mut self, at: WireClock) -> TrsyncEvent {
        let expired = match self.expire_at {
            Some(e) if !at.is_before(e) && self.can_trigger => Some(self.expire_reason),
            _ => None,
        };
        let report = match self.report_at {
            Some(r) if !at.is_before(r) => {
                self.report_at = Some(r.add(self.report_ticks));
                true
            }
            _ => false,
        };
        TrsyncEvent { expired, report }
    }

    /// The host's `trsync_trigger` (after [`Trsync::trigger`]): no more reports or expiry
    /// until the next `trsync_start`; the trigger reason and clock stay for the one report
    /// that answers the command.
    pub fn stop(&mut self) {
        self.report_at = None;
        self.expire_at = None;
        self.can_trigger = false;
    }

    /// Shutdown: no more reports or expiry.
    pub fn halt(&mut self) {
        self.report_at = None;
        self.expire_at = None;
        self.can_trigger = false;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reports_and_expiry_share_one_wake_time() {
        let mut t = Trsync::new();
        assert!(!t.trigger(2, WireClock(1)), "not started: cannot trigger");
        t.start(WireClock(1000), 300, REASON_COMMS_TIMEOUT);
        assert_eq!(t.next_wake(), Some(WireClock(1000)));
        t.set_timeout(WireClock(1500));
        assert_eq!(
            t.event(WireClock(1000)),
            TrsyncEvent {
                expired: None,
                report: true
            }
        );
        assert_eq!(t.next_wake(), Some(WireClock(1300)));
        t.event(WireClock(1300));
        assert_eq!(
            t.next_wake(),
            Some(WireClock(1500)),
            "expiry before the 1600 report"
        );
        let e = t.event(WireClock(1500));
        assert_eq!(e.expired, Some(REASON_COMMS_TIMEOUT));
        assert!(!e.report);
        assert!(t.trigger(REASON_COMMS_TIMEOUT, WireClock(1500)));
        assert!(!t.can_trigger());
        assert_eq!(
            t.next_wake(),
            Some(WireClock(1600)),
            "reports go on, expiry is gone"
        );
        assert_eq!(t.report_clock(WireClock(1600)), WireClock(1500));
        assert!(!t.trigger(REASON_HOST_REQUEST, WireClock(1700)), "one shot");
        assert_eq!(t.trigger_reason(), REASON_COMMS_TIMEOUT);
    }

    #[test]
    fn renewal_and_wrap() {
        let mut t = Trsync::new();
        let base = WireClock(u32::MAX - 50);
        t.start(base, 0, 4);
        assert_eq!(t.next_wake(), None, "no reports with report_ticks 0");
        t.set_timeout(base.add(100));
        t.set_timeout(base.add(200)); // renewed
        assert_eq!(t.event(base.add(100)).expired, None);
        assert_eq!(t.event(base.add(200)).expired, Some(4));
        t.halt();
        assert_eq!(t.next_wake(), None);
    }
}
