//! A transport wrapper that injects faults: each `write_all` call (and, if enabled, each chunk
//! returned by `read`) is dropped, corrupted (one bit flipped) or duplicated with given
//! probabilities, decided by a seeded xorshift generator so every run is reproducible.
//!
//! The link writes whole blocks per call, so a "dropped write" is a lost block (or a lost burst
//! of blocks) and a corrupted one fails its CRC: exactly the faults the reliable transport
//! must survive.

use std::io;
use std::time::Duration;

use super::{Transport, Wake};

/// Marsaglia's xorshift64 generator (shifts 13, 7, 17): tiny, fast, reproducible; not for
/// anything but test randomness.
#[derive(Debug, Clone)]
pub struct XorShift64(u64);

impl XorShift64 {
    /// A generator from `seed` (0 is replaced, since the all-zero state is a fixed point).
    pub fn new(seed: u64) -> XorShift64 {
        XorShift64(if seed == 0 { 0x9E37_79B9_7F4A_7C15 } else { seed })
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        let mut x = self.0;
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        self.0 = x;
        x
    }

    /// A uniform value in `[0, 1)` (53 random bits).
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// A uniform index in `0..n` (`0` when `n == 0`).
    pub fn below(&mut self, n: usize) -> usize {
        if n == 0 {
            0
        } else {
            (self.next_u64() % n as u64) as usize
        }
    }
}

/// Fault probabilities (each in 0..=1) and the seed.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FaultConfig {
    /// Seed of the generator.
    pub seed: u64,
    /// Probability that a write (or read chunk) is lost entirely.
    pub drop_rate: f64,
    /// Probability that one bit of a write (or read chunk) is flipped.
    pub corrupt_rate: f64,
    /// Probability that a write is sent twice.
    pub duplicate_rate: f64,
    /// Also drop/corrupt chunks coming back from `read`.
    pub on_read: bool,
}

/// What a [`FaultyTransport`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct FaultStats {
    /// Writes or read chunks dropped.
    pub dropped: u64,
    /// Writes or read chunks corrupted.
    pub corrupted: u64,
    /// Writes duplicated.
    pub duplicated: u64,
}

/// Wraps a transport and injects faults.
#[derive(Debug)]
pub struct FaultyTransport<T> {
    inner: T,
    cfg: FaultConfig,
    rng: XorShift64,
    scratch: Vec<u8>,
    stats: FaultStats,
}

impl<T: Transport> FaultyTransport<T> {
    /// Wraps `inner`.
    pub fn new(inner: T, cfg: FaultConfig) -> FaultyTransport<T> {
        FaultyTransport {
            inner,
            rng: XorShift64::new(cfg.seed),
            cfg,
            scratch: Vec::with_capacity(1024),
            stats: FaultStats::default(),
        }
    }

    /// Faults injected so far.
    pub fn stats(&self) -> FaultStats {
        self.stats
    }

    /// The wrapped transport.
    pub fn into_inner(self) -> T {
        self.inner
    }

    fn hit(&mut self, rate: f64) -> bool {
        rate > 0.0 && self.rng.next_f64() < rate
    }

    /// Applies the read-side faults to the `n` bytes just read into `buf`.
    fn filter_read(&mut self, buf: &mut [u8], n: usize) -> io::Result<usize> {
        if n == 0 || !self.cfg.on_read {
            return Ok(n);
        }
        if self.hit(self.cfg.drop_rate) {
            self.stats.dropped += 1;
            return Ok(0);
        }
        if self.hit(self.cfg.corrupt_rate) {
            self.stats.corrupted += 1;
            if let Some(chunk) = buf.get_mut(..n) {
                self.flip_bit(chunk);
            }
        }
        Ok(n)
    }

    fn flip_bit(&mut self, data: &mut [u8]) {
        let i = self.rng.below(data.len());
        let bit = self.rng.below(8);
        if let Some(b) = data.get_mut(i) {
            *b ^= 1 << bit;
        }
    }
}

impl<T: Transport> Transport for FaultyTransport<T> {
    fn read(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        let n = self.inner.read(buf, timeout)?;
        self.filter_read(buf, n)
    }

    fn read_wake(&mut self, buf: &mut [u8], timeout: Duration, wake: &Wake) -> io::Result<usize> {
        let n = self.inner.read_wake(buf, timeout, wake)?;
        self.filter_read(buf, n)
    }

    fn supports_wake(&self) -> bool {
        self.inner.supports_wake()
    }

    fn write_all(&mut self, data: &[u8]) -> io::Result<()> {
        if self.hit(self.cfg.drop_rate) {
            self.stats.dropped += 1;
            return Ok(());
        }
        let mut scratch = std::mem::take(&mut self.scratch);
        scratch.clear();
        scratch.extend_from_slice(data);
        if self.hit(self.cfg.corrupt_rate) && !scratch.is_empty() {
            self.stats.corrupted += 1;
            self.flip_bit(&mut scratch);
        }
        let twice = self.hit(self.cfg.duplicate_rate);
        let mut res = self.inner.write_all(&scratch);
        if twice && res.is_ok() {
            self.stats.duplicated += 1;
            res = self.inner.write_all(&scratch);
        }
        self.scratch = scratch;
        res
    }

    fn describe(&self) -> String {
        format!("faulty {}", self.inner.describe())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transport::{conformance, MemoryPair};

    #[test]
    fn conformance_without_faults() {
        let (a, b) = MemoryPair::new();
        let a = FaultyTransport::new(a, FaultConfig::default());
        conformance::run(Box::new(a), Box::new(b));
    }

    #[test]
    fn injects_at_about_the_given_rates() {
        let (a, mut b) = MemoryPair::new();
        let cfg = FaultConfig {
            seed: 7,
            drop_rate: 0.1,
            corrupt_rate: 0.1,
            duplicate_rate: 0.1,
            on_read: false,
        };
        let mut f = FaultyTransport::new(a, cfg);
        for _ in 0..1000 {
            f.write_all(&[0u8; 4]).unwrap();
        }
        let s = f.stats();
        for v in [s.dropped, s.corrupted, s.duplicated] {
            assert!((50..170).contains(&v), "{s:?}");
        }
        let mut total = 0;
        let mut buf = [0u8; 8192];
        loop {
            let n = b.read(&mut buf, Duration::ZERO).unwrap();
            if n == 0 {
                break;
            }
            total += n;
        }
        assert_eq!(total as u64, 4 * (1000 - s.dropped + s.duplicated));
    }

    #[test]
    fn xorshift_is_reproducible_and_uniformish() {
        let mut a = XorShift64::new(1);
        let mut b = XorShift64::new(1);
        assert_eq!(a.next_u64(), b.next_u64());
        let mean = (0..10_000).map(|_| a.next_f64()).sum::<f64>() / 10_000.0;
        assert!((0.45..0.55).contains(&mean));
        assert_eq!(XorShift64::new(0).below(0), 0);
    }
}
