//! A sequence lock over atomic words: one writer publishes a small `Copy` value, any number of
//! readers take consistent snapshots without locks and without `unsafe`.
//!
//! Protocol: the writer makes the sequence odd, stores the words, then makes it even again;
//! a reader retries while the sequence is odd or changed across its reads. Every word is an
//! atomic, so a torn read is merely detected and retried, never undefined behaviour.

use std::sync::atomic::{fence, AtomicU64, Ordering};

/// A sequence lock over `N` 64-bit words.
#[derive(Debug)]
pub struct SeqLock<const N: usize> {
    seq: AtomicU64,
    words: [AtomicU64; N],
}

impl<const N: usize> SeqLock<N> {
    /// A lock holding `init`.
    pub fn new(init: [u64; N]) -> SeqLock<N> {
        SeqLock {
            seq: AtomicU64::new(0),
            words: init.map(AtomicU64::new),
        }
    }

    /// Publishes `value`. Concurrent writers are serialised by the odd/even handshake.
    pub fn store(&self, value: [u64; N]) {
        let mut s = self.seq.load(Ordering::Relaxed);
        loop {
            if s & 1 == 1 {
                std::hint::spin_loop();
                s = self.seq.load(Ordering::Relaxed);
                continue;
            }
            // Acquire pairs with the Release store that ended the previous write.
            match self
                .seq
                .compare_exchange_weak(s, s + 1, Ordering::Acquire, Ordering::Relaxed)
            {
                Ok(_) => break,
                Err(now) => s = now,
            }
        }
        // Keeps the word stores below from moving before the odd sequence store; pairs with the
        // reader's Acquire fence.
        fence(Ordering::Release);
        for (w, v) in self.words.iter().zip(value) {
            w.store(v, Ordering::Relaxed);
        }
        // Release pairs with the reader's Acquire load of `seq`: a reader that sees s + 2 sees
        // every word stored above.
        self.seq.store(s + 2, Ordering::Release);
    }

    /// A consistent snapshot.
    pub fn load(&self) -> [u64; N] {
        let mut spins = 0u32;
        loop {
            // Acquire pairs with the writer's final Release store.
            let s1 = self.seq.load(Ordering::Acquire);
            if s1 & 1 == 0 {
                let value = std::array::from_fn(|i| self.words[i].load(Ordering::Relaxed));
                // Keeps the word loads above before the second sequence load; pairs with the
                // writer's Release fence.
                fence(Ordering::Acquire);
                if self.seq.load(Ordering::Relaxed) == s1 {
                    return value;
                }
            }
            spins += 1;
            if spins.is_multiple_of(64) {
                // The writer was preempted mid-write: let it run.
                std::thread::yield_now();
            } else {
                std::hint::spin_loop();
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn readers_never_see_torn_values() {
        let lock = Arc::new(SeqLock::<4>::new([0; 4]));
        let writer = {
            let lock = lock.clone();
            std::thread::spawn(move || {
                for k in 1..=20_000u64 {
                    lock.store([k, 2 * k, 3 * k, 4 * k]);
                }
            })
        };
        let readers: Vec<_> = (0..2)
            .map(|_| {
                let lock = lock.clone();
                std::thread::spawn(move || {
                    let mut last = 0;
                    for _ in 0..20_000 {
                        let [a, b, c, d] = lock.load();
                        assert_eq!((b, c, d), (2 * a, 3 * a, 4 * a));
                        assert!(a >= last, "went backwards");
                        last = a;
                    }
                })
            })
            .collect();
        writer.join().unwrap();
        for r in readers {
            r.join().unwrap();
        }
        assert_eq!(lock.load()[0], 20_000);
    }
}
