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
