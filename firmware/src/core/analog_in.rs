//! An analog input sampled periodically and reported as a sum of samples.
//!
//! `query_analog_in clock sample_ticks sample_count rest_ticks min_value max_value
//! range_check_count`: starting at `clock`, take `sample_count` ADC readings `sample_ticks`
//! apart and report their sum (saturating at 65535) as `analog_in_state next_clock value`,
//! where `next_clock` = the start of the next round = previous start + `rest_ticks`. A sum
//! outside `[min_value, max_value]` in `range_check_count` consecutive rounds (0 = never) shuts
//! the MCU down with "ADC out of range". `sample_count = 0` stops sampling.

use rt_core::WireClock;

/// `query_analog_in` parameters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct AnalogQuery {
    /// Start of the first round.
    pub clock: WireClock,
    /// Ticks between readings of one round.
    pub sample_ticks: u32,
    /// Readings per round.
    pub sample_count: u8,
    /// Ticks between round starts.
    pub rest_ticks: u32,
    /// Smallest valid sum.
    pub min_value: u16,
    /// Largest valid sum.
    pub max_value: u16,
    /// Consecutive invalid rounds that shut down (0 = no range check).
    pub range_check_count: u8,
}

/// What a reading produced.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AnalogEvent {
    /// Read again at this clock (mid-round).
    Rearm(WireClock),
    /// A round ended: report `value`; the next round starts at `next_clock` (arm there).
    Report {
        /// Start of the next round.
        next_clock: WireClock,
        /// Sum of the round's readings.
        value: u16,
    },
    /// Too many rounds out of range: shut down.
    OutOfRange,
    /// Not sampling.
    Idle,
}

/// The state of one analog input.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AnalogIn {
    /// The pin (a GPIO number, or [`ADC_TEMPERATURE_PIN`]).
    ///
    /// [`ADC_TEMPERATURE_PIN`]: super::constants::ADC_TEMPERATURE_PIN
    pub pin: u32,
    q: AnalogQuery,
    active: bool,
    round_start: WireClock,
    taken: u8,
    sum: u32,
    invalid: u8,
}

impl AnalogIn {
    /// `config_analog_in`.
    pub const fn new(pin: u32) -> AnalogIn {
        AnalogIn {
            pin,
            q: AnalogQuery {
                clock: WireClock(0),
                sample_ticks: 0,
                sample_count: 0,
                rest_ticks: 0,
                min_value: 0,
                max_value: 0,
                range_check_count: 0,
            },
            active: false,
            round_start: WireClock(0),
            taken: 0,
            sum: 0,
            invalid: 0,
        }
    }

    /// `query_analog_in`: the clock to arm at, or `None` if sampling stopped.
    pub fn query(&mut self, q: AnalogQuery) -> Option<WireClock> {
        self.q = q;
        self.active = q.sample_count > 0;
        self.round_start = q.clock;
        self.taken = 0;
        self.sum = 0;
        self.invalid = 0;
        self.active.then_some(q.clock)
    }

    /// The timer fired at `at` and the ADC reads `value`.
    pub fn event(&mut self, at: WireClock, value: u16) -> AnalogEvent {
        if !self.active {
            return AnalogEvent::Idle;
        }
        self.sum = self.sum.saturating_add(value as u32);
        self.taken += 1;
        if self.taken < self.q.sample_count {
            return AnalogEvent::Rearm(at.add(self.q.sample_ticks));
        }
        let value = u16::try_from(self.sum).unwrap_or(u16::MAX);
        self.sum = 0;
        self.taken = 0;
        self.round_start = self.round_start.add(self.q.rest_ticks);
        if self.q.range_check_count > 0 && (value < self.q.min_value || value > self.q.max_value) {
            self.invalid = self.invalid.saturating_add(1);
            if self.invalid >= self.q.range_check_count {
                self.active = false;
                return AnalogEvent::OutOfRange;
            }
        } else {
            self.invalid = 0;
        }
        AnalogEvent::Report {
            next_clock: self.round_start,
            value,
        }
    }

    /// Shutdown: stop sampling.
    pub fn halt(&mut self) {
        self.active = false;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn query(range_check_count: u8) -> AnalogQuery {
        AnalogQuery {
            clock: WireClock(1000),
            sample_ticks: 10,
            sample_count: 3,
            rest_ticks: 500,
            min_value: 100,
            max_value: 10_000,
            range_check_count,
        }
    }

    #[test]
    fn sums_rounds_and_reports_next_start() {
        let mut a = AnalogIn::new(4);
        let mut at = a.query(query(0)).unwrap();
        let mut got = Vec::new();
        for i in 0..6u16 {
            match a.event(at, 100 * (i + 1)) {
                AnalogEvent::Rearm(t) => at = t,
                AnalogEvent::Report { next_clock, value } => {
                    got.push((at.0, next_clock.0, value));
                    at = next_clock;
                }
                e => panic!("{e:?}"),
            }
        }
        assert_eq!(got, [(1020, 1500, 600), (1520, 2000, 1500)]);
        assert_eq!(a.query(AnalogQuery::default()), None);
        assert_eq!(a.event(WireClock(3000), 1), AnalogEvent::Idle);
    }

    #[test]
    fn range_check_counts_consecutive_rounds() {
        let mut a = AnalogIn::new(4);
        let mut at = a.query(query(2)).unwrap();
        let mut outcome = Vec::new();
        for v in [1u16, 1, 1, 1000, 1000, 1000, 1, 1, 1, 1, 1, 1] {
            match a.event(at, v) {
                AnalogEvent::Rearm(t) => at = t,
                AnalogEvent::Report { next_clock, value } => {
                    outcome.push(Some(value));
                    at = next_clock;
                }
                AnalogEvent::OutOfRange => {
                    outcome.push(None);
                    break;
                }
                AnalogEvent::Idle => break,
            }
        }
        // 3 (bad), 3000 (good, resets), 3 (bad), 3 (bad: second in a row) → shutdown.
        assert_eq!(outcome, [Some(3), Some(3000), Some(3), None]);
        let mut a = AnalogIn::new(4);
        a.query(AnalogQuery {
            sample_count: 30,
            ..query(0)
        });
        let mut last = AnalogEvent::Idle;
        for i in 0..30 {
            last = a.event(WireClock(1000 + i), 4095);
        }
        assert!(matches!(last, AnalogEvent::Report { value: u16::MAX, .. }));
    }
}
