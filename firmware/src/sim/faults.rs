//! Fault injection on the simulator's output: dropped bytes and delayed bytes.
//!
//! Every byte the core sends passes through [`TxFaults::push`]: with probability `drop_rate`
//! (a xorshift64* generator seeded by `--fault-seed`, so runs repeat) it is lost; the rest are
//! held for `delay` of wall time and handed out by [`TxFaults::ready`] in order. With neither
//! fault configured bytes pass straight through.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// The output fault stage.
#[derive(Debug)]
pub struct TxFaults {
    drop_rate: f64,
    delay: Duration,
    rng: u64,
    held: VecDeque<(Instant, Vec<u8>)>,
    /// Bytes dropped so far.
    pub dropped: u64,
}

impl TxFaults {
    /// A stage dropping `drop_rate` of the bytes and delaying the rest by `delay`.
    pub fn new(drop_rate: f64, delay: Duration, seed: u64) -> TxFaults {
        TxFaults {
            drop_rate,
            delay,
            rng: seed.max(1),
            held: VecDeque::new(),
            dropped: 0,
        }
    }

    /// True if bytes pass through unchanged.
    pub fn is_transparent(&self) -> bool {
        self.drop_rate == 0.0 && self.delay.is_zero()
    }

    fn next_unit(&mut self) -> f64 {
        let mut x = self.rng;
        x ^= x >> 12;
        x ^= x << 25;
        x ^= x >> 27;
        self.rng = x;
        (x.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Takes bytes sent at `now`.
    pub fn push(&mut self, bytes: &[u8], now: Instant) {
        let mut kept = Vec::with_capacity(bytes.len());
        for &b in bytes {
            if self.drop_rate > 0.0 && self.next_unit() < self.drop_rate {
                self.dropped += 1;
            } else {
                kept.push(b);
            }
        }
        if !kept.is_empty() {
            self.held.push_back((now + self.delay, kept));
        }
    }

    /// Appends to `out` every byte whose hold time has passed at `now`.
    pub fn ready(&mut self, now: Instant, out: &mut Vec<u8>) {
        while let Some((at, _)) = self.held.front() {
            if *at > now {
                break;
            }
            if let Some((_, bytes)) = self.held.pop_front() {
                out.extend_from_slice(&bytes);
            }
        }
    }

    /// When the next held bytes are due.
    pub fn next_release(&self) -> Option<Instant> {
        self.held.front().map(|(at, _)| *at)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn delays_in_order() {
        let mut f = TxFaults::new(0.0, Duration::from_millis(30), 1);
        let t0 = Instant::now();
        f.push(b"ab", t0);
        f.push(b"c", t0 + Duration::from_millis(5));
        let mut out = Vec::new();
        f.ready(t0 + Duration::from_millis(29), &mut out);
        assert!(out.is_empty());
        assert_eq!(f.next_release(), Some(t0 + Duration::from_millis(30)));
        f.ready(t0 + Duration::from_millis(30), &mut out);
        assert_eq!(out, b"ab");
        f.ready(t0 + Duration::from_millis(40), &mut out);
        assert_eq!(out, b"abc");
        assert_eq!(f.next_release(), None);
    }

    #[test]
    fn drops_about_the_rate_repeatably() {
        let run = |seed| {
            let mut f = TxFaults::new(0.01, Duration::ZERO, seed);
            let now = Instant::now();
            f.push(&[0u8; 100_000], now);
            let mut out = Vec::new();
            f.ready(now, &mut out);
            (f.dropped, out.len())
        };
        let (dropped, kept) = run(7);
        assert_eq!(dropped as usize + kept, 100_000);
        assert!((700..1300).contains(&dropped), "{dropped}");
        assert_eq!(run(7), (dropped, kept), "same seed, same drops");
        assert!(TxFaults::new(0.0, Duration::ZERO, 0).is_transparent());
    }
}
