//! The latest `counter_state` report of a pulse counter (fan tachometers), and of
//! `thermocouple_result` of an SPI temperature chip, kept lock-free for
//! the threads that read it: the IO thread is the only writer.
//!
//! Three words that belong together (next poll clock, count, clock of the last change) are
//! published under a sequence number (a seqlock): the writer makes it odd, stores, makes it
//! even again; a reader takes the words only when the sequence was even and unchanged around
//! its loads.

use std::sync::atomic::{AtomicU64, Ordering};

/// One counter's latest report.
#[derive(Debug, Default)]
pub struct CounterSlot {
    /// Even when stable; 0 before the first report.
    seq: AtomicU64,
    /// `count << 32 | count_clock`.
    counts: AtomicU64,
    /// `next_clock`.
    next: AtomicU64,
}

/// A `counter_state` report.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CounterReport {
    /// Reports so far (tells a new report from the one seen before).
    pub serial: u64,
    /// The counter's next poll (32-bit MCU clock).
    pub next_clock: u32,
    /// Level changes counted.
    pub count: u32,
    /// Clock of the last change (32-bit MCU clock).
    pub count_clock: u32,
}

/// A `thermocouple_result` report (kept in a [`CounterSlot`]: `next_clock`, `value`, `fault`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ThermocoupleReport {
    /// Reports so far (tells a new report from the one seen before).
    pub serial: u64,
    /// The chip's next read (32-bit MCU clock).
    pub next_clock: u32,
    /// The chip's raw value.
    pub value: u32,
    /// The chip's fault bits.
    pub fault: u8,
}

impl CounterSlot {
    /// Publishes a report (the IO thread only).
    pub(crate) fn store(&self, next_clock: u32, count: u32, count_clock: u32) {
        let s = self.seq.load(Ordering::Relaxed);
        // Odd: a write is under way (pairs with the Acquire loads of `load`).
        self.seq.store(s + 1, Ordering::Release);
        self.counts.store(
            (u64::from(count) << 32) | u64::from(count_clock),
            Ordering::Release,
        );
        self.next.store(u64::from(next_clock), Ordering::Release);
        self.seq.store(s + 2, Ordering::Release);
    }

    /// The latest report, `None` before the first.
    pub fn load(&self) -> Option<CounterReport> {
        loop {
            let s1 = self.seq.load(Ordering::Acquire);
            if s1 == 0 {
                return None;
            }
            if s1 % 2 == 1 {
                std::hint::spin_loop();
                continue;
            }
            let counts = self.counts.load(Ordering::Acquire);
            let next = self.next.load(Ordering::Acquire);
            if self.seq.load(Ordering::Acquire) == s1 {
                return Some(CounterReport {
                    serial: s1 / 2,
                    next_clock: next as u32,
                    count: (counts >> 32) as u32,
                    count_clock: counts as u32,
                });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reports_round_trip_with_a_serial() {
        let s = CounterSlot::default();
        assert_eq!(s.load(), None);
        s.store(10, 7, 5);
        s.store(20, 9, 15);
        assert_eq!(
            s.load(),
            Some(CounterReport {
                serial: 2,
                next_clock: 20,
                count: 9,
                count_clock: 15
            })
        );
    }
}
