//! A hardware PWM output (Klipper's `config_pwm_out`): the chip's PWM unit drives the pin at
//! `cycle_ticks` per cycle with a duty of `value / PWM_MAX`; the MCU only schedules duty changes.
//!
//! `queue_pwm_out clock value` schedules a change at `clock`; changes wait in a small FIFO
//! ([`QUEUE_LEN`]). `max_duration` (non-zero): once a change leaves the duty away from
//! `default_value`, the next change must come within `max_duration` ticks, else the MCU shuts
//! down ("Missed scheduling of next hard pwm event"); a change queued further than that after
//! the one in force is refused ("Scheduled pwm event will exceed max_duration"). On shutdown
//! the duty returns to `default_value`.

use rt_core::WireClock;

/// Scheduled changes a PWM output can hold.
pub const QUEUE_LEN: usize = 8;

/// `config_pwm_out` parameters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct PwmOutConfig {
    /// The pin.
    pub pin: u8,
    /// Ticks per PWM cycle.
    pub cycle_ticks: u32,
    /// Initial duty (0..=PWM_MAX).
    pub value: u16,
    /// Duty on shutdown.
    pub default_value: u16,
    /// Longest time away from the default without a change (0 = unlimited).
    pub max_duration: u32,
}

/// Why a PWM command or event failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PwmOutError {
    /// A change scheduled in the past, or the `max_duration` deadline passed.
    Missed,
    /// The FIFO is full.
    QueueFull,
    /// A change queued further than `max_duration` after the one away from the default.
    ExceedsMaxDuration,
}

/// The state of one hardware PWM output.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PwmOut {
    config: PwmOutConfig,
    value: u16,
    queue: [(WireClock, u16); QUEUE_LEN],
    head: usize,
    len: usize,
    deadline: Option<WireClock>,
    /// The latest change queued or applied, and whether it is away from the default.
    last: Option<(WireClock, bool)>,
}

impl PwmOut {
    /// `config_pwm_out` (the caller sets the pin to `config.value`).
    pub const fn new(config: PwmOutConfig) -> PwmOut {
        PwmOut {
            config,
            value: config.value,
            queue: [(WireClock(0), 0); QUEUE_LEN],
            head: 0,
            len: 0,
            deadline: None,
            last: None,
        }
    }

    /// The configuration.
    pub const fn config(&self) -> &PwmOutConfig {
        &self.config
    }

    /// The duty in force.
    pub const fn value(&self) -> u16 {
        self.value
    }

    /// `queue_pwm_out` received at `now`.
    pub fn queue(&mut self, clock: WireClock, value: u16, now: WireClock) -> Result<(), PwmOutError> {
        if clock.is_before(now) {
            return Err(PwmOutError::Missed);
        }
        if self.len == QUEUE_LEN {
            return Err(PwmOutError::QueueFull);
        }
        let limit = self.config.max_duration;
        if let Some((last, true)) = self.last.filter(|_| limit > 0) {
            if last.add(limit).is_before(clock) {
                return Err(PwmOutError::ExceedsMaxDuration);
            }
        }
        self.last = Some((clock, value != self.config.default_value));
        self.queue[(self.head + self.len) % QUEUE_LEN] = (clock, value);
        self.len += 1;
        Ok(())
    }

    /// When the timer must fire next.
    pub fn next_wake(&self) -> Option<WireClock> {
        let front = (self.len > 0).then(|| self.queue[self.head].0);
        match (front, self.deadline) {
            (Some(f), Some(d)) => Some(if d.is_before(f) { d } else { f }),
            (f, d) => f.or(d),
        }
    }

    /// The timer fired at `at`: the new duty if a change was applied.
    pub fn event(&mut self, at: WireClock) -> Result<Option<u16>, PwmOutError> {
        if self.len > 0 && !at.is_before(self.queue[self.head].0) {
            let (_, value) = self.queue[self.head];
            self.head = (self.head + 1) % QUEUE_LEN;
            self.len -= 1;
            self.value = value;
            let away = value != self.config.default_value && self.config.max_duration > 0;
            self.deadline = away.then(|| at.add(self.config.max_duration));
            return Ok(Some(value));
        }
        if self.deadline.is_some_and(|d| !at.is_before(d)) {
            return Err(PwmOutError::Missed);
        }
        Ok(None)
    }

    /// Shutdown: back to the default duty, nothing scheduled. Returns that duty.
    pub fn halt(&mut self) -> u16 {
        self.len = 0;
        self.deadline = None;
        self.last = None;
        self.value = self.config.default_value;
        self.value
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn out(max_duration: u32) -> PwmOut {
        PwmOut::new(PwmOutConfig {
            pin: 3,
            cycle_ticks: 100,
            value: 0,
            default_value: 0,
            max_duration,
        })
    }

    #[test]
    fn changes_apply_at_their_clocks_in_order() {
        let mut p = out(0);
        p.queue(WireClock(100), 128, WireClock(0)).unwrap();
        p.queue(WireClock(200), 255, WireClock(0)).unwrap();
        assert_eq!(p.next_wake(), Some(WireClock(100)));
        assert_eq!(p.event(WireClock(100)), Ok(Some(128)));
        assert_eq!(p.next_wake(), Some(WireClock(200)));
        assert_eq!(p.event(WireClock(200)), Ok(Some(255)));
        assert_eq!(p.value(), 255);
        assert_eq!(p.next_wake(), None, "no max_duration: nothing more to do");
        assert_eq!(p.halt(), 0);
    }

    #[test]
    fn max_duration_and_the_queue_are_enforced() {
        let mut p = out(1000);
        p.queue(WireClock(100), 200, WireClock(0)).unwrap();
        assert_eq!(
            p.queue(WireClock(1200), 100, WireClock(0)),
            Err(PwmOutError::ExceedsMaxDuration)
        );
        assert_eq!(p.event(WireClock(100)), Ok(Some(200)));
        assert_eq!(p.next_wake(), Some(WireClock(1100)));
        assert_eq!(p.event(WireClock(1100)), Err(PwmOutError::Missed));
        assert_eq!(p.queue(WireClock(5), 1, WireClock(10)), Err(PwmOutError::Missed));
        let mut q = out(0);
        for i in 0..QUEUE_LEN as u32 {
            q.queue(WireClock(10 + i), 1, WireClock(0)).unwrap();
        }
        assert_eq!(
            q.queue(WireClock(100), 1, WireClock(0)),
            Err(PwmOutError::QueueFull)
        );
    }
}
