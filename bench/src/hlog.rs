//! `--hlog FILE`: the HdrHistogram V2 interval log (deflate-compressed histograms, base64, one
//! tagged interval a line) that HdrHistogram's own tools read (HistogramLogProcessor,
//! HistogramLogAnalyzer, hdrhistogram-rs's `IntervalLogIterator`). Values are nanoseconds;
//! each series is a tag (`cpu0`, `cyclictest-cpu0`, `queue-poll` ...).

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use hdrhistogram::serialization::interval_log::{IntervalLogWriterBuilder, Tag};
use hdrhistogram::serialization::V2DeflateSerializer;
use hdrhistogram::Histogram;

use crate::error::BenchError;

/// Column legend line of the Java implementation (its readers skip it).
const LEGEND: &str =
    "\"StartTimestamp\",\"Interval_Length\",\"Interval_Max\",\"Interval_Compressed_Histogram\"";

/// An interval log being written.
pub struct Hlog {
    path: PathBuf,
    out: BufWriter<File>,
    serializer: V2DeflateSerializer,
}

impl std::fmt::Debug for Hlog {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Hlog({})", self.path.display())
    }
}

impl Hlog {
    /// Creates `path` with `comment`, `StartTime`/`BaseTime` = `base` and the legend; interval
    /// start times are then given relative to `base`.
    pub fn create(path: &Path, comment: &str, base: SystemTime) -> Result<Hlog, BenchError> {
        let file = File::create(path).map_err(|e| BenchError::file(path, e))?;
        let mut log = Hlog {
            path: path.to_path_buf(),
            out: BufWriter::new(file),
            serializer: V2DeflateSerializer::new(),
        };
        IntervalLogWriterBuilder::new()
            .add_comment(comment)
            .add_comment("values in nanoseconds")
            .with_start_time(base)
            .with_base_time(base)
            .begin_log_with(&mut log.out, &mut log.serializer)
            .map_err(|e| BenchError::file(path, e))?;
        writeln!(log.out, "{LEGEND}").map_err(|e| BenchError::file(path, e))?;
        Ok(log)
    }

    /// Appends `hist`, recorded from `start` (after the base time) for `length`, as `tag`
    /// (spaces and commas, which the format cannot hold, become '_').
    pub fn write(
        &mut self,
        tag: &str,
        hist: &Histogram<u64>,
        start: Duration,
        length: Duration,
    ) -> Result<(), BenchError> {
        let clean: String = tag
            .chars()
            .map(|c| if c == ',' || c.is_whitespace() { '_' } else { c })
            .collect();
        let path = self.path.clone();
        let mut w = IntervalLogWriterBuilder::new()
            .begin_log_with(&mut self.out, &mut self.serializer)
            .map_err(|e| BenchError::file(&path, e))?;
        w.write_histogram(hist, start, length, Tag::new(&clean))
            .map_err(|e| BenchError::Histogram(format!("{}: writing '{clean}': {e}", path.display())))
    }

    /// Flushes the file.
    pub fn finish(mut self) -> Result<(), BenchError> {
        self.out.flush().map_err(|e| BenchError::file(&self.path, e))
    }
}

/// One interval read back from a log.
#[derive(Debug)]
pub struct LoggedInterval {
    pub tag: Option<String>,
    /// After the log's base time.
    pub start: Duration,
    pub hist: Histogram<u64>,
}

/// Reads an interval log back (for tests and checks).
pub fn read(path: &Path) -> Result<Vec<LoggedInterval>, BenchError> {
    use base64::Engine as _;
    use hdrhistogram::serialization::interval_log::{IntervalLogIterator, LogEntry};
    use hdrhistogram::serialization::Deserializer;
    let bytes = std::fs::read(path).map_err(|e| BenchError::file(path, e))?;
    let mut de = Deserializer::new();
    let mut out = Vec::new();
    for entry in IntervalLogIterator::new(&bytes) {
        let entry = entry.map_err(|e| BenchError::Histogram(format!("{}: {e:?}", path.display())))?;
        if let LogEntry::Interval(ih) = entry {
            let raw = base64::engine::general_purpose::STANDARD
                .decode(ih.encoded_histogram())
                .map_err(|e| BenchError::Histogram(format!("{}: base64: {e}", path.display())))?;
            let h: Histogram<u64> = de
                .deserialize(&mut raw.as_slice())
                .map_err(|e| BenchError::Histogram(format!("{}: {e:?}", path.display())))?;
            out.push(LoggedInterval {
                tag: ih.tag().map(|t| t.as_str().to_string()),
                start: ih.start_timestamp(),
                hist: h,
            });
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stats::new_hist;

    #[test]
    fn intervals_read_back_with_tags() {
        let dir = std::env::temp_dir().join(format!("cadence-hlog-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("t.hlog");
        let mut h = new_hist().unwrap();
        for v in [1_000u64, 2_000, 3_000_000] {
            h.record(v).unwrap();
        }
        let mut log = Hlog::create(&path, "cadence bench test", SystemTime::now()).unwrap();
        log.write("cpu 0", &h, Duration::from_secs(1), Duration::from_secs(1))
            .unwrap();
        log.write(
            "cyclictest,cpu0",
            &h,
            Duration::from_secs(2),
            Duration::from_secs(1),
        )
        .unwrap();
        log.finish().unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.starts_with("#cadence bench test\n"), "{text}");
        assert!(text.contains("#[StartTime: ") && text.contains(LEGEND), "{text}");
        let back = read(&path).unwrap();
        assert_eq!(back.len(), 2);
        assert_eq!(back[0].tag.as_deref(), Some("cpu_0"));
        assert_eq!(back[1].tag.as_deref(), Some("cyclictest_cpu0"));
        assert_eq!(back[1].start, Duration::from_secs(2));
        assert_eq!(back[0].hist.len(), 3);
        assert_eq!(back[0].hist.max(), h.max());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
