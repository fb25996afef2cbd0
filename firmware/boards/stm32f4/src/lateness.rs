//! Step lateness histogram (µs of MCU time), fixed size, no allocation: 1 µs buckets below
//! [`LINEAR`] µs, above that each power of two split into 32 buckets (values reported at their
//! bucket's lower bound, at most 1/32 = 3% low), plus the exact maximum.

use firmware::core::Lateness;

/// Values below this have a bucket each.
const LINEAR: u32 = 256;
/// Sub-buckets per power of two above [`LINEAR`] (5 bits).
const SUB_BITS: u32 = 5;
/// 256 linear buckets, then 24 powers of two (2^8 ..= 2^31) of 32 buckets.
const BUCKETS: usize = LINEAR as usize + (32 - 8) * (1 << SUB_BITS);

fn bucket(us: u32) -> usize {
    if us < LINEAR {
        return us as usize;
    }
    let e = 31 - us.leading_zeros(); // 8..=31
    let sub = (us >> (e - SUB_BITS)) & ((1 << SUB_BITS) - 1);
    LINEAR as usize + ((e - 8) << SUB_BITS) as usize + sub as usize
}

fn lower_bound(i: usize) -> u32 {
    if i < LINEAR as usize {
        return i as u32;
    }
    let k = i - LINEAR as usize;
    let e = (k >> SUB_BITS) as u32 + 8;
    let sub = (k & ((1 << SUB_BITS) - 1)) as u32;
    ((1 << SUB_BITS) | sub) << (e - SUB_BITS)
}

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
        let i = bucket(us);
        self.buckets[i] = self.buckets[i].saturating_add(1);
        self.count = self.count.saturating_add(1);
        self.max = self.max.max(us);
    }

    /// The value below which `per_mille`‰ of the steps fall.
    fn quantile(&self, per_mille: u64) -> u32 {
        let want = (self.count as u64 * per_mille).div_ceil(1000).max(1);
        let mut seen = 0u64;
        for (i, &n) in self.buckets.iter().enumerate() {
            seen += n as u64;
            if seen >= want {
                return lower_bound(i).min(self.max);
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
