//! The timer scheduler: one timer slot per oid on the MCU's 32-bit wrapping clock.
//!
//! Armed slots are kept in a small array sorted by wake time, so the next wake time is the
//! front entry and a due timer is popped from the front. Wake times are compared only through
//! [`WireClock::is_before`], which is correct while all armed timers lie within 2^31 ticks of
//! each other (43 s at 50 MHz; steps are queued at most a few seconds ahead). Equal wake times
//! run in the order they were armed. Insertion scans from the back: a re-armed step timer is
//! usually the latest one, so the common case is O(1); the list holds at most `N` entries.
//!
//! The scheduler never reads a clock: `now` is an argument of [`Scheduler::pop_due`].

use rt_core::WireClock;

/// Timers of up to `N` (≤ 256) slots, addressed by slot number (the oid).
#[derive(Debug, Clone)]
pub struct Scheduler<const N: usize> {
    wake: [WireClock; N],
    armed: [bool; N],
    /// Armed slots, earliest wake time first.
    order: [u8; N],
    len: usize,
}

impl<const N: usize> Default for Scheduler<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> Scheduler<N> {
    /// An empty scheduler.
    pub const fn new() -> Self {
        const { assert!(N <= 256, "timer slots are addressed by a u8") };
        Scheduler {
            wake: [WireClock(0); N],
            armed: [false; N],
            order: [0; N],
            len: 0,
        }
    }

    /// Arms (or re-arms) slot `id` to fire at `at`. Returns false if `id` is out of range.
    pub fn arm(&mut self, id: u8, at: WireClock) -> bool {
        let slot = id as usize;
        if slot >= N {
            return false;
        }
        self.disarm(id);
        // Find the insertion point from the back: after every entry not later than `at`.
        let mut pos = self.len;
        while pos > 0 && at.is_before(self.wake[self.order[pos - 1] as usize]) {
            pos -= 1;
        }
        self.order.copy_within(pos..self.len, pos + 1);
        self.order[pos] = id;
        self.len += 1;
        self.wake[slot] = at;
        self.armed[slot] = true;
        true
    }

    /// Disarms slot `id` (no effect if it is not armed).
    pub fn disarm(&mut self, id: u8) {
        let slot = id as usize;
        if slot >= N || !self.armed[slot] {
            return;
        }
        self.armed[slot] = false;
        if let Some(pos) = self.order[..self.len].iter().position(|&o| o == id) {
            self.order.copy_within(pos + 1..self.len, pos);
            self.len -= 1;
        }
    }

    /// Disarms every slot.
    pub fn clear(&mut self) {
        self.armed = [false; N];
        self.len = 0;
    }

    /// The wake time of slot `id`, if it is armed.
    pub fn wake_time(&self, id: u8) -> Option<WireClock> {
        let slot = id as usize;
        (slot < N && self.armed[slot]).then(|| self.wake[slot])
    }

    /// The earliest wake time of any armed slot.
    pub fn next_wake(&self) -> Option<WireClock> {
        (self.len > 0).then(|| self.wake[self.order[0] as usize])
    }

    /// Number of armed slots.
    pub fn armed_count(&self) -> usize {
        self.len
    }

    /// Removes and returns the earliest timer whose wake time is not after `now`, as
    /// `(slot, wake time)`. Call repeatedly until `None` to run every due timer.
    pub fn pop_due(&mut self, now: WireClock) -> Option<(u8, WireClock)> {
        if self.len == 0 {
            return None;
        }
        let id = self.order[0];
        let at = self.wake[id as usize];
        if now.is_before(at) {
            return None;
        }
        self.order.copy_within(1..self.len, 0);
        self.len -= 1;
        self.armed[id as usize] = false;
        Some((id, at))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn pops_in_time_order_across_the_wrap() {
        let mut s = Scheduler::<8>::new();
        let base = WireClock(u32::MAX - 100);
        s.arm(3, base.add(150)); // wraps to 49
        s.arm(1, base.add(10));
        s.arm(2, base.add(100)); // u32::MAX exactly
        s.arm(0, base.add(200));
        assert_eq!(s.next_wake(), Some(base.add(10)));
        let now = base.add(160);
        assert_eq!(s.pop_due(now), Some((1, base.add(10))));
        assert_eq!(s.pop_due(now), Some((2, base.add(100))));
        assert_eq!(s.pop_due(now), Some((3, base.add(150))));
        assert_eq!(s.pop_due(now), None);
        assert_eq!(s.next_wake(), Some(base.add(200)));
        assert_eq!(s.pop_due(base.add(200)), Some((0, base.add(200))));
        assert_eq!(s.next_wake(), None);
    }

    #[test]
    fn equal_times_run_in_arming_order_and_rearm_moves() {
        let mut s = Scheduler::<4>::new();
        s.arm(2, WireClock(50));
        s.arm(0, WireClock(50));
        s.arm(1, WireClock(50));
        s.arm(2, WireClock(60)); // re-arm moves slot 2 behind the others
        let order: Vec<u8> = core::iter::from_fn(|| s.pop_due(WireClock(100)).map(|t| t.0)).collect();
        assert_eq!(order, [0, 1, 2]);
    }

    #[test]
    fn disarm_out_of_range_and_clear() {
        let mut s = Scheduler::<2>::new();
        assert!(!s.arm(2, WireClock(1)));
        assert!(s.arm(1, WireClock(5)));
        assert!(s.arm(0, WireClock(7)));
        assert_eq!(s.wake_time(1), Some(WireClock(5)));
        s.disarm(1);
        assert_eq!(s.wake_time(1), None);
        assert_eq!(s.next_wake(), Some(WireClock(7)));
        assert_eq!(s.pop_due(WireClock(6)), None);
        s.clear();
        assert_eq!(s.armed_count(), 0);
        assert_eq!(s.pop_due(WireClock(100)), None);
    }

    proptest! {
        /// Postcondition: timers come out sorted by their (unwrapped) time, whatever the base.
        #[test]
        fn order_matches_sorted_offsets(base in any::<u32>(), offs in proptest::collection::vec(0u32..1_000_000, 1..16)) {
            let mut s = Scheduler::<16>::new();
            for (i, &o) in offs.iter().enumerate() {
                s.arm(i as u8, WireClock(base).add(o));
            }
            let mut expect: Vec<(u32, usize)> = offs.iter().enumerate().map(|(i, &o)| (o, i)).collect();
            expect.sort();
            let now = WireClock(base).add(1_000_000);
            for (o, i) in expect {
                prop_assert_eq!(s.pop_due(now), Some((i as u8, WireClock(base).add(o))));
            }
            prop_assert_eq!(s.pop_due(now), None);
        }
    }
}
