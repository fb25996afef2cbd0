//! A digital output pin with scheduled updates and software PWM.
//!
//! `queue_digital_out clock on_ticks` schedules an update at `clock`: `on_ticks = 0` is off,
//! `on_ticks ≥ cycle_ticks` (or any non-zero value while `cycle_ticks = 0`) is on, anything in
//! between is software PWM — on at the update clock `c`, off at `c + on_ticks`, on again at
//! `c + cycle_ticks`, and so on until the next update. Updates wait in a FIFO per output whose
//! slots come from one [`UpdatePool`] shared by every digital out of the MCU ([`POOL_LEN`]
//! updates in all), as Klipper's MCU takes them from its shared move queue: a rarely used
//! output costs no slots, and one output can queue a burst (a Smart Effector's sensitivity
//! command, 3 bytes of 14 bits at 1 ms, is up to 43 level changes scheduled together). `max_duration` (non-zero): after an update leaves the pin away from its
//! default, the next update must be applied within `max_duration` ticks, else the MCU shuts down
//! ("Missed scheduling of next digital out event"); an update queued more than `max_duration`
//! after the previous one, which leaves the pin away from its default, is refused at once
//! ("Scheduled digital out event will exceed max_duration"). `update_digital_out` sets the pin
//! at once. A heater's pin thus turns itself off when the host stops sending updates.
//!
//! The timer wakes at the earliest of the next queued update, the next PWM edge and the
//! `max_duration` deadline.

use rt_core::WireClock;

/// Scheduled updates every digital out of an MCU can hold together.
pub const POOL_LEN: usize = 128;

/// "No slot" in a link field.
const NIL: u8 = u8::MAX;

/// One queued update: its clock, its `on_ticks`, the next slot of its output's FIFO.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Slot {
    clock: WireClock,
    on_ticks: u32,
    next: u8,
}

/// The update slots shared by the digital outs: a free list threaded through `next`, and the
/// never-used tail of the array (so construction needs no loop).
#[derive(Debug, Clone)]
pub struct UpdatePool {
    slots: [Slot; POOL_LEN],
    free: u8,
    /// Slots never used yet start here.
    fresh: usize,
    used: usize,
}

impl Default for UpdatePool {
    fn default() -> Self {
        Self::new()
    }
}

impl UpdatePool {
    /// An empty pool.
    pub const fn new() -> UpdatePool {
        UpdatePool {
            slots: [Slot {
                clock: WireClock(0),
                on_ticks: 0,
                next: NIL,
            }; POOL_LEN],
            free: NIL,
            fresh: 0,
            used: 0,
        }
    }

    /// Slots in use.
    pub const fn used(&self) -> usize {
        self.used
    }

    /// Every slot free again (shutdown, `config_reset`).
    pub fn clear(&mut self) {
        *self = UpdatePool::new();
    }

    fn alloc(&mut self, clock: WireClock, on_ticks: u32) -> Option<u8> {
        let i = if self.free != NIL {
            let i = self.free;
            self.free = self.slots[usize::from(i)].next;
            i
        } else if self.fresh < POOL_LEN {
            self.fresh += 1;
            u8::try_from(self.fresh - 1).ok()?
        } else {
            return None;
        };
        self.slots[usize::from(i)] = Slot {
            clock,
            on_ticks,
            next: NIL,
        };
        self.used += 1;
        Some(i)
    }

    fn release(&mut self, i: u8) {
        self.slots[usize::from(i)].next = self.free;
        self.free = i;
        self.used = self.used.saturating_sub(1);
    }
}

/// `config_digital_out` parameters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct DigitalOutConfig {
    /// The pin.
    pub pin: u8,
    /// Initial value.
    pub value: bool,
    /// Value on shutdown.
    pub default_value: bool,
    /// Longest time away from the default without an update (0 = unlimited).
    pub max_duration: u32,
}

/// Why a digital out command or event failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DigitalOutError {
    /// An update scheduled in the past, or the `max_duration` deadline passed.
    Missed,
    /// The shared update pool is full.
    QueueFull,
    /// An update queued more than `max_duration` after the previous one, which left the pin
    /// away from its default.
    ExceedsMaxDuration,
}

/// The state of one digital out.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DigitalOut {
    config: DigitalOutConfig,
    cycle_ticks: u32,
    value: bool,
    /// First and last slot of its FIFO in the [`UpdatePool`].
    head: u8,
    tail: u8,
    on_ticks: u32,
    cycle_start: WireClock,
    toggle_at: Option<WireClock>,
    deadline: Option<WireClock>,
    /// The latest update queued or applied, and whether it leaves the pin away from default.
    last_update: Option<(WireClock, bool)>,
}

fn earliest(a: Option<WireClock>, b: Option<WireClock>) -> Option<WireClock> {
    match (a, b) {
        (Some(x), Some(y)) => Some(if y.is_before(x) { y } else { x }),
        (x, y) => x.or(y),
    }
}

impl DigitalOut {
    /// `config_digital_out` (the caller sets the pin to `config.value`).
    pub const fn new(config: DigitalOutConfig) -> DigitalOut {
        DigitalOut {
            config,
            cycle_ticks: 0,
            value: config.value,
            head: NIL,
            tail: NIL,
            on_ticks: 0,
            cycle_start: WireClock(0),
            toggle_at: None,
            deadline: None,
            last_update: None,
        }
    }

    /// The configuration.
    pub const fn config(&self) -> &DigitalOutConfig {
        &self.config
    }

    /// The pin's current level.
    pub const fn value(&self) -> bool {
        self.value
    }

    /// `set_digital_out_pwm_cycle`.
    pub fn set_cycle(&mut self, cycle_ticks: u32) {
        self.cycle_ticks = cycle_ticks;
    }

    /// `queue_digital_out` received at `now`, its slot from `pool`.
    pub fn queue(
        &mut self,
        pool: &mut UpdatePool,
        clock: WireClock,
        on_ticks: u32,
        now: WireClock,
    ) -> Result<(), DigitalOutError> {
        if clock.is_before(now) {
            return Err(DigitalOutError::Missed);
        }
        let limit = self.config.max_duration;
        if let Some((last, true)) = self.last_update.filter(|_| limit > 0) {
            if last.add(limit).is_before(clock) {
                return Err(DigitalOutError::ExceedsMaxDuration);
            }
        }
        let slot = pool.alloc(clock, on_ticks).ok_or(DigitalOutError::QueueFull)?;
        match self.tail {
            NIL => self.head = slot,
            t => pool.slots[usize::from(t)].next = slot,
        }
        self.tail = slot;
        self.last_update = Some((clock, self.is_away(on_ticks)));
        Ok(())
    }

    /// The queued updates given back to `pool`.
    fn drop_queue(&mut self, pool: &mut UpdatePool) {
        while self.head != NIL {
            let i = self.head;
            self.head = pool.slots[usize::from(i)].next;
            pool.release(i);
        }
        self.tail = NIL;
    }

    /// `update_digital_out` at `now`: the new level (queued updates are dropped).
    pub fn update(&mut self, pool: &mut UpdatePool, value: bool, now: WireClock) -> bool {
        self.drop_queue(pool);
        let on_ticks = if value { u32::MAX } else { 0 };
        self.last_update = Some((now, self.is_away(on_ticks)));
        self.apply(on_ticks, now)
    }

    fn is_on(&self, on_ticks: u32) -> bool {
        on_ticks > 0
    }

    fn is_pwm(&self, on_ticks: u32) -> bool {
        on_ticks > 0 && self.cycle_ticks > 0 && on_ticks < self.cycle_ticks
    }

    /// True if `on_ticks` leaves the pin away from its default (PWM counts as away).
    fn is_away(&self, on_ticks: u32) -> bool {
        self.is_on(on_ticks) != self.config.default_value || self.is_pwm(on_ticks)
    }

    fn apply(&mut self, on_ticks: u32, at: WireClock) -> bool {
        self.on_ticks = on_ticks;
        self.value = self.is_on(on_ticks);
        let pwm = self.is_pwm(on_ticks);
        self.cycle_start = at;
        self.toggle_at = pwm.then(|| at.add(on_ticks));
        let away = self.is_away(on_ticks);
        self.deadline = (away && self.config.max_duration > 0).then(|| at.add(self.config.max_duration));
        self.value
    }

    /// When the timer must fire next.
    pub fn next_wake(&self, pool: &UpdatePool) -> Option<WireClock> {
        let front = (self.head != NIL).then(|| pool.slots[usize::from(self.head)].clock);
        earliest(earliest(front, self.toggle_at), self.deadline)
    }

    /// The timer fired at `at`: the pin's new level if it changed.
    pub fn event(&mut self, pool: &mut UpdatePool, at: WireClock) -> Result<Option<bool>, DigitalOutError> {
        let before = self.value;
        let front = (self.head != NIL).then(|| pool.slots[usize::from(self.head)]);
        if let Some(slot) = front.filter(|s| !at.is_before(s.clock)) {
            pool.release(self.head);
            self.head = slot.next;
            if self.head == NIL {
                self.tail = NIL;
            }
            self.apply(slot.on_ticks, at);
        } else if self.toggle_at.is_some_and(|t| !at.is_before(t)) {
            if self.value {
                self.value = false;
                self.toggle_at = Some(self.cycle_start.add(self.cycle_ticks));
            } else {
                self.value = true;
                self.cycle_start = self.cycle_start.add(self.cycle_ticks);
                self.toggle_at = Some(self.cycle_start.add(self.on_ticks));
            }
        } else if self.deadline.is_some_and(|d| !at.is_before(d)) {
            return Err(DigitalOutError::Missed);
        }
        Ok((self.value != before).then_some(self.value))
    }

    /// Shutdown: back to the default level, nothing scheduled (the caller clears the pool).
    /// Returns that level.
    pub fn halt(&mut self) -> bool {
        self.head = NIL;
        self.tail = NIL;
        self.toggle_at = None;
        self.deadline = None;
        self.last_update = None;
        self.value = self.config.default_value;
        self.value
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn out(max_duration: u32) -> DigitalOut {
        DigitalOut::new(DigitalOutConfig {
            pin: 1,
            value: false,
            default_value: false,
            max_duration,
        })
    }

    /// Runs every event until `until`; returns (clock, level) of each change.
    fn run(d: &mut DigitalOut, p: &mut UpdatePool, until: u32) -> Result<Vec<(u32, bool)>, DigitalOutError> {
        let mut edges = Vec::new();
        while let Some(t) = d.next_wake(p).filter(|t| t.0 <= until) {
            if let Some(v) = d.event(p, t)? {
                edges.push((t.0, v));
            }
        }
        Ok(edges)
    }

    #[test]
    fn scheduled_on_off_and_pwm() {
        let mut p = UpdatePool::new();
        let mut d = out(0);
        d.set_cycle(100);
        d.queue(&mut p, WireClock(1000), 100, WireClock(0)).unwrap(); // fully on
        d.queue(&mut p, WireClock(1500), 0, WireClock(0)).unwrap();
        d.queue(&mut p, WireClock(2000), 30, WireClock(0)).unwrap(); // 30 % PWM
        d.queue(&mut p, WireClock(2250), 0, WireClock(0)).unwrap();
        let edges = run(&mut d, &mut p, 5000).unwrap();
        assert_eq!(
            edges,
            [
                (1000, true),
                (1500, false),
                (2000, true),
                (2030, false),
                (2100, true),
                (2130, false),
                (2200, true),
                (2230, false)
            ]
        );
        assert_eq!(d.next_wake(&p), None);
    }

    #[test]
    fn past_update_and_max_duration_are_missed() {
        let mut p = UpdatePool::new();
        let mut d = out(500);
        assert_eq!(
            d.queue(&mut p, WireClock(10), 1, WireClock(20)),
            Err(DigitalOutError::Missed)
        );
        d.queue(&mut p, WireClock(100), 1, WireClock(20)).unwrap();
        assert_eq!(run(&mut d, &mut p, 599), Ok(vec![(100, true)]));
        assert_eq!(run(&mut d, &mut p, 600), Err(DigitalOutError::Missed));
        // Renewed in time: no fault; back at the default: no deadline.
        let mut d = out(500);
        d.queue(&mut p, WireClock(100), 1, WireClock(0)).unwrap();
        d.queue(&mut p, WireClock(550), 0, WireClock(0)).unwrap();
        assert_eq!(run(&mut d, &mut p, 10_000), Ok(vec![(100, true), (550, false)]));
        for i in 0..POOL_LEN as u32 {
            d.queue(&mut p, WireClock(20_000 + i), 0, WireClock(0)).unwrap();
        }
        assert_eq!(
            d.queue(&mut p, WireClock(30_000), 0, WireClock(0)),
            Err(DigitalOutError::QueueFull)
        );
        assert!(d.update(&mut p, true, WireClock(11_000)));
        assert_eq!(p.used(), 0, "an update gives the queued slots back");
        // Queued too far after an update that left the pin on: refused at once.
        let mut far = out(500);
        far.queue(&mut p, WireClock(100), 1, WireClock(0)).unwrap();
        far.queue(&mut p, WireClock(600), 1, WireClock(0)).unwrap();
        assert_eq!(
            far.queue(&mut p, WireClock(1101), 0, WireClock(0)),
            Err(DigitalOutError::ExceedsMaxDuration)
        );
        far.queue(&mut p, WireClock(1100), 0, WireClock(0)).unwrap();
        far.queue(&mut p, WireClock(90_000), 1, WireClock(0)).unwrap(); // after an off: any time
        assert_eq!(d.next_wake(&p), Some(WireClock(11_500)));
        p.clear();
        assert!(!d.halt());
        assert_eq!(d.next_wake(&p), None);
    }

    #[test]
    fn outputs_share_the_pool_and_give_slots_back() {
        let mut p = UpdatePool::new();
        let (mut a, mut b) = (out(0), out(0));
        // One output can take most of the pool (a burst of 100 level changes)…
        for i in 0..100u32 {
            a.queue(&mut p, WireClock(1000 + 10 * i), i % 2, WireClock(0))
                .unwrap();
        }
        for i in 0..28u32 {
            b.queue(&mut p, WireClock(5000 + i), 0, WireClock(0)).unwrap();
        }
        assert_eq!(
            b.queue(&mut p, WireClock(9000), 0, WireClock(0)),
            Err(DigitalOutError::QueueFull)
        );
        // …and each applied update frees its slot, in FIFO order per output.
        let edges = run(&mut a, &mut p, 2000).unwrap();
        // (The first update, off, changes nothing.)
        assert_eq!(edges.first(), Some(&(1010, true)));
        assert_eq!(edges.len(), 99);
        assert_eq!(p.used(), 28);
        assert_eq!(b.next_wake(&p), Some(WireClock(5000)));
        b.queue(&mut p, WireClock(9000), 1, WireClock(0)).unwrap();
        let edges = run(&mut b, &mut p, 10_000).unwrap();
        assert_eq!(edges, [(9000, true)]);
        assert_eq!(p.used(), 0);
    }
}
