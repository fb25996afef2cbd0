//! How the simulator waits for its next timer: sleep, then a short bounded spin.
//!
//! A kernel sleep wakes up late by tens of µs (more on a loaded machine), so the event loop
//! sleeps only until `window` before the next timer and busy-waits the rest, reading the
//! (vDSO) clock. When steps are dense (gaps shorter than `window`) that alone would turn into
//! one endless busy loop that keeps a core to itself — on a 2-core machine shared with the
//! host, the host then starves. So spinning is also bounded in a row: a *streak* (busy-waiting
//! since the last real sleep) lasts at most `window`; once it is used up, the loop sleeps until
//! the timer itself (giving the CPU away, accepting the wake-up delay) and a new streak starts
//! after that sleep. Hence in any stretch of wall time the loop busy-waits at most `window`
//! between two sleeps, and with `window` = 0 it never busy-waits.
//!
//! Running timers that are already due is work, not spinning: only waiting counts. The policy
//! never reads a clock; the caller passes `now`.

use std::time::{Duration, Instant};

/// Default spin window (`--spin-us`).
pub const DEFAULT_SPIN: Duration = Duration::from_micros(50);

/// What to do until the next timer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Wait {
    /// Busy-wait: check the clock again at once.
    Spin,
    /// Sleep (in `ppoll`) this long; zero means "just poll".
    Sleep(Duration),
}

/// The sleep-then-spin policy with a bounded streak.
#[derive(Debug, Clone, Copy)]
pub struct SpinPolicy {
    window: Duration,
    streak_start: Option<Instant>,
}

impl SpinPolicy {
    /// Spin at most `window` before a timer, and at most `window` in a row.
    pub fn new(window: Duration) -> SpinPolicy {
        SpinPolicy {
            window,
            streak_start: None,
        }
    }

    /// The spin window.
    pub fn window(&self) -> Duration {
        self.window
    }

    /// The next timer is `until_wake` of wall time away at `now`: spin or sleep, and how long.
    pub fn decide(&mut self, until_wake: Duration, now: Instant) -> Wait {
        if until_wake > self.window {
            // Far away: sleep until the window opens (a real sleep ends the streak).
            self.streak_start = None;
            return Wait::Sleep(until_wake - self.window);
        }
        let start = *self.streak_start.get_or_insert(now);
        if now.saturating_duration_since(start) < self.window {
            return Wait::Spin;
        }
        // Streak used up: sleep until the timer itself. A zero sleep does not give the CPU
        // away, so it does not end the streak either.
        if !until_wake.is_zero() {
            self.streak_start = None;
        }
        Wait::Sleep(until_wake)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const US: Duration = Duration::from_micros(1);

    #[test]
    fn sleeps_until_the_window_then_spins() {
        let t0 = Instant::now();
        let mut p = SpinPolicy::new(50 * US);
        assert_eq!(p.decide(1000 * US, t0), Wait::Sleep(950 * US));
        assert_eq!(p.decide(50 * US, t0 + 950 * US), Wait::Spin);
        assert_eq!(p.decide(10 * US, t0 + 990 * US), Wait::Spin);
        // The timer ran; the next one is far: sleep again, a new streak later.
        assert_eq!(p.decide(500 * US, t0 + 1000 * US), Wait::Sleep(450 * US));
        assert_eq!(p.decide(40 * US, t0 + 1460 * US), Wait::Spin);
    }

    #[test]
    fn dense_timers_cannot_spin_forever() {
        // A timer every 20 µs: the streak spans several timers, then the loop must sleep.
        let t0 = Instant::now();
        let mut p = SpinPolicy::new(50 * US);
        let mut now = t0;
        let mut spun_in_a_row = Duration::ZERO;
        let mut sleeps = 0;
        for _ in 0..1000 {
            let until = 20 * US - Duration::from_nanos((now - t0).as_nanos() as u64 % 20_000);
            match p.decide(until, now) {
                Wait::Spin => {
                    now += US;
                    spun_in_a_row += US;
                    assert!(spun_in_a_row <= 50 * US, "spun {spun_in_a_row:?} in a row");
                }
                Wait::Sleep(d) => {
                    assert!(d <= 20 * US);
                    if !d.is_zero() {
                        sleeps += 1;
                        spun_in_a_row = Duration::ZERO;
                    }
                    now += d + 30 * US; // the kernel wakes up late
                }
            }
        }
        assert!(sleeps > 10, "only {sleeps} sleeps");
    }

    #[test]
    fn zero_sleep_keeps_the_streak_and_zero_window_never_spins() {
        let t0 = Instant::now();
        let mut p = SpinPolicy::new(50 * US);
        assert_eq!(p.decide(10 * US, t0), Wait::Spin);
        assert_eq!(
            p.decide(Duration::ZERO, t0 + 60 * US),
            Wait::Sleep(Duration::ZERO)
        );
        assert_eq!(
            p.decide(5 * US, t0 + 61 * US),
            Wait::Sleep(5 * US),
            "no new streak without a real sleep"
        );
        assert_eq!(
            p.decide(5 * US, t0 + 100 * US),
            Wait::Spin,
            "a real sleep: new streak"
        );

        let mut never = SpinPolicy::new(Duration::ZERO);
        assert_eq!(never.window(), Duration::ZERO);
        for d in [0u32, 1, 49, 50, 1000] {
            assert_eq!(never.decide(US * d, t0), Wait::Sleep(US * d));
        }
    }
}
