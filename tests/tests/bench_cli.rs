//! End to end: `cadence bench wakeup|handoff|plan` as a user runs them (a second or less each):
//! the text header and table, `--json`, the hand-off consumer in its own `cadence` process,
//! `--hlog` and `--plot` files, and clear errors for options that cannot make a run.

use std::time::Duration;

use cadence_tests::{assert_success, cadence, scratch};

const TIMEOUT: Duration = Duration::from_secs(120);

#[test]
fn wakeup_prints_the_host_and_a_percentile_table() {
    let dir = scratch("bench_wakeup_text");
    let (hlog, png) = (dir.join("w.hlog"), dir.join("w.png"));
    let run = cadence(
        &[
            "bench",
            "wakeup",
            "--cpus",
            "0",
            "--duration",
            "500ms",
            "--hlog",
            hlog.to_str().unwrap(),
            "--plot",
            png.to_str().unwrap(),
        ],
        TIMEOUT,
    );
    assert_success(&run);
    for want in [
        "host: kernel",
        "RT throttling",
        "SCHED_FIFO 80",
        "p99.99",
        "cpu0",
        "budget",
    ] {
        assert!(run.stdout.contains(want), "{want:?} missing:\n{}", run.stdout);
    }
    assert!(std::fs::read(&hlog)
        .unwrap()
        .starts_with(b"#cadence bench wakeup"));
    assert!(std::fs::read(&png).unwrap().starts_with(b"\x89PNG"));
}

#[test]
fn wakeup_json_is_one_document_of_the_schema() {
    let run = cadence(
        &[
            "bench",
            "wakeup",
            "--cpus",
            "0",
            "--loops",
            "200",
            "--priority",
            "0",
            "--json",
        ],
        TIMEOUT,
    );
    assert_success(&run);
    let out = run.stdout.trim();
    assert!(out.starts_with('{') && out.ends_with('}'), "{out}");
    for want in [
        "\"schema\": \"cadence-bench/1\"",
        "\"mode\": \"wakeup\"",
        "\"count\": 200",
        "\"p99_99_ns\"",
    ] {
        assert!(out.contains(want), "{want:?} missing:\n{out}");
    }
}

#[test]
fn handoff_measures_threads_and_a_consumer_process() {
    let run = cadence(
        &["bench", "handoff", "--samples", "300", "--json", "--no-progress"],
        TIMEOUT,
    );
    assert_success(&run);
    for want in [
        "\"mode\": \"handoff\"",
        "\"queue-poll\"",
        "\"ipc-event\"",
        "\"proc-poll\"",
        "\"proc-event\"",
    ] {
        assert!(run.stdout.contains(want), "{want:?} missing:\n{}", run.stdout);
    }
    assert!(!run.stdout.contains("failed"), "{}", run.stdout);
}

#[test]
fn plan_takes_the_common_options() {
    let run = cadence(&["bench", "plan", "examples/square.gcode", "--json"], TIMEOUT);
    assert_success(&run);
    assert!(
        run.stdout.contains("\"mode\": \"plan\"") && run.stdout.contains("\"steps_per_s\""),
        "{}",
        run.stdout
    );
}

/// `--compare STREAM`: another host's batch stream of the same file beside this run, stepper by
/// stepper. Cadence's own batch stream of the file must count exactly as the run does; a
/// truncated one is an error naming the byte.
#[test]
fn plan_compare_counts_a_batch_stream_beside_the_run() {
    let dir = scratch("bench_plan_compare");
    let stream = dir.join("square.bin");
    let print = cadence(
        &[
            "print",
            "examples/square.gcode",
            "--batch",
            stream.to_str().unwrap(),
        ],
        TIMEOUT,
    );
    assert_success(&print);
    let args = [
        "bench",
        "plan",
        "examples/square.gcode",
        "--compare",
        stream.to_str().unwrap(),
    ];
    let run = cadence(&args, TIMEOUT);
    assert_success(&run);
    let rows: Vec<&str> = run
        .stdout
        .lines()
        .skip_while(|l| !l.starts_with("against "))
        .skip(2)
        .collect();
    for want in [
        "queue_step",
        "set_next_step_dir",
        "step command bytes",
        "stepper_x steps",
        "extruder queue_step",
    ] {
        let row = rows.iter().find(|r| r.trim_start().starts_with(want));
        let row = row.unwrap_or_else(|| panic!("no {want:?} row:\n{}", run.stdout));
        let cells: Vec<&str> = row.split_whitespace().rev().take(3).collect();
        assert_eq!(cells[0], "1.000", "{row}");
        assert_eq!(cells[1], cells[2], "{row}");
    }
    // The same figures in the JSON report, each beside its stream's.
    let json = cadence(&[&args[..], &["--json"]].concat(), TIMEOUT);
    assert_success(&json);
    let v: serde_json::Value = serde_json::from_str(&json.stdout).expect("JSON report");
    let f = &v["figures"];
    for key in ["queue_steps", "steps", "steps.stepper_y", "queue_steps.extruder"] {
        assert!(f[key].as_f64().is_some_and(|n| n > 0.0), "{key}: {f}");
        assert_eq!(f[key], f[format!("compare_{key}")], "{key}: {f}");
    }
    // A stream cut short.
    let bytes = std::fs::read(&stream).unwrap();
    std::fs::write(&stream, &bytes[..bytes.len() - 3]).unwrap();
    let cut = cadence(&args, TIMEOUT);
    assert_eq!(cut.code, Some(1), "{}", cut.stdout);
    assert!(
        cut.stderr.contains("truncated block") && cut.stderr.contains("square.bin"),
        "{}",
        cut.stderr
    );
}

#[test]
fn options_that_make_no_run_are_clear_errors() {
    for (args, want) in [
        (
            &["bench", "wakeup", "--busy-wait", "--compare-cyclictest"][..],
            "busy",
        ),
        (
            &["bench", "wakeup", "--loops", "10", "--compare-cyclictest"],
            "--duration",
        ),
        (
            &["bench", "wakeup", "--loops", "10", "--plot", "x.jpg"],
            ".svg or .png",
        ),
        (
            &["bench", "plan", "examples/square.gcode", "--plot", "x.svg"],
            "--hlog and --plot",
        ),
        (&["bench", "handoff", "--cores", "0"], "two CPUs"),
    ] {
        let run = cadence(args, TIMEOUT);
        assert_eq!(run.code, Some(1), "{args:?}: {}", run.stdout);
        assert!(run.stderr.contains(want), "{args:?}: {}", run.stderr);
        assert!(!run.stderr.contains("panicked"), "{args:?}: {}", run.stderr);
    }
}
