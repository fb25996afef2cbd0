//! The simulated MCU clock: `(CLOCK_MONOTONIC − start) × time_scale × clock_freq` ticks.
//!
//! Ticks are computed from nanoseconds in f64: exact to the tick for 2^53 ticks (5.7 years at
//! 50 MHz). The inverse, [`SimClock::wall_until`], turns a tick deadline into a sleep.

use std::time::{Duration, Instant};

/// Maps `Instant` (CLOCK_MONOTONIC on Linux) to 64-bit MCU ticks.
#[derive(Debug, Clone, Copy)]
pub struct SimClock {
    start: Instant,
    ticks_per_ns: f64,
}

impl SimClock {
    /// A clock at tick 0 now, running `time_scale × clock_freq` ticks per wall second.
    pub fn start(clock_freq: u32, time_scale: f64) -> SimClock {
        SimClock {
            start: Instant::now(),
            ticks_per_ns: ticks_per_ns(clock_freq, time_scale),
        }
    }

    /// The current MCU clock.
    pub fn now(&self) -> u64 {
        ticks_at(self.start.elapsed(), self.ticks_per_ns)
    }

    /// CLOCK_MONOTONIC (ns) at tick 0 (to within the nanoseconds between two clock reads).
    pub fn monotonic_start_ns(&self) -> Option<u64> {
        let now = nix::time::clock_gettime(nix::time::ClockId::CLOCK_MONOTONIC).ok()?;
        let now_ns = u64::try_from(now.tv_sec()).ok()? * 1_000_000_000 + u64::try_from(now.tv_nsec()).ok()?;
        now_ns.checked_sub(u64::try_from(self.start.elapsed().as_nanos()).ok()?)
    }

    /// MCU ticks per CLOCK_MONOTONIC ns.
    pub fn ticks_per_ns(&self) -> f64 {
        self.ticks_per_ns
    }

    /// Wall time from MCU clock `now` until `deadline` (zero if it has passed).
    pub fn wall_until(&self, now: u64, deadline: u64) -> Duration {
        wall_for_ticks(deadline.saturating_sub(now), self.ticks_per_ns)
    }
}

fn ticks_per_ns(clock_freq: u32, time_scale: f64) -> f64 {
    clock_freq as f64 * time_scale / 1e9
}

fn ticks_at(elapsed: Duration, ticks_per_ns: f64) -> u64 {
    (elapsed.as_nanos() as f64 * ticks_per_ns) as u64
}

/// Rounded up, so a sleep never ends before the deadline tick.
fn wall_for_ticks(ticks: u64, ticks_per_ns: f64) -> Duration {
    let ns = (ticks as f64 / ticks_per_ns).ceil();
    if ns.is_finite() && ns < 1e18 {
        Duration::from_nanos(ns as u64)
    } else {
        Duration::from_secs(3600)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scale_and_inverse() {
        let r = ticks_per_ns(50_000_000, 1.0);
        assert_eq!(ticks_at(Duration::from_secs(2), r), 100_000_000);
        let r10 = ticks_per_ns(50_000_000, 10.0);
        assert_eq!(ticks_at(Duration::from_millis(100), r10), 50_000_000);
        assert_eq!(wall_for_ticks(50_000_000, r10), Duration::from_millis(100));
        assert_eq!(wall_for_ticks(1, r), Duration::from_nanos(20));
        for t in [0u64, 1, 7, 12_345, 1 << 40] {
            let d = wall_for_ticks(t, r);
            assert!(ticks_at(d, r) >= t, "sleeping {d:?} reaches tick {t}");
        }
    }

    #[test]
    fn clock_is_monotonic() {
        let c = SimClock::start(1_000_000, 1.0);
        let a = c.now();
        let b = c.now();
        assert!(b >= a);
        assert_eq!(c.wall_until(10, 5), Duration::ZERO);
    }
}
