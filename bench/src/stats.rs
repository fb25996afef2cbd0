//! Nanosecond latency histograms and the percentile summary every `cadence bench` mode reports:
//! count, min, avg, p50, p99, p99.9, p99.99, max.
//!
//! Histograms span 1 ns .. 10 s with 3 significant digits (0.1 % resolution) and never resize,
//! so a measurement thread records into one without allocating; larger values are clamped.

use hdrhistogram::Histogram;
use serde::{Deserialize, Serialize};

use crate::error::BenchError;

/// Highest value a histogram tracks (10 s in ns); larger values are recorded as this.
pub const HIGHEST_NS: u64 = 10_000_000_000;

/// A fixed-bound ns histogram (1 ns .. 10 s, 3 digits) that never resizes.
pub fn new_hist() -> Result<Histogram<u64>, BenchError> {
    let mut h =
        Histogram::new_with_bounds(1, HIGHEST_NS, 3).map_err(|e| BenchError::Histogram(format!("{e:?}")))?;
    h.auto(false);
    Ok(h)
}

/// Adds `from` into `into` (same bounds: both made by [`new_hist`]).
pub fn merge(into: &mut Histogram<u64>, from: &Histogram<u64>) -> Result<(), BenchError> {
    into.add(from)
        .map_err(|e| BenchError::Histogram(format!("{e:?}")))
}

/// The reported figures of one histogram, in nanoseconds. Percentiles and max are the high end
/// of their 0.1 % bucket (HdrHistogram's convention: 76 µs reads 76.00, not 75.97), min the low
/// end.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Percentiles {
    pub count: u64,
    pub min_ns: u64,
    pub avg_ns: f64,
    pub p50_ns: u64,
    pub p99_ns: u64,
    pub p99_9_ns: u64,
    pub p99_99_ns: u64,
    pub max_ns: u64,
}

/// Column names of [`Percentiles::columns`], in order.
pub const COLUMNS: [&str; 7] = ["min", "avg", "p50", "p99", "p99.9", "p99.99", "max"];

impl Percentiles {
    /// The figures of `h` (all zero when it is empty).
    pub fn of(h: &Histogram<u64>) -> Percentiles {
        if h.is_empty() {
            return Percentiles::default();
        }
        let q = |x: f64| h.value_at_quantile(x);
        Percentiles {
            count: h.len(),
            min_ns: h.min(),
            avg_ns: h.mean(),
            p50_ns: q(0.5),
            p99_ns: q(0.99),
            p99_9_ns: q(0.999),
            p99_99_ns: q(0.9999),
            max_ns: h.max(),
        }
    }

    /// min, avg, p50, p99, p99.9, p99.99, max (ns), as named by [`COLUMNS`].
    pub fn columns(&self) -> [f64; 7] {
        [
            self.min_ns as f64,
            self.avg_ns,
            self.p50_ns as f64,
            self.p99_ns as f64,
            self.p99_9_ns as f64,
            self.p99_99_ns as f64,
            self.max_ns as f64,
        ]
    }

    /// True when min ≤ p50 ≤ p99 ≤ p99.9 ≤ p99.99 ≤ max and min ≤ avg ≤ max.
    pub fn ordered(&self) -> bool {
        let c = [
            self.min_ns,
            self.p50_ns,
            self.p99_ns,
            self.p99_9_ns,
            self.p99_99_ns,
            self.max_ns,
        ];
        c.windows(2).all(|w| w[0] <= w[1])
            && self.min_ns as f64 <= self.avg_ns
            && self.avg_ns <= self.max_ns as f64
    }
}

/// Microseconds with two decimals (the unit of the text tables).
pub fn us(ns: f64) -> String {
    format!("{:.2}", ns / 1e3)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_of_a_known_histogram() {
        let mut h = new_hist().unwrap();
        for v in 1..=10_000u64 {
            h.record(v * 100).unwrap();
        }
        let p = Percentiles::of(&h);
        assert_eq!(p.count, 10_000);
        assert_eq!(p.min_ns, 100);
        // 0.1 % resolution.
        assert!((p.p50_ns as f64 - 500_000.0).abs() <= 500.0, "{p:?}");
        assert!((p.p99_ns as f64 - 990_000.0).abs() <= 1000.0, "{p:?}");
        assert!(p.max_ns >= 1_000_000 && p.max_ns <= 1_001_000, "{p:?}");
        assert!(p.ordered());
        assert_eq!(Percentiles::of(&new_hist().unwrap()), Percentiles::default());
    }

    #[test]
    fn values_past_the_bound_are_clamped_not_lost() {
        let mut h = new_hist().unwrap();
        h.saturating_record(HIGHEST_NS * 5);
        assert_eq!(h.len(), 1);
        assert!(h.max() >= HIGHEST_NS);
    }
}
