//! Step lateness histogram (µs of MCU time): 1 µs buckets up to [`BUCKETS`]` - 1` µs, one
//! bucket for everything later, and the exact maximum. Fixed size, no allocation.

use firmware::core::Lateness;

/// Buckets of 1 µs; the last one holds every lateness ≥ `BUCKETS - 1` µs.
pub const BUCKETS: usize = 1024;

/// The histogram.
#[derive(Debug)]
pub struct LatenessHistogram {
    buckets: [u32; BUCKETS],
    count: u32,
    max: u32,
}

impl LatenessHistogram {
    /// Empty.
    pub const fn new() -> Self {
        LatenessHistogram {
            buckets: [0; BUCKETS],
            count: 0,
            max: 0,
        }
    }

    /// Records one step `us` µs late.
    pub fn record(&mut self, us: u32) {
        let i = (us as usize).min(BUCKETS - 1);
        self.buckets[i] = self.buckets[i].saturating_add(1);
        self.count = self.count.saturating_add(1);
        self.max = self.max.max(us);
    }

    /// The value below which `per_mille`‰ of the steps fall (the maximum if that is in the
    /// overflow bucket).
    fn quantile(&self, per_mille: u64) -> u32 {
        let want = (self.count as u64 * per_mille).div_ceil(1000).max(1);
        let mut seen = 0u64;
        for (us, &n) in self.buckets.iter().enumerate() {
            seen += n as u64;
            if seen >= want {
                return if us == BUCKETS - 1 { self.max } else { us as u32 };
            }
        }
        self.max
    }

    /// Percentiles for `cadence_lateness`.
    pub fn summary(&self) -> Lateness {
        if self.count == 0 {
            return Lateness::default();
        }
        Lateness {
            count: self.count,
            p50: self.quantile(500),
            p99: self.quantile(990),
            p999: self.quantile(999),
            max: self.max,
        }
    }
}
