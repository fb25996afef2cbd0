//! The live print's log: the planner, IO stage and link threads push fixed-size records to the
//! logger thread, which alone writes them (stderr and `--log-file`); the summary reports how many
//! were written and dropped.

use std::time::Duration;

use cadence_tests::{assert_success, cadence, scratch, workspace};

#[test]
fn print_writes_its_log_through_the_logger_thread() {
    let dir = scratch("print-log");
    let log = dir.join("print.log");
    let gcode = workspace().join("examples/square.gcode");
    let run = cadence(
        &[
            "print",
            gcode.to_str().unwrap(),
            "--log-file",
            log.to_str().unwrap(),
            "--log-level",
            "debug",
        ],
        Duration::from_secs(120),
    );
    assert_success(&run);
    let text = std::fs::read_to_string(&log).expect("log file");
    for what in [
        "INFO  planner planner started",
        "INFO  planner homing axes x 1, y 1, z 1",
        "INFO  planner homing done",
        "INFO  io io stage subscribed",
        "INFO  planner planner done",
        "INFO  io io stage done",
    ] {
        assert!(text.contains(what), "'{what}' missing from the log:\n{text}");
    }
    // Homing reports are printed by the main thread with the summary.
    assert!(run.stdout.contains("homing z"), "{}", run.stdout);
    let report = run
        .stdout
        .lines()
        .find(|l| l.contains("records written"))
        .expect("logger report line");
    assert!(report.contains(" 0 dropped"), "{report}");
}

#[test]
fn unknown_log_level_is_a_clear_error() {
    let gcode = workspace().join("examples/square.gcode");
    let run = cadence(
        &["print", gcode.to_str().unwrap(), "--log-level", "loud"],
        Duration::from_secs(60),
    );
    assert_eq!(run.code, Some(2), "{}", run.stderr);
    assert!(run.stderr.contains("unknown log level 'loud'"), "{}", run.stderr);
}
