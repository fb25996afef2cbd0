//! Time types. Cadence has three clocks (see docs/architecture.md):
//!
//! | type | unit | owner |
//! |---|---|---|
//! | [`SystemTime`] | seconds of `CLOCK_MONOTONIC` (f64) | the host OS |
//! | [`PrintTime`] | seconds on the main MCU's timeline (f64) | the planner |
//! | [`McuClock`] | ticks of one MCU's `CLOCK_FREQ`, 64-bit | the host's view of an MCU |
//! | [`WireClock`] | the low 32 bits of an [`McuClock`] | the wire and the MCU itself |
//!
//! 32-bit clocks wrap (every ~86 s at 50 MHz). They are compared only through
//! [`WireClock::is_before`] and widened only through [`McuClock::extend`].

/// Seconds of the host's monotonic clock.
#[derive(Debug, Clone, Copy, PartialEq, PartialOrd, Default)]
pub struct SystemTime(pub f64);

/// Seconds on the main MCU's timeline; every move is scheduled in print time.
#[derive(Debug, Clone, Copy, PartialEq, PartialOrd, Default)]
pub struct PrintTime(pub f64);

/// A 64-bit MCU clock as the host tracks it (never wraps in practice: 11,000 years at 50 MHz).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub struct McuClock(pub u64);

/// The 32-bit clock an MCU keeps and the wire carries. Wraps; compare with [`Self::is_before`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct WireClock(pub u32);

impl WireClock {
    /// True when `self` is strictly before `other`, assuming the two are less than 2^31 ticks
    /// apart. Correct across the wrap: the wrapping difference, read as a signed number, is the
    /// true (short) distance between the two instants.
    #[inline]
    pub const fn is_before(self, other: WireClock) -> bool {
        (self.0.wrapping_sub(other.0) as i32) < 0
    }

    /// Signed ticks from `earlier` to `self` (valid while |distance| < 2^31).
    #[inline]
    pub const fn ticks_since(self, earlier: WireClock) -> i32 {
        self.0.wrapping_sub(earlier.0) as i32
    }

    /// This clock plus `ticks`, wrapping.
    #[inline]
    pub const fn add(self, ticks: u32) -> WireClock {
        WireClock(self.0.wrapping_add(ticks))
    }
}

impl McuClock {
    /// The 32 bits that go on the wire.
    #[inline]
    pub const fn wire(self) -> WireClock {
        WireClock(self.0 as u32)
    }

    /// Widens a 32-bit clock read from the wire using `self`, the last known 64-bit clock.
    ///
    /// Why it is correct: the true clock is within ±2^31 ticks of `self` (the host hears from
    /// each MCU far more often than every 43 s at 50 MHz), and exactly one 64-bit value in that
    /// window has the given low 32 bits: `self + signed(wire - low32(self))`.
    #[inline]
    pub const fn extend(self, wire: WireClock) -> McuClock {
        let delta = wire.0.wrapping_sub(self.0 as u32) as i32 as i64;
        McuClock(self.0.wrapping_add(delta as u64))
    }

    /// Ticks from `earlier` to `self`, saturating at 0.
    #[inline]
    pub const fn saturating_since(self, earlier: McuClock) -> u64 {
        self.0.saturating_sub(earlier.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn is_before_across_wrap() {
        let a = WireClock(u32::MAX - 5);
        let b = a.add(10);
        assert_eq!(b.0, 4);
        assert!(a.is_before(b));
        assert!(!b.is_before(a));
        assert!(!a.is_before(a));
        assert_eq!(b.ticks_since(a), 10);
        assert_eq!(a.ticks_since(b), -10);
    }

    #[test]
    fn extend_forward_and_backward() {
        let last = McuClock(0x1_FFFF_FFF0);
        assert_eq!(last.extend(WireClock(0x10)), McuClock(0x2_0000_0010));
        assert_eq!(last.extend(WireClock(0xFFFF_FF00)), McuClock(0x1_FFFF_FF00));
        let start = McuClock(5);
        assert_eq!(start.extend(WireClock(100)), McuClock(100));
    }

    #[test]
    fn extend_round_trips_within_window() {
        let base = McuClock(0x7_1234_5678);
        for d in [
            -(1i64 << 31) + 1,
            -1_000_000,
            -1,
            0,
            1,
            1_000_000,
            (1i64 << 31) - 1,
        ] {
            let truth = McuClock((base.0 as i64 + d) as u64);
            assert_eq!(base.extend(truth.wire()), truth, "delta {d}");
        }
    }
}
