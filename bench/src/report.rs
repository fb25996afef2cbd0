//! The one result schema of every `cadence bench` mode, written by `--json` and documented
//! here field by field (README's bench section points to it).
//!
//! ```text
//! {
//!   "schema": "cadence-bench/1",
//!   "mode": "wakeup" | "handoff" | "plan",
//!   "host": { kernel, preempt, governor, isolated_cpus, rt_throttling, smt, cpus },
//!   "settings": { ...the mode's options as given, names as on the command line... },
//!   "load": null | { "kind": "cpu"|"io"|"mem", "tool": "stress-ng"|"builtin" },
//!   "wall_s": seconds the measurement ran,
//!   "budget_ns": null | the budget drawn in plots (e.g. 25 ms homing),
//!   "series": [ { "name", "unit": "ns", "percentiles": { count, min_ns, avg_ns, p50_ns,
//!                 p99_ns, p99_9_ns, p99_99_ns, max_ns } } ],
//!   "compare": null | { "tool", "version", "series": [same as above],
//!                       "ratios": [ { "percentile", "cadence_us", "tool_us", "ratio" } ] },
//!   "figures": { name: number } (throughput figures: plan's moves_per_s, wall_s...),
//!   "verdict": null | one line,
//!   "notes": [ refusals and fallbacks, e.g. "SCHED_FIFO refused: ..." ],
//!   "baseline": null | { "file", "ratios": [ { "figure", "this", "baseline", "ratio" } ] }
//! }
//! ```
//! `baseline` (with `--compare REPORT.json`, optional when read back) holds this run's figures
//! over a saved report's of the same mode: every `figures` entry both have, and each series
//! both have as `SERIES.p50_ns`, `.p99_ns`, `.p99_9_ns`, `.max_ns`.
//! Latencies are integers in nanoseconds (avg a float); a series' `name` is its thread
//! (`cpu0`), transport (`queue-poll`) or `all`. `ratio` is Cadence's over the tool's figure,
//! null where the tool's is 0.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::host::Host;
use crate::stats::{us, Percentiles, COLUMNS};

/// The value of `schema`.
pub const SCHEMA: &str = "cadence-bench/1";

/// One run's results.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Report {
    pub schema: String,
    pub mode: String,
    pub host: Host,
    pub settings: serde_json::Map<String, serde_json::Value>,
    pub load: Option<LoadInfo>,
    pub wall_s: f64,
    pub budget_ns: Option<u64>,
    pub series: Vec<SeriesReport>,
    pub compare: Option<Compare>,
    pub figures: BTreeMap<String, f64>,
    pub verdict: Option<String>,
    pub notes: Vec<String>,
    #[serde(default)]
    pub baseline: Option<Baseline>,
}

/// This run against a saved report (`--compare`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Baseline {
    /// The saved report's path.
    pub file: String,
    pub ratios: Vec<FigureRatio>,
}

/// One figure of this run and of the saved report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FigureRatio {
    pub figure: String,
    pub this: f64,
    pub baseline: f64,
    /// `this / baseline`, null where the baseline is 0.
    pub ratio: Option<f64>,
}

/// The stressor that ran beside the measurement.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LoadInfo {
    pub kind: String,
    pub tool: String,
}

/// One latency series.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SeriesReport {
    pub name: String,
    pub unit: String,
    pub percentiles: Percentiles,
}

/// The same measurement by another tool, and Cadence's figures over its figures.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Compare {
    pub tool: String,
    pub version: String,
    pub series: Vec<SeriesReport>,
    pub ratios: Vec<Ratio>,
}

/// One percentile of the comparison.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ratio {
    pub percentile: String,
    pub cadence_us: f64,
    pub tool_us: f64,
    pub ratio: Option<f64>,
}

impl Report {
    /// An empty report of `mode` on `host`.
    pub fn new(mode: &str, host: Host) -> Report {
        Report {
            schema: SCHEMA.into(),
            mode: mode.into(),
            host,
            settings: serde_json::Map::new(),
            load: None,
            wall_s: 0.0,
            budget_ns: None,
            series: Vec::new(),
            compare: None,
            figures: BTreeMap::new(),
            verdict: None,
            notes: Vec::new(),
            baseline: None,
        }
    }

    /// Reads a saved report (`--compare FILE`).
    pub fn read(path: &std::path::Path) -> Result<Report, crate::BenchError> {
        let text = std::fs::read_to_string(path).map_err(|e| crate::BenchError::file(path, e))?;
        let r: Report = serde_json::from_str(&text).map_err(|e| {
            crate::BenchError::Options(format!(
                "{}: not a cadence bench --json report: {e}",
                path.display()
            ))
        })?;
        if r.schema != SCHEMA {
            return Err(crate::BenchError::Options(format!(
                "{}: schema {:?}, expected {SCHEMA:?}",
                path.display(),
                r.schema
            )));
        }
        Ok(r)
    }

    /// This report's figures and series percentiles over `saved`'s, where both have them.
    pub fn ratios_to(&self, saved: &Report) -> Vec<FigureRatio> {
        let ratio = |figure: String, this: f64, baseline: f64| FigureRatio {
            figure,
            this,
            baseline,
            ratio: (baseline != 0.0).then(|| this / baseline),
        };
        let mut out: Vec<FigureRatio> = self
            .figures
            .iter()
            .filter_map(|(k, &v)| saved.figures.get(k).map(|&b| ratio(k.clone(), v, b)))
            .collect();
        for s in &self.series {
            let Some(b) = saved.series.iter().find(|b| b.name == s.name) else {
                continue;
            };
            let (p, q) = (&s.percentiles, &b.percentiles);
            for (name, x, y) in [
                ("p50_ns", p.p50_ns, q.p50_ns),
                ("p99_ns", p.p99_ns, q.p99_ns),
                ("p99_9_ns", p.p99_9_ns, q.p99_9_ns),
                ("max_ns", p.max_ns, q.max_ns),
            ] {
                out.push(ratio(format!("{}.{name}", s.name), x as f64, y as f64));
            }
        }
        out
    }

    /// Records a setting (`settings[name] = value`).
    pub fn set(&mut self, name: &str, value: impl Into<serde_json::Value>) {
        self.settings.insert(name.into(), value.into());
    }

    /// Pretty JSON (serializing plain data cannot fail; the error is kept for the caller).
    pub fn to_json(&self) -> Result<String, serde_json::Error> {
        serde_json::to_string_pretty(self)
    }

    /// The text table of the series (µs), then the comparison, verdict and notes.
    pub fn text_body(&self) -> Vec<String> {
        let mut out = Vec::new();
        if !self.series.is_empty() {
            out.push(table_head("series"));
            for s in &self.series {
                out.push(table_row(&s.name, &s.percentiles));
            }
        }
        if let Some(c) = &self.compare {
            out.push(format!("{} {} over the same slices:", c.tool, c.version));
            out.push(table_head(c.tool.as_str()));
            for s in &c.series {
                out.push(table_row(&s.name, &s.percentiles));
            }
            let mut line = format!("{:<14}", "ratio");
            for r in &c.ratios {
                let v = r.ratio.map_or("-".to_string(), |x| format!("{x:.2}"));
                line.push_str(&format!(" {}={v}", r.percentile));
            }
            out.push(line);
        }
        for (k, v) in &self.figures {
            out.push(format!("{k}: {v}"));
        }
        if let Some(v) = &self.verdict {
            out.push(v.clone());
        }
        for n in &self.notes {
            out.push(format!("note: {n}"));
        }
        if let Some(b) = &self.baseline {
            out.push(format!("against {}:", b.file));
            out.push(format!(
                "{:<34} {:>16} {:>16} {:>8}",
                "figure", "this", "baseline", "ratio"
            ));
            for r in &b.ratios {
                let v = r.ratio.map_or("-".to_string(), |x| format!("{x:.3}"));
                out.push(format!(
                    "{:<34} {:>16} {:>16} {v:>8}",
                    r.figure,
                    num(r.this),
                    num(r.baseline)
                ));
            }
        }
        out
    }
}

/// A figure for the comparison table: whole numbers without decimals.
fn num(v: f64) -> String {
    if v.fract() == 0.0 && v.abs() < 1e15 {
        format!("{v:.0}")
    } else {
        format!("{v:.4}")
    }
}

fn table_head(first: &str) -> String {
    let mut s = format!("{first:<14} {:>9}", "count");
    for c in COLUMNS {
        s.push_str(&format!(" {c:>9}"));
    }
    s.push_str("  (µs)");
    s
}

fn table_row(name: &str, p: &Percentiles) -> String {
    let mut s = format!("{name:<14} {:>9}", p.count);
    for v in p.columns() {
        s.push_str(&format!(" {:>9}", us(v)));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_round_trips_and_names_every_field() {
        let mut r = Report::new("wakeup", Host::read());
        r.set("interval_us", 1000);
        r.series.push(SeriesReport {
            name: "cpu0".into(),
            unit: "ns".into(),
            percentiles: Percentiles {
                count: 3,
                min_ns: 1,
                avg_ns: 2.0,
                p50_ns: 2,
                p99_ns: 3,
                p99_9_ns: 3,
                p99_99_ns: 3,
                max_ns: 3,
            },
        });
        let text = r.to_json().unwrap();
        let back: Report = serde_json::from_str(&text).unwrap();
        assert_eq!(back, r);
        let v: serde_json::Value = serde_json::from_str(&text).unwrap();
        for key in [
            "schema",
            "mode",
            "host",
            "settings",
            "load",
            "wall_s",
            "budget_ns",
            "series",
            "compare",
            "figures",
            "verdict",
            "notes",
            "baseline",
        ] {
            assert!(v.get(key).is_some(), "{key} missing from {text}");
        }
        assert_eq!(v["series"][0]["percentiles"]["p99_9_ns"], 3);
        let table = r.text_body().join("\n");
        assert!(table.contains("p99.99") && table.contains("cpu0"), "{table}");
        // A report without `baseline` (written before it existed) still reads.
        let mut old: serde_json::Value = v.clone();
        old.as_object_mut().unwrap().remove("baseline");
        let back: Report = serde_json::from_value(old).unwrap();
        assert_eq!(back.baseline, None);
    }

    #[test]
    fn ratios_to_a_saved_report() {
        let mut saved = Report::new("plan", Host::read());
        saved.figures.insert("queue_steps".into(), 200.0);
        saved.figures.insert("wall_s".into(), 0.0);
        saved.figures.insert("only_saved".into(), 1.0);
        let mut this = saved.clone();
        this.figures.insert("queue_steps".into(), 100.0);
        this.figures.insert("only_this".into(), 1.0);
        this.figures.remove("only_saved");
        let p = Percentiles {
            count: 1,
            p50_ns: 10,
            p99_ns: 20,
            p99_9_ns: 30,
            max_ns: 40,
            ..Percentiles::default()
        };
        let series = |p: Percentiles| SeriesReport {
            name: "all".into(),
            unit: "ns".into(),
            percentiles: p,
        };
        saved.series.push(series(p));
        this.series.push(series(Percentiles { p50_ns: 20, ..p }));
        let r = this.ratios_to(&saved);
        let get = |f: &str| r.iter().find(|x| x.figure == f).map(|x| x.ratio);
        assert_eq!(get("queue_steps"), Some(Some(0.5)));
        assert_eq!(get("wall_s"), Some(None));
        assert_eq!(get("only_this"), None);
        assert_eq!(get("only_saved"), None);
        assert_eq!(get("all.p50_ns"), Some(Some(2.0)));
        assert_eq!(get("all.max_ns"), Some(Some(1.0)));
        this.baseline = Some(Baseline {
            file: "saved.json".into(),
            ratios: r,
        });
        let text = this.text_body().join("\n");
        assert!(
            text.contains("against saved.json:") && text.contains("queue_steps"),
            "{text}"
        );
    }
}
