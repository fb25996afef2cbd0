//! Fixed-bound histograms for latencies and lead margins (hdrhistogram 7).
//!
//! One [`LatencyHist`] per thread, recorded with `saturating_record` on fixed bounds (1 ..
//! 10^10 units, 3 significant digits: 0.1 % resolution), so recording never allocates or
//! resizes; values outside the bounds are clamped (and a negative value, e.g. a late step's
//! margin, is counted in `negative` and recorded as 0). Histograms are merged off the RT thread.
//! A value's unit is set at construction as nanoseconds per unit (1.0 for ns; 1e9/clock_freq
//! for MCU ticks) and used only for formatting.
//!
//! [`Summary`] holds the quantiles Cadence reports: latencies as p50/p99/p99.9/max, margins as
//! min/p0.1/p1/p50 (for margins the low tail is what matters). [`IntervalLog`] writes the
//! HdrHistogram interval-log format (V2 + deflate) that standard HdrHistogram plotters read.

use std::fmt::Write as _;
use std::io;
use std::time::Duration;

use hdrhistogram::serialization::interval_log::{IntervalLogWriterBuilder, Tag};
use hdrhistogram::serialization::V2DeflateSerializer;
use hdrhistogram::Histogram;

/// Lowest discernible value.
pub const LOW: u64 = 1;
/// Highest trackable value (10 s in ns).
pub const HIGH: u64 = 10_000_000_000;
/// Significant decimal digits.
pub const SIGFIG: u8 = 3;

/// Errors of histogram construction, merge and log writing.
#[derive(Debug, thiserror::Error)]
pub enum HistError {
    /// Bounds hdrhistogram cannot represent (low < 1, high < 2 * low, sigfig > 5).
    #[error("histogram bounds {low}..{high} with {sigfig} digits: {reason}")]
    Bounds {
        low: u64,
        high: u64,
        sigfig: u8,
        reason: String,
    },
    /// Merging histograms of different bounds.
    #[error("merging histograms: {0}")]
    Merge(String),
    /// Writing an interval log.
    #[error("writing histogram log: {0}")]
    Io(#[from] io::Error),
    /// Serializing a histogram into the log.
    #[error("serializing histogram '{tag}': {reason}")]
    Serialize { tag: String, reason: String },
}

/// A fixed-bound histogram that never allocates while recording.
#[derive(Debug, Clone)]
pub struct LatencyHist {
    h: Histogram<u64>,
    ns_per_unit: f64,
    negative: u64,
}

impl Default for LatencyHist {
    fn default() -> Self {
        LatencyHist::new()
    }
}

impl LatencyHist {
    /// Nanoseconds, 1 ns .. 10 s, 3 digits.
    pub fn new() -> LatencyHist {
        // Constant, valid bounds: construction cannot fail.
        LatencyHist::with_bounds(LOW, HIGH, SIGFIG, 1.0).unwrap_or_else(|_| unreachable_bounds())
    }

    /// Custom bounds in a unit of `ns_per_unit` nanoseconds (for formatting only).
    pub fn with_bounds(low: u64, high: u64, sigfig: u8, ns_per_unit: f64) -> Result<LatencyHist, HistError> {
        let mut h = Histogram::new_with_bounds(low, high, sigfig).map_err(|e| HistError::Bounds {
            low,
            high,
            sigfig,
            reason: format!("{e:?}"),
        })?;
        h.auto(false);
        let ns_per_unit = if ns_per_unit.is_finite() && ns_per_unit > 0.0 {
            ns_per_unit
        } else {
            1.0
        };
        Ok(LatencyHist {
            h,
            ns_per_unit,
            negative: 0,
        })
    }

    /// Records one value, clamped to the bounds. Never allocates.
    #[inline]
    pub fn record(&mut self, value: u64) {
        self.h.saturating_record(value);
    }

    /// Records a signed value (a margin); negatives are counted and recorded as 0.
    #[inline]
    pub fn record_signed(&mut self, value: i64) {
        if value < 0 {
            self.negative += 1;
            self.h.saturating_record(0);
        } else {
            self.h.saturating_record(value as u64);
        }
    }

    /// Records a duration in nanoseconds (for ns histograms).
    #[inline]
    pub fn record_duration(&mut self, d: Duration) {
        self.record(u64::try_from(d.as_nanos()).unwrap_or(u64::MAX));
    }

    /// Adds `other`'s counts (same bounds required).
    pub fn merge(&mut self, other: &LatencyHist) -> Result<(), HistError> {
        self.h
            .add(&other.h)
            .map_err(|e| HistError::Merge(format!("{e:?}")))?;
        self.negative += other.negative;
        Ok(())
    }

    /// Forgets all values (keeps the bounds and the allocation).
    pub fn reset(&mut self) {
        self.h.reset();
        self.negative = 0;
    }

    /// Number of recorded values.
    pub fn count(&self) -> u64 {
        self.h.len()
    }

    /// Nanoseconds per recorded unit.
    pub fn ns_per_unit(&self) -> f64 {
        self.ns_per_unit
    }

    /// The underlying histogram (for serialization or custom queries).
    pub fn histogram(&self) -> &Histogram<u64> {
        &self.h
    }

    /// The quantiles Cadence reports, in recorded units.
    pub fn summary(&self) -> Summary {
        let q = |x: f64| {
            if self.h.is_empty() {
                0
            } else {
                self.h.value_at_quantile(x)
            }
        };
        Summary {
            count: self.h.len(),
            negative: self.negative,
            min: if self.h.is_empty() { 0 } else { self.h.min() },
            p0_1: q(0.001),
            p1: q(0.01),
            p50: q(0.5),
            p99: q(0.99),
            p999: q(0.999),
            max: self.h.max(),
            mean: self.h.mean(),
            ns_per_unit: self.ns_per_unit,
        }
    }
}

fn unreachable_bounds() -> LatencyHist {
    // Only reachable if hdrhistogram rejected its own documented constant bounds.
    panic!("hdrhistogram rejected the constant bounds {LOW}..{HIGH}/{SIGFIG}")
}

/// Quantiles of one histogram, in its recorded unit.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Summary {
    pub count: u64,
    /// Values below 0 (recorded as 0); for margins, each one is a lead violation.
    pub negative: u64,
    pub min: u64,
    pub p0_1: u64,
    pub p1: u64,
    pub p50: u64,
    pub p99: u64,
    pub p999: u64,
    pub max: u64,
    pub mean: f64,
    /// Nanoseconds per unit, for formatting.
    pub ns_per_unit: f64,
}

impl Summary {
    /// A value in this summary's unit formatted as ns/µs/ms/s with 3-4 significant digits.
    pub fn fmt_value(&self, v: u64) -> String {
        fmt_ns(v as f64 * self.ns_per_unit)
    }

    /// `"n=1000 p50 1.20 µs p99 3.40 µs p99.9 8.00 µs max 4.10 ms"`.
    pub fn format_latency(&self) -> String {
        format!(
            "n={} p50 {} p99 {} p99.9 {} max {}",
            self.count,
            self.fmt_value(self.p50),
            self.fmt_value(self.p99),
            self.fmt_value(self.p999),
            self.fmt_value(self.max)
        )
    }

    /// `"n=1000 min 120 ms p0.1 130 ms p1 150 ms p50 300 ms"` plus `", 2 negative"` if any.
    pub fn format_margin(&self) -> String {
        let mut s = format!(
            "n={} min {} p0.1 {} p1 {} p50 {}",
            self.count,
            self.fmt_value(self.min),
            self.fmt_value(self.p0_1),
            self.fmt_value(self.p1),
            self.fmt_value(self.p50)
        );
        if self.negative > 0 {
            let _ = write!(s, ", {} negative", self.negative);
        }
        s
    }
}

/// Formats nanoseconds with a unit that keeps 3-4 significant digits.
pub fn fmt_ns(ns: f64) -> String {
    let a = ns.abs();
    if a < 1e3 {
        format!("{ns:.0} ns")
    } else if a < 1e6 {
        format!("{:.2} µs", ns / 1e3)
    } else if a < 1e9 {
        format!("{:.2} ms", ns / 1e6)
    } else {
        format!("{:.3} s", ns / 1e9)
    }
}

/// Writes HdrHistogram interval logs (V2, deflate-compressed), one tagged histogram per line.
pub struct IntervalLog<W: io::Write> {
    out: W,
    serializer: V2DeflateSerializer,
}

impl<W: io::Write> std::fmt::Debug for IntervalLog<W> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("IntervalLog")
    }
}

impl<W: io::Write> IntervalLog<W> {
    /// Starts a log on `out` with a comment header and `BaseTime` = now.
    pub fn begin(mut out: W, comment: &str) -> Result<IntervalLog<W>, HistError> {
        let mut serializer = V2DeflateSerializer::new();
        IntervalLogWriterBuilder::new()
            .add_comment(comment)
            .with_base_time(std::time::SystemTime::now())
            .begin_log_with(&mut out, &mut serializer)?;
        Ok(IntervalLog { out, serializer })
    }

    /// Appends one interval: `hist` recorded from `start` (since BaseTime) for `duration`,
    /// tagged `tag` (no spaces, commas or newlines; others are replaced by '_').
    pub fn write(
        &mut self,
        tag: &str,
        hist: &LatencyHist,
        start: Duration,
        duration: Duration,
    ) -> Result<(), HistError> {
        let clean: String = tag
            .chars()
            .map(|c| {
                if c == ',' || c == ' ' || c == '\n' || c == '\r' {
                    '_'
                } else {
                    c
                }
            })
            .collect();
        let builder = IntervalLogWriterBuilder::new();
        let mut w = builder.begin_log_with(&mut self.out, &mut self.serializer)?;
        w.write_histogram(hist.histogram(), start, duration, Tag::new(&clean))
            .map_err(|e| HistError::Serialize {
                tag: clean.clone(),
                reason: e.to_string(),
            })
    }

    /// Flushes and returns the writer.
    pub fn finish(mut self) -> Result<W, HistError> {
        self.out.flush()?;
        Ok(self.out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use hdrhistogram::serialization::interval_log::{IntervalLogIterator, LogEntry};
    use hdrhistogram::serialization::Deserializer;

    #[test]
    fn summary_quantiles_and_merge() {
        let mut a = LatencyHist::new();
        let mut b = LatencyHist::new();
        for v in 1..=1000u64 {
            a.record(v * 1000);
        }
        b.record(HIGH * 10); // clamped, not lost
        a.merge(&b).unwrap();
        let s = a.summary();
        assert_eq!(s.count, 1001);
        assert_eq!(s.min, 1000);
        // 0.1 % resolution; the 501st of 1001 values is 501_000.
        assert!((s.p50 as f64 - 501_000.0).abs() <= 1000.0, "{s:?}");
        assert!(s.max >= HIGH && s.max <= HIGH + HIGH / 1000, "{s:?}");
        assert!(
            s.format_latency().starts_with("n=1001 p50 50"),
            "{}",
            s.format_latency()
        );
    }

    #[test]
    fn negative_margins_are_counted() {
        let mut m = LatencyHist::with_bounds(1, 1 << 40, 3, 20.0).unwrap();
        m.record_signed(-5);
        m.record_signed(5_000_000);
        let s = m.summary();
        assert_eq!((s.count, s.negative, s.min), (2, 1, 0));
        assert!(s.format_margin().ends_with(", 1 negative"));
        assert_eq!(s.fmt_value(5_000_000), "100.00 ms");
    }

    #[test]
    fn empty_summary_is_zero() {
        let s = LatencyHist::new().summary();
        assert_eq!((s.count, s.min, s.p50, s.max), (0, 0, 0, 0));
    }

    #[test]
    fn merge_of_different_bounds_is_an_error_or_exact() {
        let mut a = LatencyHist::with_bounds(1, 1000, 2, 1.0).unwrap();
        let mut b = LatencyHist::new();
        b.record(5_000_000);
        assert!(a.merge(&b).is_err());
    }

    #[test]
    fn interval_log_round_trips() {
        let mut h = LatencyHist::new();
        for v in [100u64, 200, 300, 40_000] {
            h.record(v);
        }
        let mut log = IntervalLog::begin(Vec::new(), "cadence test").unwrap();
        log.write("handoff ipc", &h, Duration::from_secs(1), Duration::from_secs(2))
            .unwrap();
        log.write("lead", &h, Duration::from_secs(3), Duration::from_secs(2))
            .unwrap();
        let bytes = log.finish().unwrap();
        let text = String::from_utf8(bytes.clone()).unwrap();
        assert!(text.starts_with("#cadence test\n"), "{text}");
        let mut de = Deserializer::new();
        let mut tags = Vec::new();
        for entry in IntervalLogIterator::new(&bytes) {
            if let Ok(LogEntry::Interval(ih)) = entry {
                let raw = base64_decode(ih.encoded_histogram());
                let back: Histogram<u64> = de.deserialize(&mut raw.as_slice()).unwrap();
                assert_eq!(back.len(), 4);
                assert_eq!(back.max(), h.histogram().max());
                tags.push(ih.tag().map(|t| t.as_str().to_string()));
            }
        }
        assert_eq!(
            tags,
            vec![Some("handoff_ipc".to_string()), Some("lead".to_string())]
        );
    }

    /// Minimal standard base64 decoder for the test (the crate's own dependency is private).
    fn base64_decode(s: &str) -> Vec<u8> {
        let val = |c: u8| match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' => 62,
            _ => 63,
        };
        let mut out = Vec::new();
        let bytes: Vec<u8> = s.bytes().filter(|&c| c != b'=').collect();
        for chunk in bytes.chunks(4) {
            let mut acc = 0u32;
            for (i, &c) in chunk.iter().enumerate() {
                acc |= (val(c) as u32) << (18 - 6 * i);
            }
            for i in 0..chunk.len().saturating_sub(1) {
                out.push((acc >> (16 - 8 * i)) as u8);
            }
        }
        out
    }
}
