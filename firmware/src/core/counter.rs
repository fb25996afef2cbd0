//! A pulse counter on an input pin (Klipper's `config_counter`, used for fan tachometers): a
//! timer reads the pin every `poll_ticks` and counts each change of level, noting the clock of
//! the last change; every `sample_ticks` it reports `counter_state next_clock count
//! count_clock` (the count's parity is the pin's level, as on Klipper's MCU).

use rt_core::WireClock;

/// The state of one counter.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Counter {
    /// The pin.
    pub pin: u8,
    poll_ticks: u32,
    sample_ticks: u32,
    next_sample: WireClock,
    count: u32,
    last_count_clock: WireClock,
    active: bool,
}

/// A report to send: `next_clock`, `count`, `count_clock`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CounterReport {
    /// The timer's next wake.
    pub next_clock: WireClock,
    /// Level changes so far.
    pub count: u32,
    /// Clock of the last change.
    pub count_clock: WireClock,
}

impl Counter {
    /// `config_counter`.
    pub const fn new(pin: u8) -> Counter {
        Counter {
            pin,
            poll_ticks: 0,
            sample_ticks: 0,
            next_sample: WireClock(0),
            count: 0,
            last_count_clock: WireClock(0),
            active: false,
        }
    }

    /// `query_counter`: the clock to arm at (none when `poll_ticks` is 0).
    pub fn query(&mut self, clock: WireClock, poll_ticks: u32, sample_ticks: u32) -> Option<WireClock> {
        self.poll_ticks = poll_ticks;
        self.sample_ticks = sample_ticks;
        // The first poll reports at once.
        self.next_sample = clock;
        self.active = poll_ticks > 0;
        self.active.then_some(clock)
    }

    /// The timer fired at `at` and the pin reads `level`: the next wake and a report if due.
    pub fn event(&mut self, at: WireClock, level: bool) -> (Option<WireClock>, Option<CounterReport>) {
        if !self.active {
            return (None, None);
        }
        if (self.count & 1 == 1) != level {
            self.count = self.count.wrapping_add(1);
            self.last_count_clock = at;
        }
        let next = at.add(self.poll_ticks);
        let report = (!at.is_before(self.next_sample)).then(|| {
            self.next_sample = at.add(self.sample_ticks);
            CounterReport {
                next_clock: next,
                count: self.count,
                count_clock: self.last_count_clock,
            }
        });
        (Some(next), report)
    }

    /// Shutdown: stop polling.
    pub fn halt(&mut self) {
        self.active = false;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_level_changes_and_reports_each_sample() {
        let mut c = Counter::new(4);
        assert_eq!(c.query(WireClock(100), 10, 50), Some(WireClock(100)));
        let mut reports = Vec::new();
        let mut at = WireClock(100);
        // A square wave of period 40 ticks: a change every 20.
        for _ in 0..20 {
            let level = (at.0 / 20) % 2 == 1;
            let (next, report) = c.event(at, level);
            reports.extend(report);
            at = next.unwrap();
        }
        // Polls at 100..=290, reports at 100, 150, 200 and 250; the line is high at the first
        // poll (a change from the count's even start), then changes at 120, 140, …: 8 changes
        // by the last report, the last at 240.
        assert_eq!(reports.len(), 4);
        let last = reports[3];
        assert_eq!(last.next_clock, WireClock(260));
        assert_eq!((last.count, last.count_clock), (8, WireClock(240)));
        c.halt();
        assert_eq!(c.event(at, true), (None, None));
    }
}
