//! A short real run (a second or less) of each `cadence bench` mode through the library the
//! CLI calls, with every common output: the JSON parsed back into the schema, the interval log
//! read back with hdrhistogram, the SVG parsed as XML. Figures are checked for plausibility
//! (positive, percentiles ordered), never against a time.

use std::path::{Path, PathBuf};
use std::time::Duration;

use bench::handoff::HandoffOpts;
use bench::load::{LoadKind, LoadTool};
use bench::modes::plan::Extras;
use bench::modes::wakeup::WakeupMode;
use bench::report::{Report, SCHEMA};
use bench::run::Common;
use bench::wakeup::{Stop, Wait, WakeupOptions};

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("cadence-bench-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn common(dir: &Path, json: bool) -> Common {
    Common {
        json,
        hlog: Some(dir.join("run.hlog")),
        plot: Some(dir.join("run.svg")),
        progress: false,
        ..Common::default()
    }
}

fn check_series(r: &Report) {
    assert!(!r.series.is_empty(), "no series: {r:?}");
    for s in &r.series {
        let p = &s.percentiles;
        assert!(p.count > 0, "{}: no samples", s.name);
        assert!(p.max_ns > 0, "{}: {p:?}", s.name);
        assert!(p.ordered(), "{}: percentiles out of order {p:?}", s.name);
        assert_eq!(s.unit, "ns");
    }
}

fn check_svg(path: &Path, names: &[&str]) {
    let text = std::fs::read_to_string(path).unwrap();
    let doc = roxmltree::Document::parse(&text).unwrap();
    let texts: Vec<&str> = doc
        .descendants()
        .filter(|n| n.has_tag_name("text"))
        .filter_map(|n| n.text())
        .collect();
    for want in [
        "latency histogram",
        "percentile distribution",
        "percentile",
        "latency",
    ]
    .iter()
    .chain(names)
    {
        assert!(
            texts.iter().any(|t| t.contains(want)),
            "{want:?} not in {texts:?}"
        );
    }
    let lines = doc.descendants().filter(|n| n.has_tag_name("polyline")).count();
    assert!(lines >= 2 * names.len(), "{lines} polylines for {names:?}");
}

fn check_hlog(path: &Path, tags: &[&str]) -> u64 {
    let back = bench::hlog::read(path).unwrap();
    for t in tags {
        assert!(
            back.iter().any(|i| i.tag.as_deref() == Some(*t)),
            "{t} not in the log"
        );
    }
    back.iter().map(|i| i.hist.len()).sum()
}

#[test]
fn wakeup_runs_with_every_output() {
    let dir = scratch("wakeup");
    let mode = WakeupMode {
        measure: WakeupOptions {
            cpus: vec![0],
            priority: Some(50),
            interval: Duration::from_micros(1000),
            stop: Stop::Duration(Duration::from_millis(600)),
            wait: Wait::Sleep,
            log_interval: Duration::from_millis(200),
        },
        lock_memory: false,
        compare_cyclictest: false,
        slice: Duration::from_secs(1),
    };
    let mut out = Vec::new();
    let r = bench::modes::wakeup::run(&mode, &common(&dir, true), &mut out).unwrap();
    let back: Report = serde_json::from_slice(&out).unwrap();
    assert_eq!(back, r);
    assert_eq!((r.schema.as_str(), r.mode.as_str()), (SCHEMA, "wakeup"));
    assert_eq!(r.budget_ns, Some(25_000_000));
    assert!(r.verdict.is_some());
    check_series(&r);
    // Every sample is in the log, over one or more intervals.
    assert_eq!(
        check_hlog(&dir.join("run.hlog"), &["cpu0"]),
        r.series[0].percentiles.count
    );
    check_svg(&dir.join("run.svg"), &["cadence cpu0", "budget"]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn wakeup_busy_wait_with_builtin_load_in_text() {
    let dir = scratch("busy");
    let mode = WakeupMode {
        measure: WakeupOptions {
            cpus: vec![0],
            priority: None,
            interval: Duration::from_micros(200),
            stop: Stop::Loops(500),
            wait: Wait::Busy,
            log_interval: Duration::from_secs(1),
        },
        lock_memory: false,
        compare_cyclictest: false,
        slice: Duration::from_secs(1),
    };
    let c = Common {
        load: Some(LoadKind::Mem),
        load_tool: LoadTool::Builtin,
        budget_ns: Some(0),
        progress: false,
        ..Common::default()
    };
    let mut out = Vec::new();
    let r = bench::modes::wakeup::run(&mode, &c, &mut out).unwrap();
    let text = String::from_utf8(out).unwrap();
    assert!(text.starts_with("host: kernel"), "{text}");
    assert!(
        text.contains("load: mem (builtin)") && text.contains("busy-wait"),
        "{text}"
    );
    assert!(text.contains("p99.99") && text.contains("cpu0"), "{text}");
    assert_eq!(r.series[0].percentiles.count, 500);
    assert_eq!(r.budget_ns, None);
    assert_eq!(r.load.as_ref().map(|l| l.tool.as_str()), Some("builtin"));
    check_series(&r);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn wakeup_compared_with_cyclictest_when_installed() {
    if bench::cyclictest::find().is_none() {
        println!("skipped: cyclictest is not installed (Debian package rt-tests)");
        return;
    }
    let dir = scratch("compare");
    let mode = WakeupMode {
        measure: WakeupOptions {
            cpus: vec![0],
            priority: None,
            interval: Duration::from_micros(1000),
            stop: Stop::Duration(Duration::from_secs(1)),
            wait: Wait::Sleep,
            log_interval: Duration::from_secs(1),
        },
        lock_memory: false,
        compare_cyclictest: true,
        slice: Duration::from_secs(1),
    };
    let mut out = Vec::new();
    let r = bench::modes::wakeup::run(&mode, &common(&dir, false), &mut out).unwrap();
    let text = String::from_utf8(out).unwrap();
    let c = r.compare.as_ref().expect("a comparison");
    assert_eq!(c.tool, "cyclictest");
    assert!(c.series[0].percentiles.count > 0 && c.series[0].percentiles.ordered());
    assert_eq!(c.ratios.len(), 7);
    assert!(
        c.ratios.iter().all(|x| x.ratio.is_none_or(|v| v > 0.0)),
        "{:?}",
        c.ratios
    );
    assert!(text.contains("ratio") && text.contains("p99.9="), "{text}");
    check_hlog(&dir.join("run.hlog"), &["cpu0", "cyclictest-cpu0"]);
    check_svg(&dir.join("run.svg"), &["cadence cpu0", "cyclictest cpu0"]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn handoff_runs_with_every_output() {
    let dir = scratch("handoff");
    let o = HandoffOpts {
        samples: 300,
        gap: Duration::from_micros(20),
        ..HandoffOpts::default()
    };
    let mut out = Vec::new();
    let r = bench::modes::handoff::run(&o, None, &common(&dir, true), &mut out).unwrap();
    let back: Report = serde_json::from_slice(&out).unwrap();
    assert_eq!(back.mode, "handoff");
    check_series(&r);
    let names: Vec<&str> = r.series.iter().map(|s| s.name.as_str()).collect();
    assert!(
        names.contains(&"queue-poll") && names.contains(&"handoff-poll"),
        "{names:?}"
    );
    assert!(r.series.iter().all(|s| s.percentiles.count == 300));
    check_hlog(&dir.join("run.hlog"), &["queue-poll"]);
    check_svg(&dir.join("run.svg"), &["queue-poll"]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn plan_reports_figures_and_refuses_latency_outputs() {
    let dir = scratch("plan");
    let examples = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples");
    let gcode = examples.join("square.gcode");
    let cfg = sysconfig::printer::load(&examples.join("simulated-cartesian.cfg")).unwrap();
    let opts = bench::plan::PlanOptions::default();
    let c = Common {
        json: true,
        progress: false,
        ..Common::default()
    };
    let mut out = Vec::new();
    let r = bench::modes::plan::run(&gcode, &cfg, &opts, 2, &Extras::default(), &c, &mut out).unwrap();
    let back: Report = serde_json::from_slice(&out).unwrap();
    assert_eq!(back.mode, "plan");
    for k in [
        "moves",
        "steps",
        "queue_steps",
        "wire_bytes",
        "wall_s",
        "wall_median_s",
    ] {
        assert!(r.figures.get(k).is_some_and(|v| *v > 0.0), "{k}: {:?}", r.figures);
    }
    let e = bench::modes::plan::run(
        &gcode,
        &cfg,
        &opts,
        1,
        &Extras::default(),
        &common(&dir, false),
        &mut Vec::new(),
    )
    .unwrap_err();
    assert!(e.to_string().contains("--hlog and --plot"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn plan_compares_with_a_saved_report() {
    let dir = scratch("plan_compare");
    let examples = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples");
    let gcode = examples.join("square.gcode");
    let cfg = sysconfig::printer::load(&examples.join("simulated-cartesian.cfg")).unwrap();
    let opts = bench::plan::PlanOptions::default();
    let c = Common {
        json: true,
        progress: false,
        ..Common::default()
    };
    let mut out = Vec::new();
    bench::modes::plan::run(&gcode, &cfg, &opts, 1, &Extras::default(), &c, &mut out).unwrap();
    let saved = dir.join("saved.json");
    std::fs::write(&saved, &out).unwrap();
    // Text mode: the comparison table is printed, and the report keeps the ratios.
    let c = Common {
        json: false,
        progress: false,
        compare: Some(saved.clone()),
        ..Common::default()
    };
    let mut text = Vec::new();
    let r = bench::modes::plan::run(&gcode, &cfg, &opts, 1, &Extras::default(), &c, &mut text).unwrap();
    let text = String::from_utf8(text).unwrap();
    assert!(text.contains(&format!("against {}:", saved.display())), "{text}");
    let b = r.baseline.unwrap();
    let get = |f: &str| b.ratios.iter().find(|x| x.figure == f).unwrap();
    // Planning is deterministic: the same commands, bytes and steps.
    for f in ["queue_steps", "wire_bytes", "steps", "moves"] {
        assert_eq!(get(f).ratio, Some(1.0), "{f}: {:?}", get(f));
    }
    assert!(get("wall_s").ratio.is_some_and(|x| x > 0.0));
    // A report of another mode, or not a report at all, is refused before running.
    let mut wakeup = Report::new("wakeup", bench::host::Host::read());
    wakeup.wall_s = 1.0;
    let other = dir.join("wakeup.json");
    std::fs::write(&other, wakeup.to_json().unwrap()).unwrap();
    let garbage = dir.join("garbage.json");
    std::fs::write(&garbage, "{\"schema\": 1}").unwrap();
    for (file, want) in [
        (&other, "not of bench plan"),
        (&garbage, "not a cadence bench --json report"),
    ] {
        let c = Common {
            compare: Some(file.clone()),
            progress: false,
            ..Common::default()
        };
        let e = bench::modes::plan::run(&gcode, &cfg, &opts, 1, &Extras::default(), &c, &mut Vec::new())
            .unwrap_err();
        assert!(e.to_string().contains(want), "{e}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
