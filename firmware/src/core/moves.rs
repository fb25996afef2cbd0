//! The move pool: every stepper's queued `queue_step` moves share one fixed array of `N` slots.
//!
//! Each stepper owns a [`MoveQueue`] (head and tail slot numbers); slots are linked through
//! their `next` field. A slot is taken from the free list, or else from the never-used tail of
//! the array (so construction needs no initialisation loop). The pool reports at most `limit`
//! moves in use at once: `limit` is the `move_count` the MCU advertises in `config`
//! (`limit ≤ N ≤ 65535`, since `move_count` is a 16-bit field and `u16::MAX` marks "no slot").

/// "No slot" in a link field.
const NIL: u16 = u16::MAX;

/// One queued `queue_step`: `count` steps, the first `interval` ticks after the previous step,
/// the interval growing by `add` after each step, all in direction `dir`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Move {
    /// Ticks from the previous step to the first step of this move.
    pub interval: u32,
    /// Number of steps (never 0).
    pub count: u16,
    /// Change of the interval after each step.
    pub add: i16,
    /// Direction: true = position +1 per step.
    pub dir: bool,
    next: u16,
}

impl Move {
    const EMPTY: Move = Move {
        interval: 0,
        count: 0,
        add: 0,
        dir: false,
        next: NIL,
    };

    /// A move (not yet linked into any queue).
    pub const fn new(interval: u32, count: u16, add: i16, dir: bool) -> Move {
        Move {
            interval,
            count,
            add,
            dir,
            next: NIL,
        }
    }
}

/// A FIFO of moves inside a [`MovePool`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MoveQueue {
    head: u16,
    tail: u16,
}

impl Default for MoveQueue {
    fn default() -> Self {
        Self::new()
    }
}

impl MoveQueue {
    /// An empty queue.
    pub const fn new() -> Self {
        MoveQueue { head: NIL, tail: NIL }
    }

    /// True when no move is queued.
    pub const fn is_empty(&self) -> bool {
        self.head == NIL
    }
}

/// The shared storage of `N` move slots.
#[derive(Debug, Clone)]
pub struct MovePool<const N: usize> {
    slots: [Move; N],
    free: u16,
    fresh: usize,
    used: usize,
    limit: usize,
}

impl<const N: usize> MovePool<N> {
    /// A pool that hands out at most `limit` (clamped to `N`) moves at once.
    pub const fn new(limit: usize) -> Self {
        const { assert!(N < NIL as usize, "move slots are addressed by a u16") };
        MovePool {
            slots: [Move::EMPTY; N],
            free: NIL,
            fresh: 0,
            used: 0,
            limit: if limit < N { limit } else { N },
        }
    }

    /// The most moves that can be queued at once (the advertised `move_count`).
    pub const fn limit(&self) -> usize {
        self.limit
    }

    /// Moves queued right now, over all queues.
    pub const fn used(&self) -> usize {
        self.used
    }

    /// Appends `m` to `queue`. Returns false (and changes nothing) when the pool is full.
    pub fn push(&mut self, queue: &mut MoveQueue, m: Move) -> bool {
        if self.used >= self.limit {
            return false;
        }
        let idx = if self.free != NIL {
            let idx = self.free;
            self.free = self.slots[idx as usize].next;
            idx
        } else if self.fresh < N {
            self.fresh += 1;
            (self.fresh - 1) as u16
        } else {
            return false;
        };
        self.slots[idx as usize] = Move { next: NIL, ..m };
        if queue.tail == NIL {
            queue.head = idx;
        } else {
            self.slots[queue.tail as usize].next = idx;
        }
        queue.tail = idx;
        self.used += 1;
        true
    }

    /// Removes and returns the first move of `queue`.
    pub fn pop(&mut self, queue: &mut MoveQueue) -> Option<Move> {
        if queue.head == NIL {
            return None;
        }
        let idx = queue.head;
        let m = self.slots.get(idx as usize).copied()?;
        queue.head = m.next;
        if queue.head == NIL {
            queue.tail = NIL;
        }
        self.slots[idx as usize].next = self.free;
        self.free = idx;
        self.used -= 1;
        Some(Move { next: NIL, ..m })
    }

    /// Frees every slot. Every [`MoveQueue`] of this pool must be reset to empty as well.
    pub fn clear(&mut self) {
        self.free = NIL;
        self.fresh = 0;
        self.used = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fifo_per_queue_and_shared_limit() {
        let mut pool = MovePool::<8>::new(3);
        let (mut a, mut b) = (MoveQueue::new(), MoveQueue::new());
        assert!(pool.push(&mut a, Move::new(10, 1, 0, true)));
        assert!(pool.push(&mut b, Move::new(20, 2, 0, false)));
        assert!(pool.push(&mut a, Move::new(11, 3, -1, true)));
        assert!(!pool.push(&mut b, Move::new(21, 1, 0, false)), "limit 3 reached");
        assert_eq!(pool.used(), 3);
        assert_eq!(pool.pop(&mut a).map(|m| m.interval), Some(10));
        assert!(
            pool.push(&mut b, Move::new(21, 1, 0, false)),
            "freed slot is reused"
        );
        assert_eq!(pool.pop(&mut a).map(|m| m.interval), Some(11));
        assert_eq!(pool.pop(&mut a), None);
        assert!(a.is_empty());
        assert_eq!(pool.pop(&mut b).map(|m| m.interval), Some(20));
        assert_eq!(pool.pop(&mut b).map(|m| m.interval), Some(21));
        assert_eq!(pool.used(), 0);
    }

    #[test]
    fn limit_is_clamped_to_capacity_and_clear_resets() {
        let mut pool = MovePool::<2>::new(100);
        assert_eq!(pool.limit(), 2);
        let mut q = MoveQueue::new();
        assert!(pool.push(&mut q, Move::new(1, 1, 0, true)));
        assert!(pool.push(&mut q, Move::new(2, 1, 0, true)));
        assert!(!pool.push(&mut q, Move::new(3, 1, 0, true)));
        pool.clear();
        let mut q = MoveQueue::new();
        assert!(pool.push(&mut q, Move::new(4, 1, 0, true)));
        assert_eq!(pool.pop(&mut q).map(|m| m.interval), Some(4));
    }

    #[test]
    fn churn_never_loses_slots() {
        let mut pool = MovePool::<4>::new(4);
        let mut q = MoveQueue::new();
        for i in 0..1000u32 {
            assert!(pool.push(&mut q, Move::new(i, 1, 0, true)));
            if i % 3 != 0 {
                assert!(pool.pop(&mut q).is_some());
            }
            if pool.used() == 4 {
                while pool.pop(&mut q).is_some() {}
            }
        }
    }
}
