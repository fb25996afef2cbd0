//! A bounded, preallocated queue that never waits on another thread: the hand-off for threads of
//! different real-time priorities (a link's outgoing messages to its IO thread, log records to
//! the logger).
//!
//! Why not `crossbeam_queue::ArrayQueue`: its `pop` spins while a `push` is half done (the
//! producer has claimed a slot but not yet published it), and its `push` spins while a `pop` is
//! half done. Under SCHED_FIFO that is a livelock whenever the waiting thread has preempted the
//! other one on the same core: the IO thread (FIFO 45 on the IO core) woke up in the middle of a
//! push by the IO stage (FIFO 40, same core) and spun in `pop` forever, the producer never ran
//! again (seen in a live print: the link's IO thread at 100% CPU in `ArrayQueue::pop`).
//!
//! Here neither side ever waits for the other: the ring of slots is Vyukov's bounded queue (a
//! sequence number per slot says whose turn it is), `pop` returns `None` when the oldest slot is
//! claimed but not yet published, and `push` returns the item when the slot it needs is still
//! being read. Each slot's value sits in its own `Mutex` (a safe cell: the sequence numbers
//! order every access, so the lock is never contended and never blocks). No allocation after
//! [`HandoffQueue::new`].
//!
//! Wake-up ordering: the publishing store and [`HandoffQueue::has_ready`] are SeqCst, so the
//! IO thread's "announce sleep, then look" and a producer's "publish, then wake" cannot both
//! miss each other (see `transport::wake`).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard};

/// The slot's value; a poisoned lock (a panic while holding it) still yields the value.
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

struct Slot<T> {
    /// `pos` when free for the push at position `pos`; `pos + 1` once that push published its
    /// value; `pos + capacity` once the pop at `pos` has taken it.
    seq: AtomicU64,
    value: Mutex<Option<T>>,
}

/// A bounded multi-producer, multi-consumer queue that never spins on another thread.
pub struct HandoffQueue<T> {
    slots: Box<[Slot<T>]>,
    /// Next push position.
    tail: AtomicU64,
    /// Next pop position.
    head: AtomicU64,
}

impl<T> std::fmt::Debug for HandoffQueue<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("HandoffQueue")
            .field("capacity", &self.capacity())
            .field("len", &self.len())
            .finish()
    }
}

impl<T> HandoffQueue<T> {
    /// A queue of `capacity` (at least 1) slots, all allocated now.
    pub fn new(capacity: usize) -> HandoffQueue<T> {
        let slots = (0..capacity.max(1) as u64)
            .map(|i| Slot {
                seq: AtomicU64::new(i),
                value: Mutex::new(None),
            })
            .collect();
        HandoffQueue {
            slots,
            tail: AtomicU64::new(0),
            head: AtomicU64::new(0),
        }
    }

    pub fn capacity(&self) -> usize {
        self.slots.len()
    }

    fn slot(&self, pos: u64) -> &Slot<T> {
        &self.slots[(pos % self.slots.len() as u64) as usize]
    }

    /// Appends `item`; gives it back when the queue is full (or its next slot is still being
    /// read by a pop that was interrupted).
    pub fn push(&self, item: T) -> Result<(), T> {
        let mut pos = self.tail.load(Ordering::Relaxed);
        loop {
            let slot = self.slot(pos);
            let seq = slot.seq.load(Ordering::Acquire);
            match seq.cmp(&pos) {
                std::cmp::Ordering::Equal => {
                    match self
                        .tail
                        .compare_exchange_weak(pos, pos + 1, Ordering::Relaxed, Ordering::Relaxed)
                    {
                        Ok(_) => {
                            *lock(&slot.value) = Some(item);
                            slot.seq.store(pos + 1, Ordering::SeqCst);
                            return Ok(());
                        }
                        Err(now) => pos = now,
                    }
                }
                // The slot still holds the item of the previous lap: full.
                std::cmp::Ordering::Less => return Err(item),
                // Another producer took this position: retry at the current tail.
                std::cmp::Ordering::Greater => pos = self.tail.load(Ordering::Relaxed),
            }
        }
    }

    /// Takes the oldest item; `None` when the queue is empty or the oldest item is not
    /// published yet (its producer was interrupted mid-push: it publishes when it runs again).
    pub fn pop(&self) -> Option<T> {
        let mut pos = self.head.load(Ordering::Relaxed);
        loop {
            let slot = self.slot(pos);
            let seq = slot.seq.load(Ordering::Acquire);
            match seq.cmp(&(pos + 1)) {
                std::cmp::Ordering::Equal => {
                    match self
                        .head
                        .compare_exchange_weak(pos, pos + 1, Ordering::Relaxed, Ordering::Relaxed)
                    {
                        Ok(_) => {
                            let item = lock(&slot.value).take();
                            slot.seq.store(pos + self.slots.len() as u64, Ordering::Release);
                            return item;
                        }
                        Err(now) => pos = now,
                    }
                }
                std::cmp::Ordering::Less => return None,
                std::cmp::Ordering::Greater => pos = self.head.load(Ordering::Relaxed),
            }
        }
    }

    /// True when [`pop`](Self::pop) would return an item now.
    pub fn has_ready(&self) -> bool {
        let pos = self.head.load(Ordering::SeqCst);
        self.slot(pos).seq.load(Ordering::SeqCst) == pos + 1
    }

    /// Items pushed and not yet popped, including pushes and pops under way (approximate while
    /// other threads use the queue).
    pub fn len(&self) -> usize {
        let tail = self.tail.load(Ordering::SeqCst);
        let head = self.head.load(Ordering::SeqCst);
        tail.saturating_sub(head) as usize
    }

    /// True when no item is pushed and not yet popped (approximate, as [`len`](Self::len)).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// True when every slot is taken (approximate, as [`len`](Self::len)).
    pub fn is_full(&self) -> bool {
        self.len() >= self.capacity()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn fifo_order_full_and_wraparound() {
        let q = HandoffQueue::new(3);
        assert!(q.is_empty() && !q.has_ready() && q.pop().is_none());
        for lap in 0..5u32 {
            for i in 0..3 {
                q.push(lap * 10 + i).unwrap();
            }
            assert!(q.is_full());
            assert_eq!(q.push(99), Err(99));
            assert_eq!(q.len(), 3);
            for i in 0..3 {
                assert!(q.has_ready());
                assert_eq!(q.pop(), Some(lap * 10 + i));
            }
            assert!(q.is_empty() && q.pop().is_none());
        }
    }

    #[test]
    fn a_claimed_but_unpublished_slot_is_not_waited_for() {
        // What a producer interrupted between claiming and publishing looks like.
        let q = HandoffQueue::new(4);
        q.push(1u32).unwrap();
        q.tail.fetch_add(1, Ordering::SeqCst);
        assert_eq!(q.pop(), Some(1));
        assert_eq!(q.len(), 1, "the claimed slot counts");
        assert!(!q.has_ready());
        assert_eq!(q.pop(), None, "pop must return, not spin");
        // The producer resumes and publishes.
        let slot = q.slot(1);
        *lock(&slot.value) = Some(2);
        slot.seq.store(2, Ordering::SeqCst);
        assert!(q.has_ready());
        assert_eq!(q.pop(), Some(2));
    }

    #[test]
    fn a_slot_being_read_is_not_waited_for() {
        let q = HandoffQueue::new(2);
        q.push(1u32).unwrap();
        q.push(2).unwrap();
        // A pop interrupted after claiming position 0 (head moved, slot not released yet).
        q.head.fetch_add(1, Ordering::SeqCst);
        assert_eq!(q.push(3), Err(3), "push must return, not spin");
    }

    #[test]
    fn many_producers_one_consumer_lose_nothing() {
        let q = Arc::new(HandoffQueue::new(64));
        let producers: Vec<_> = (0..4u64)
            .map(|p| {
                let q = q.clone();
                std::thread::spawn(move || {
                    for i in 0..10_000u64 {
                        let mut v = p * 1_000_000 + i;
                        while let Err(back) = q.push(v) {
                            v = back;
                            std::thread::yield_now();
                        }
                    }
                })
            })
            .collect();
        let mut next = [0u64; 4];
        let mut got = 0;
        while got < 40_000 {
            match q.pop() {
                Some(v) => {
                    let (p, i) = ((v / 1_000_000) as usize, v % 1_000_000);
                    assert_eq!(i, next[p], "per-producer order");
                    next[p] += 1;
                    got += 1;
                }
                None => std::thread::yield_now(),
            }
        }
        for t in producers {
            t.join().unwrap();
        }
        assert_eq!(q.len(), 0);
    }
}
