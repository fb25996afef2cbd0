//! An endstop: samples a pin during homing and triggers a trsync when it reads the wanted value.
//!
//! `endstop_home clock sample_ticks sample_count rest_ticks pin_value trsync_oid trigger_reason`:
//! from `clock`, read the pin every `rest_ticks`. When it reads `pin_value`, confirm: that read
//! and the next `sample_count − 1` reads, `sample_ticks` apart, must all read `pin_value`. A
//! confirmed trigger (at the clock of the last confirming read) triggers the trsync and ends
//! homing; a failed confirmation goes back to resting, continuing `rest_ticks` after the first
//! matching read. `sample_count = 0` (or `clock = 0`) cancels homing.
//!
//! `endstop_query_state` reports `next_clock` with Klipper's meaning: while resting (no match
//! yet), the clock of the next read; from the first matching read on — while confirming, and
//! after the trigger until the next `endstop_home` — that read's clock + `rest_ticks` (where
//! resting would resume). So the host recovers the trigger time as `next_clock − rest_ticks`:
//! the first read that saw the pin triggered, not the last confirming read (which is when the
//! trsync fired and the steppers stopped). A cancel (`sample_count = 0`) keeps the value.

use rt_core::WireClock;

/// `endstop_home` parameters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct HomeParams {
    /// First read.
    pub clock: WireClock,
    /// Ticks between confirming reads.
    pub sample_ticks: u32,
    /// Matching reads needed (the first match included).
    pub sample_count: u8,
    /// Ticks between reads while waiting for a match.
    pub rest_ticks: u32,
    /// The pin value that means "triggered".
    pub pin_value: bool,
    /// The trsync to trigger.
    pub trsync_oid: u8,
    /// The reason to trigger it with.
    pub trigger_reason: u8,
}

/// The state of one endstop.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Endstop {
    /// The pin (see the `pin` enumeration).
    pub pin: u8,
    /// Pull-up requested.
    pub pull_up: bool,
    params: HomeParams,
    homing: bool,
    /// Confirming a match: reads left (including the one the timer is armed for).
    confirming: u8,
    /// Where resting resumes if a confirmation fails.
    resume: WireClock,
    next_clock: WireClock,
}

/// What an endstop timer event decided.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EndstopEvent {
    /// Read again at this clock.
    Rearm(WireClock),
    /// Confirmed: trigger trsync `trsync_oid` with `reason` (homing has ended).
    Trigger {
        /// The trsync.
        trsync_oid: u8,
        /// Its trigger reason.
        reason: u8,
    },
    /// Not homing (a stale timer): nothing to do.
    Idle,
}

impl Endstop {
    /// `config_endstop`.
    pub const fn new(pin: u8, pull_up: bool) -> Endstop {
        Endstop {
            pin,
            pull_up,
            params: HomeParams {
                clock: WireClock(0),
                sample_ticks: 0,
                sample_count: 0,
                rest_ticks: 0,
                pin_value: false,
                trsync_oid: 0,
                trigger_reason: 0,
            },
            homing: false,
            confirming: 0,
            resume: WireClock(0),
            next_clock: WireClock(0),
        }
    }

    /// `endstop_home`: returns the clock to arm the timer at, or `None` if this cancelled homing.
    pub fn home(&mut self, p: HomeParams) -> Option<WireClock> {
        self.confirming = 0;
        if p.sample_count == 0 || p.clock.0 == 0 {
            self.homing = false;
            return None;
        }
        self.params = p;
        self.homing = true;
        self.next_clock = p.clock;
        Some(p.clock)
    }

    /// True while homing.
    pub const fn homing(&self) -> bool {
        self.homing
    }

    /// `next_clock` of `endstop_state` (see the module doc): the next read while resting, the
    /// first matching read + `rest_ticks` once a read matched.
    pub const fn next_clock(&self) -> WireClock {
        self.next_clock
    }

    /// The timer fired at `at` and the pin reads `pin`.
    pub fn event(&mut self, at: WireClock, pin: bool) -> EndstopEvent {
        if !self.homing {
            return EndstopEvent::Idle;
        }
        let p = self.params;
        let matched = pin == p.pin_value;
        if self.confirming == 0 {
            if !matched {
                self.next_clock = at.add(p.rest_ticks);
                return EndstopEvent::Rearm(self.next_clock);
            }
            self.resume = at.add(p.rest_ticks);
            self.next_clock = self.resume;
            self.confirming = p.sample_count;
        } else if !matched {
            self.confirming = 0;
            self.next_clock = self.resume;
            return EndstopEvent::Rearm(self.resume);
        }
        self.confirming -= 1;
        if self.confirming == 0 {
            self.homing = false;
            return EndstopEvent::Trigger {
                trsync_oid: p.trsync_oid,
                reason: p.trigger_reason,
            };
        }
        EndstopEvent::Rearm(at.add(p.sample_ticks))
    }

    /// Shutdown: stop homing.
    pub fn halt(&mut self) {
        self.homing = false;
        self.confirming = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params(count: u8) -> HomeParams {
        HomeParams {
            clock: WireClock(1000),
            sample_ticks: 15,
            sample_count: count,
            rest_ticks: 100,
            pin_value: true,
            trsync_oid: 3,
            trigger_reason: 1,
        }
    }

    /// Drives the endstop with `pin(at)` until it triggers; returns the reads and the trigger.
    fn run(e: &mut Endstop, first: WireClock, pin: impl Fn(u32) -> bool) -> (Vec<u32>, Option<u32>) {
        let mut reads = Vec::new();
        let mut at = first;
        for _ in 0..100 {
            reads.push(at.0);
            match e.event(at, pin(at.0)) {
                EndstopEvent::Rearm(t) => at = t,
                EndstopEvent::Trigger { trsync_oid, reason } => {
                    assert_eq!((trsync_oid, reason), (3, 1));
                    return (reads, Some(at.0));
                }
                EndstopEvent::Idle => break,
            }
        }
        (reads, None)
    }

    #[test]
    fn rests_then_confirms() {
        let mut e = Endstop::new(5, true);
        let first = e.home(params(4)).unwrap();
        let (reads, trig) = run(&mut e, first, |t| t >= 1250);
        assert_eq!(reads, [1000, 1100, 1200, 1300, 1315, 1330, 1345]);
        assert_eq!(trig, Some(1345));
        assert!(!e.homing());
        // Klipper's meaning: first matching read (1300) + rest_ticks; the host subtracts them.
        assert_eq!(e.next_clock(), WireClock(1400));
        assert_eq!(e.home(params(0)), None, "a cancel keeps next_clock");
        assert_eq!(e.next_clock(), WireClock(1400));
        assert_eq!(e.event(WireClock(2000), true), EndstopEvent::Idle);
    }

    #[test]
    fn next_clock_while_resting_and_confirming() {
        let mut e = Endstop::new(5, true);
        let first = e.home(params(4)).unwrap();
        assert_eq!(e.next_clock(), WireClock(1000), "armed: the first read");
        assert_eq!(e.event(first, false), EndstopEvent::Rearm(WireClock(1100)));
        assert_eq!(e.next_clock(), WireClock(1100), "resting: the next read");
        assert_eq!(
            e.event(WireClock(1100), true),
            EndstopEvent::Rearm(WireClock(1115))
        );
        assert_eq!(e.next_clock(), WireClock(1200), "confirming: first match + rest");
        assert_eq!(
            e.event(WireClock(1115), false),
            EndstopEvent::Rearm(WireClock(1200))
        );
        assert_eq!(e.next_clock(), WireClock(1200), "glitch: resting resumes there");
        assert!(e.homing());
    }

    #[test]
    fn a_glitch_resumes_resting() {
        let mut e = Endstop::new(5, true);
        let first = e.home(params(3)).unwrap();
        // A short pulse at 1100..1120, then the real trigger from 1400.
        let (reads, trig) = run(&mut e, first, |t| (1100..1120).contains(&t) || t >= 1400);
        assert_eq!(reads, [1000, 1100, 1115, 1130, 1200, 1300, 1400, 1415, 1430]);
        assert_eq!(trig, Some(1430));
    }

    #[test]
    fn single_sample_and_cancel() {
        let mut e = Endstop::new(5, false);
        let first = e.home(params(1)).unwrap();
        assert_eq!(run(&mut e, first, |_| true), (vec![1000], Some(1000)));
        assert_eq!(e.home(params(0)), None);
        assert!(!e.homing());
        let mut p = params(4);
        p.clock = WireClock(0);
        assert_eq!(e.home(p), None);
        e.home(params(2));
        e.halt();
        assert_eq!(e.event(WireClock(1000), true), EndstopEvent::Idle);
    }
}
