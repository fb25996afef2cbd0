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
//!
//! Stop on trigger (Klipper's "needs reset" state): when the trsync it is attached to fires,
//! the stepper drops its active move and its queue ([`Stepper::discard`]) and from then on
//! silently discards every `queue_step` (no shutdown, no move-pool slot used) until the next
//! `reset_step_clock`. So step commands that were already on their way when the trigger
//! happened can never restart it, and the host re-anchors the step clock before new moves.
//! The position stays the count of steps actually taken. A shutdown leaves it in the same
//! state.

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
    /// `Some(t)`: the stepper was idle, arm its timer at `t`. `None`: the move waits in the
    /// queue (or was discarded).
    pub arm_at: Option<WireClock>,
    /// The stepper needs a `reset_step_clock` (stopped by a trigger): the move was dropped.
    pub discarded: bool,
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
    /// Stopped by a trigger (or a shutdown): `queue_step` is ignored until `reset_step_clock`.
    need_reset: bool,
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
            need_reset: false,
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

    /// True after a stop on trigger until the next `reset_step_clock`: `queue_step` is ignored.
    pub const fn needs_reset(&self) -> bool {
        self.need_reset
    }

    /// Clock of the first step of a `queue_step` with `interval`, if it were queued now.
    pub fn next_first_clock(&self, interval: u32) -> WireClock {
        self.last_clock.add(interval)
    }

    /// `set_next_step_dir`.
    pub fn set_next_dir(&mut self, dir: bool) {
        self.next_dir = dir;
    }

    /// `reset_step_clock`: only valid while idle; ends the "needs reset" state.
    pub fn reset_clock(&mut self, clock: WireClock) -> Result<(), StepperError> {
        if self.is_active() {
            return Err(StepperError::ResetWhileActive);
        }
        self.last_clock = clock;
        self.need_reset = false;
        Ok(())
    }

    /// `queue_step`. An idle stepper loads the move right away (refusing it if its first
    /// step is before `now`); a busy one queues it in `pool`; a stepper that needs a reset
    /// drops it (`discarded`, nothing changes; count 0 is still refused).
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
        if self.need_reset {
            return Ok(Queued {
                first_clock,
                arm_at: None,
                discarded: true,
            });
        }
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
        Ok(Queued {
            first_clock,
            arm_at,
            discarded: false,
        })
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

    /// Shutdown: drop the active move and the queue (the caller clears the pool); needs a
    /// reset from now on.
    pub fn stop(&mut self) {
        self.count = 0;
        self.queue = MoveQueue::new();
        self.stop_on = None;
        self.need_reset = true;
    }

    /// The trsync this stepper is attached to (`stepper_stop_on_trigger`), if any.
    pub const fn stop_on(&self) -> Option<u8> {
        self.stop_on
    }

    /// `stepper_stop_on_trigger`: stop when trsync `trsync_oid` triggers (`None` detaches).
    pub fn set_stop_on(&mut self, trsync_oid: Option<u8>) {
        self.stop_on = trsync_oid;
    }

    /// A trsync trigger: drop the active move and give every queued move back to `pool`, and
    /// ignore `queue_step` until the next `reset_step_clock`. The position stays where the last
    /// executed step left it; the caller disarms the timer.
    pub fn discard<const N: usize>(&mut self, pool: &mut MovePool<N>) {
        self.count = 0;
        while pool.pop(&mut self.queue).is_some() {}
        self.stop_on = None;
        self.need_reset = true;
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

    /// Runs due steps of `s` up to and including clock `until`; returns the next wake time.
    fn run_until<const N: usize>(
        s: &mut Stepper,
        pool: &mut MovePool<N>,
        mut wake: Option<WireClock>,
        until: u32,
    ) -> Option<WireClock> {
        while let Some(at) = wake.filter(|t| t.0 <= until) {
            wake = s.step_event(pool, at).unwrap().next;
        }
        wake
    }

    #[test]
    fn trigger_mid_queue_stops_and_needs_reset() {
        let mut pool = MovePool::<8>::new(8);
        let mut s = Stepper::new(StepperConfig::default());
        s.reset_clock(WireClock(1000)).unwrap();
        s.set_next_dir(true);
        let mut wake = s
            .queue_step(&mut pool, 100, 5, 0, WireClock(1000))
            .unwrap()
            .arm_at;
        s.queue_step(&mut pool, 100, 5, 0, WireClock(1000)).unwrap();
        s.set_next_dir(false);
        s.queue_step(&mut pool, 50, 4, 0, WireClock(1000)).unwrap();
        assert_eq!(pool.used(), 2);
        // Steps at 1100, 1200, …: seven taken by 1750, inside the second move.
        wake = run_until(&mut s, &mut pool, wake, 1750);
        assert_eq!(wake, Some(WireClock(1800)));
        assert_eq!(s.position(), 7);
        s.discard(&mut pool);
        assert!(!s.is_active() && s.needs_reset());
        assert_eq!(pool.used(), 0, "the queued moves went back to the pool");
        assert_eq!(
            s.step_event(&mut pool, WireClock(1800)),
            None,
            "stale timer: no step"
        );
        assert_eq!(s.position(), 7, "the position is the steps actually taken");

        // Later queue_steps (e.g. sent before the host knew of the trigger) are dropped.
        let q = s.queue_step(&mut pool, 100, 3, 0, WireClock(1800)).unwrap();
        assert!(q.discarded);
        assert_eq!(q.arm_at, None);
        // Even one whose first step is long past: dropped, not "Timer too close".
        let q = s.queue_step(&mut pool, 1, 1, 0, WireClock(1_000_000)).unwrap();
        assert!(q.discarded);
        assert_eq!(
            s.queue_step(&mut pool, 100, 0, 0, WireClock(1800)),
            Err(StepperError::InvalidCount),
            "count 0 is still a protocol error"
        );
        assert!(!s.is_active() && pool.used() == 0);
        assert_eq!(s.position(), 7);

        // reset_step_clock re-enables it; new moves start from the new base.
        s.reset_clock(WireClock(5000)).unwrap();
        assert!(!s.needs_reset());
        s.set_next_dir(false);
        let q = s.queue_step(&mut pool, 10, 3, 0, WireClock(4000)).unwrap();
        assert!(!q.discarded);
        assert_eq!(q.arm_at, Some(WireClock(5010)));
        assert_eq!(run_until(&mut s, &mut pool, q.arm_at, u32::MAX), None);
        assert_eq!(s.position(), 4);
        assert_eq!(s.next_first_clock(10), WireClock(5040));
    }

    #[test]
    fn shutdown_stop_also_needs_reset() {
        let mut pool = MovePool::<2>::new(2);
        let mut s = Stepper::new(StepperConfig::default());
        assert!(!s.needs_reset(), "a fresh stepper takes moves");
        s.queue_step(&mut pool, 100, 1, 0, WireClock(0)).unwrap();
        s.stop();
        pool.clear();
        assert!(s.needs_reset());
        assert!(
            s.queue_step(&mut pool, 100, 1, 0, WireClock(0))
                .unwrap()
                .discarded
        );
    }

    proptest! {
        /// A stop after any number of executed steps: the position is exactly the net count of
        /// the steps taken, nothing runs until a reset, and the pool is whole again.
        #[test]
        fn stop_anywhere_keeps_the_exact_position(
            moves in proptest::collection::vec((1u32..500, 1u16..20, any::<bool>()), 1..8),
            stop_after in 0usize..200,
        ) {
            let mut pool = MovePool::<16>::new(16);
            let mut s = Stepper::new(StepperConfig::default());
            s.reset_clock(WireClock(0)).unwrap();
            let mut wake = None;
            for &(i, c, d) in &moves {
                s.set_next_dir(d);
                wake = wake.or(s.queue_step(&mut pool, i, c, 0, WireClock(0)).unwrap().arm_at);
            }
            let mut expect = 0i32;
            let mut taken = 0;
            while let Some(at) = wake.filter(|_| taken < stop_after) {
                let t = s.step_event(&mut pool, at).unwrap();
                expect += if t.dir { 1 } else { -1 };
                taken += 1;
                wake = t.next;
            }
            s.discard(&mut pool);
            prop_assert_eq!(s.position(), expect);
            prop_assert_eq!(pool.used(), 0);
            prop_assert!(s.queue_step(&mut pool, 10, 1, 0, WireClock(0)).unwrap().discarded);
            prop_assert_eq!(s.position(), expect);
        }

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
