//! One stepper: replays `queue_step` moves against the MCU clock.
//!
//! Step semantics (docs/contract.md): `queue_step interval=i count=n add=a` means, repeated n
//! times, `last_clock += i; step at last_clock; i += a` (all wrapping u32 arithmetic). So the
//! k-th step (k = 1..n) of a move lands at `base + k·i + a·k(k−1)/2`, and the move ends at
//! `base + n·i + a·n(n−1)/2`; that end is the base of the next move. The stepper keeps the base
//! for the next queued move in `last_clock` (so a move's first step time is known the moment
//! it is queued), and replays the active move one step per timer event, each step time derived
//! from the previous *scheduled* step time, so lateness of the timer never accumulates.
//!
//! The stepper never touches the scheduler: its methods return the clock at which its timer
//! must fire next, and the caller arms it.

use super::moves::{Move, MovePool, MoveQueue};
use rt_core::WireClock;

/// `config_stepper` parameters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct StepperConfig {
    /// Step pin number (see the `pin` enumeration).
    pub step_pin: u8,
    /// Direction pin number.
    pub dir_pin: u8,
    /// Step pin is active low.
    pub invert_step: bool,
    /// Minimum step pulse width in ticks.
    pub step_pulse_ticks: u32,
}

/// Why a stepper command was refused (each maps to one shutdown reason).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StepperError {
    /// `queue_step` with count 0.
    InvalidCount,
    /// The first step of a move loaded right away is already in the past.
    TimerTooClose,
    /// The move pool is full.
    QueueOverflow,
    /// `reset_step_clock` while moves are queued or running.
    ResetWhileActive,
}

/// What a successful `queue_step` did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Queued {
    /// Clock of the move's first step.
    pub first_clock: WireClock,
    /// `Some(t)`: the stepper was idle, arm its timer at `t`. `None`: the move waits in the queue.
    pub arm_at: Option<WireClock>,
}

/// A step the timer event just took.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StepTaken {
    /// Direction of the step.
    pub dir: bool,
    /// When to fire next, if more steps are queued.
    pub next: Option<WireClock>,
}

/// Clock at which a move of `count` steps starting from `base` ends (its last step).
pub fn move_end(base: WireClock, interval: u32, count: u16, add: i16) -> WireClock {
    let n = count as i64;
    let span = n
        .wrapping_mul(interval as i64)
        .wrapping_add((add as i64).wrapping_mul(n * (n - 1) / 2));
    base.add(span as u32)
}

/// The state of one stepper.
#[derive(Debug, Clone)]
pub struct Stepper {
    config: StepperConfig,
    /// Direction for the next `queue_step`.
    next_dir: bool,
    /// Last step of everything queued so far: the base of the next `queue_step`.
    last_clock: WireClock,
    /// Steps left in the active move, counting the one the timer is armed for.
    count: u32,
    interval: u32,
    add: i16,
    dir: bool,
    queue: MoveQueue,
    position: i32,
    /// `stepper_stop_on_trigger`: the trsync whose trigger stops this stepper.
    stop_on: Option<u8>,
}

impl Stepper {
    /// A freshly configured, idle stepper at position 0 with `last_clock` 0.
    pub const fn new(config: StepperConfig) -> Stepper {
        Stepper {
            config,
            next_dir: false,
            last_clock: WireClock(0),
            count: 0,
            interval: 0,
            add: 0,
            dir: false,
            queue: MoveQueue::new(),
            position: 0,
            stop_on: None,
        }
    }

    /// The `config_stepper` parameters.
    pub const fn config(&self) -> &StepperConfig {
        &self.config
    }

    /// Net steps executed since configuration (+1 per step with dir = 1).
    pub const fn position(&self) -> i32 {
        self.position
    }

    /// True while a move is running or queued.
    pub const fn is_active(&self) -> bool {
        self.count > 0
    }

    /// Clock of the first step of a `queue_step` with `interval`, if it were queued now.
    pub fn next_first_clock(&self, interval: u32) -> WireClock {
        self.last_clock.add(interval)
    }

    /// `set_next_step_dir`.
    pub fn set_next_dir(&mut self, dir: bool) {
        self.next_dir = dir;
    }

    /// `reset_step_clock`: only valid while idle.
    pub fn reset_clock(&mut self, clock: WireClock) -> Result<(), StepperError> {
        if self.is_active() {
            return Err(StepperError::ResetWhileActive);
        }
        self.last_clock = clock;
        Ok(())
    }

    /// `queue_step`. An idle stepper loads the move right away (refusing it if its first
    /// step is before `now`); a busy one queues it in `pool`.
    pub fn queue_step<const N: usize>(
        &mut self,
        pool: &mut MovePool<N>,
        interval: u32,
        count: u16,
        add: i16,
        now: WireClock,
    ) -> Result<Queued, StepperError> {
        if count == 0 {
            return Err(StepperError::InvalidCount);
        }
        let first_clock = self.last_clock.add(interval);
        let arm_at = if self.is_active() {
            if !pool.push(&mut self.queue, Move::new(interval, count, add, self.next_dir)) {
                return Err(StepperError::QueueOverflow);
            }
            None
        } else {
            if first_clock.is_before(now) {
                return Err(StepperError::TimerTooClose);
            }
            self.load(Move::new(interval, count, add, self.next_dir));
            Some(first_clock)
        };
        self.last_clock = move_end(self.last_clock, interval, count, add);
        Ok(Queued { first_clock, arm_at })
    }

    fn load(&mut self, m: Move) {
        self.count = m.count as u32;
        self.interval = m.interval;
        self.add = m.add;
        self.dir = m.dir;
    }

    /// The timer fired for the step scheduled at `at`: take it and say when the next is due.
    /// Returns `None` if the stepper was idle (a stale timer; nothing happens).
    pub fn step_event<const N: usize>(&mut self, pool: &mut MovePool<N>, at: WireClock) -> Option<StepTaken> {
        if self.count == 0 {
            return None;
        }
        let dir = self.dir;
        self.position = self.position.wrapping_add(if dir { 1 } else { -1 });
        self.count -= 1;
        let next = if self.count > 0 {
            self.interval = self.interval.wrapping_add(self.add as i32 as u32);
            Some(at.add(self.interval))
        } else if let Some(m) = pool.pop(&mut self.queue) {
            self.load(m);
            Some(at.add(m.interval))
        } else {
            None
        };
        Some(StepTaken { dir, next })
    }

    /// Shutdown: drop the active move and the queue (the caller clears the pool).
    pub fn stop(&mut self) {
        self.count = 0;
        self.queue = MoveQueue::new();
        self.stop_on = None;
    }

    /// The trsync this stepper is attached to (`stepper_stop_on_trigger`), if any.
    pub const fn stop_on(&self) -> Option<u8> {
        self.stop_on
    }

    /// `stepper_stop_on_trigger`: stop when trsync `trsync_oid` triggers (`None` detaches).
    pub fn set_stop_on(&mut self, trsync_oid: Option<u8>) {
        self.stop_on = trsync_oid;
    }

    /// A trsync trigger: drop the active move and give every queued move back to `pool`. The
    /// position stays where the last executed step left it; the caller disarms the timer.
    pub fn discard<const N: usize>(&mut self, pool: &mut MovePool<N>) {
        self.count = 0;
        while pool.pop(&mut self.queue).is_some() {}
        self.stop_on = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The contract's loop, in 64-bit arithmetic: the reference every replay must match.
    fn reference(base: u64, moves: &[(u32, u16, i16, bool)]) -> Vec<(u64, bool)> {
        let mut last = base;
        let mut out = Vec::new();
        for &(interval, count, add, dir) in moves {
            let mut i = interval;
            for _ in 0..count {
                last += i as u64;
                out.push((last, dir));
                i = i.wrapping_add(add as i32 as u32);
            }
        }
        out
    }

    /// Queues all moves at `now = base`, then fires timers in order; steps as 64-bit clocks.
    fn replay(base: u64, moves: &[(u32, u16, i16, bool)]) -> Vec<(u64, bool)> {
        let mut pool = MovePool::<64>::new(64);
        let mut s = Stepper::new(StepperConfig::default());
        let now = WireClock(base as u32);
        s.reset_clock(now).unwrap();
        let mut wake = None;
        for &(interval, count, add, dir) in moves {
            s.set_next_dir(dir);
            let q = s.queue_step(&mut pool, interval, count, add, now).unwrap();
            wake = wake.or(q.arm_at);
        }
        let mut out = Vec::new();
        let mut clock64 = rt_core::McuClock(base);
        while let Some(at) = wake {
            clock64 = clock64.extend(at);
            let t = s.step_event(&mut pool, at).unwrap();
            out.push((clock64.0, t.dir));
            wake = t.next;
        }
        assert!(!s.is_active());
        out
    }

    #[test]
    fn simple_accelerating_move() {
        let moves = [(1000, 4, -100, true), (500, 2, 0, false)];
        let steps = replay(0, &moves);
        let clocks: Vec<u64> = steps.iter().map(|s| s.0).collect();
        assert_eq!(clocks, [1000, 1900, 2700, 3400, 3900, 4400]);
        assert_eq!(steps, reference(0, &moves));
    }

    #[test]
    fn move_end_matches_loop() {
        let base = WireClock(u32::MAX - 10);
        let end = move_end(base, 7, 5, 3);
        // 7 + 10 + 13 + 16 + 19 = 65
        assert_eq!(end, base.add(65));
    }

    #[test]
    fn refusals() {
        let mut pool = MovePool::<2>::new(1);
        let mut s = Stepper::new(StepperConfig::default());
        let now = WireClock(10_000);
        assert_eq!(
            s.queue_step(&mut pool, 100, 0, 0, now),
            Err(StepperError::InvalidCount)
        );
        assert_eq!(
            s.queue_step(&mut pool, 100, 1, 0, now),
            Err(StepperError::TimerTooClose)
        );
        s.reset_clock(now).unwrap();
        let q = s.queue_step(&mut pool, 100, 1, 0, now).unwrap();
        assert_eq!(q.arm_at, Some(WireClock(10_100)));
        assert_eq!(s.reset_clock(now), Err(StepperError::ResetWhileActive));
        assert_eq!(s.queue_step(&mut pool, 100, 1, 0, now).unwrap().arm_at, None);
        assert_eq!(
            s.queue_step(&mut pool, 100, 1, 0, now),
            Err(StepperError::QueueOverflow)
        );
        s.stop();
        pool.clear();
        assert!(!s.is_active());
        assert_eq!(s.step_event(&mut pool, WireClock(0)), None);
    }

    #[test]
    fn position_counts_executed_steps() {
        let mut pool = MovePool::<4>::new(4);
        let mut s = Stepper::new(StepperConfig::default());
        s.set_next_dir(true);
        let mut at = s.queue_step(&mut pool, 10, 3, 0, WireClock(0)).unwrap().arm_at;
        s.set_next_dir(false);
        s.queue_step(&mut pool, 10, 1, 0, WireClock(0)).unwrap();
        let mut positions = Vec::new();
        while let Some(t) = at {
            at = s.step_event(&mut pool, t).unwrap().next;
            positions.push(s.position());
        }
        assert_eq!(positions, [1, 2, 3, 2]);
    }

    proptest! {
        /// Postcondition: the replay reproduces the contract loop exactly, across the 32-bit wrap.
        #[test]
        fn replay_matches_reference(
            base in prop_oneof![Just(u32::MAX as u64 - 5000), 0u64..(1 << 40)],
            moves in proptest::collection::vec((1u32..20_000, 1u16..50, -20i16..20, any::<bool>()), 1..12),
        ) {
            // Keep intervals positive so the steps stay in time order (as the host guarantees).
            let moves: Vec<_> = moves.into_iter().map(|(i, c, a, d)| {
                let a = if (i as i64) + (a as i64) * (c as i64) < 1 { 0 } else { a };
                (i, c, a, d)
            }).collect();
            prop_assert_eq!(replay(base, &moves), reference(base, &moves));
        }
    }
}
