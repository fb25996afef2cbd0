//! Runs Debian's `cyclictest` (package rt-tests) with the settings of a `cadence bench wakeup`
//! run and reads its per-thread histograms back from its `--json` file, so both tools'
//! figures can be set side by side.
//!
//! Same settings means: one thread per CPU pinned in the same order (`-t N -a LIST`), the same
//! SCHED_FIFO priority (`-p P`, 0 for normal scheduling), the same interval with no distance
//! between threads (`-i I -d 0`), `-m` (mlockall), and a histogram (`-h`) with 1 µs buckets up
//! to [`HIST_LIMIT_US`]. cyclictest counts whole microseconds (it truncates), and holds
//! `/dev/cpu_dma_latency` at 0 as `cadence bench wakeup` does. Samples past the histogram's
//! limit are not in its JSON: they are recorded at the thread's exact maximum, which cyclictest
//! does report (an upper bound for them).

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

use hdrhistogram::Histogram;

use crate::error::BenchError;
use crate::stats::new_hist;

/// cyclictest's histogram covers 0 .. this many µs (100 ms).
pub const HIST_LIMIT_US: u64 = 100_000;

const TOOL: &str = "cyclictest";

/// The settings cyclictest runs with.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CyclictestRun {
    pub cpus: Vec<usize>,
    /// SCHED_FIFO priority; `None` runs it with `-p 0` (normal scheduling).
    pub priority: Option<i32>,
    pub interval: Duration,
    /// Whole seconds (`-D`).
    pub seconds: u64,
}

/// One thread's figures as cyclictest reported them.
#[derive(Debug)]
pub struct CyclictestThread {
    /// Latencies in ns (whole µs × 1000).
    pub hist: Histogram<u64>,
    /// Samples beyond [`HIST_LIMIT_US`] (recorded at the thread's maximum).
    pub overflows: u64,
}

/// The path of the `cyclictest` executable on `PATH`, if any.
pub fn find() -> Option<PathBuf> {
    crate::find_on_path(TOOL)
}

impl CyclictestRun {
    /// The command-line arguments (without the executable), writing JSON to `json`.
    pub fn args(&self, json: &Path) -> Vec<String> {
        let cpus: Vec<String> = self.cpus.iter().map(|c| c.to_string()).collect();
        vec![
            "-q".into(),
            "-m".into(),
            "-t".into(),
            self.cpus.len().to_string(),
            "-a".into(),
            cpus.join(","),
            "-p".into(),
            self.priority.unwrap_or(0).to_string(),
            "-i".into(),
            self.interval.as_micros().to_string(),
            "-d".into(),
            "0".into(),
            "-D".into(),
            self.seconds.max(1).to_string(),
            "-h".into(),
            HIST_LIMIT_US.to_string(),
            format!("--json={}", json.display()),
        ]
    }

    /// Runs cyclictest (`exe`) and returns its threads in CPU order, and its version.
    pub fn run(&self, exe: &Path) -> Result<(Vec<CyclictestThread>, String), BenchError> {
        let json = std::env::temp_dir().join(format!("cadence-bench-cyclictest-{}.json", std::process::id()));
        let out = Command::new(exe)
            .args(self.args(&json))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .output()
            .map_err(|e| BenchError::Tool {
                tool: TOOL,
                reason: format!("{}: {e}", exe.display()),
            })?;
        let text = std::fs::read_to_string(&json);
        let _ = std::fs::remove_file(&json);
        if !out.status.success() {
            return Err(BenchError::Tool {
                tool: TOOL,
                reason: format!("{}: {}", out.status, String::from_utf8_lossy(&out.stderr).trim()),
            });
        }
        let text = text.map_err(|e| BenchError::file(&json, e))?;
        parse_json(&text)
    }
}

fn bad(reason: impl Into<String>) -> BenchError {
    BenchError::Tool {
        tool: TOOL,
        reason: format!("its --json output: {}", reason.into()),
    }
}

/// Reads cyclictest's `--json` output: per-thread histograms (in thread order) and the version.
pub fn parse_json(text: &str) -> Result<(Vec<CyclictestThread>, String), BenchError> {
    let v: serde_json::Value = serde_json::from_str(text).map_err(|e| bad(e.to_string()))?;
    let version = v
        .get("rt_test_version:")
        .or_else(|| v.get("rt_test_version"))
        .and_then(|x| x.as_str())
        .unwrap_or("(version unknown)")
        .to_string();
    let threads = v
        .get("thread")
        .and_then(|t| t.as_object())
        .ok_or_else(|| bad("no \"thread\" object"))?;
    let mut numbered: Vec<(usize, &serde_json::Value)> = Vec::new();
    for (k, t) in threads {
        let n = k.parse().map_err(|_| bad(format!("thread key {k:?}")))?;
        numbered.push((n, t));
    }
    numbered.sort_by_key(|(n, _)| *n);
    let mut out = Vec::new();
    for (n, t) in numbered {
        let field = |name: &str| {
            t.get(name)
                .and_then(|x| x.as_u64())
                .ok_or_else(|| bad(format!("thread {n}: no {name}")))
        };
        let (cycles, max_us) = (field("cycles")?, field("max")?);
        let buckets = t
            .get("histogram")
            .and_then(|h| h.as_object())
            .ok_or_else(|| bad(format!("thread {n}: no histogram (was -h given?)")))?;
        let mut hist = new_hist()?;
        let mut counted = 0u64;
        for (us, count) in buckets {
            let us: u64 = us
                .parse()
                .map_err(|_| bad(format!("thread {n}: bucket {us:?}")))?;
            let count = count
                .as_u64()
                .ok_or_else(|| bad(format!("thread {n}: bucket {us} count")))?;
            hist.saturating_record_n(us * 1000, count);
            counted += count;
        }
        let overflows = cycles.saturating_sub(counted);
        if overflows > 0 {
            hist.saturating_record_n(max_us * 1000, overflows);
        }
        out.push(CyclictestThread { hist, overflows });
    }
    if out.is_empty() {
        return Err(bad("no threads"));
    }
    Ok((out, version))
}

#[cfg(test)]
mod tests {
    use super::*;

    const SAMPLE: &str = r#"{
  "file_version": 1,
  "rt_test_version:": "2.40",
  "num_threads": 2,
  "thread": {
    "1": { "histogram": { "5": 3, "7": 1 }, "cycles": 4, "min": 5, "max": 7, "avg": 5.5, "cpu": 1 },
    "0": { "histogram": { "6": 2, "9": 1 }, "cycles": 5, "min": 6, "max": 250000, "avg": 9.0, "cpu": 0 }
  }
}"#;

    #[test]
    fn json_histograms_are_read_in_thread_order_with_overflows() {
        let (threads, version) = parse_json(SAMPLE).unwrap();
        assert_eq!(version, "2.40");
        assert_eq!(threads.len(), 2);
        let t0 = &threads[0];
        assert_eq!((t0.hist.len(), t0.overflows), (5, 2));
        assert_eq!(t0.hist.min(), 6000);
        assert!(t0.hist.max() >= 250_000_000);
        assert_eq!((threads[1].hist.len(), threads[1].overflows), (4, 0));
        // 5 µs, within the histogram's 0.1 % resolution.
        let p50 = crate::stats::Percentiles::of(&threads[1].hist).p50_ns;
        assert!((5000..=5005).contains(&p50), "{p50}");
    }

    #[test]
    fn bad_output_is_a_clear_error() {
        for text in [
            "",
            "{}",
            r#"{"thread": {"x": {}}}"#,
            r#"{"thread": {"0": {"cycles": 1, "max": 1}}}"#,
        ] {
            let e = parse_json(text).unwrap_err().to_string();
            assert!(e.starts_with("cyclictest: its --json output"), "{e}");
        }
    }

    #[test]
    fn args_match_the_settings() {
        let r = CyclictestRun {
            cpus: vec![1, 0],
            priority: None,
            interval: Duration::from_micros(250),
            seconds: 2,
        };
        let a = r.args(Path::new("/tmp/x.json")).join(" ");
        assert_eq!(
            a,
            "-q -m -t 2 -a 1,0 -p 0 -i 250 -d 0 -D 2 -h 100000 --json=/tmp/x.json"
        );
    }

    #[test]
    fn runs_when_installed() {
        let Some(exe) = find() else {
            println!("skipped: cyclictest is not installed (Debian package rt-tests)");
            return;
        };
        let r = CyclictestRun {
            cpus: vec![0],
            priority: None,
            interval: Duration::from_micros(1000),
            seconds: 1,
        };
        let (threads, _) = r.run(&exe).unwrap();
        assert_eq!(threads.len(), 1);
        assert!(!threads[0].hist.is_empty());
    }
}
