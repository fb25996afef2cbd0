//! CLI smoke tests of the `cadence` executable (the end-to-end prints live in `tests/`).

use std::process::Command;

fn cadence(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_cadence"))
        .args(args)
        .output()
        .expect("run cadence")
}

#[test]
fn help_lists_the_subcommands() {
    let out = cadence(&["--help"]);
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    for sub in ["print", "decode"] {
        assert!(text.contains(sub), "{sub} missing from:\n{text}");
    }
}

#[test]
fn bad_arguments_are_a_clear_error_not_a_panic() {
    for args in [
        &["print"][..],
        &["print", "x.gcode", "--time-scale", "abc"],
        &["print", "x.gcode", "--time-scale", "0"],
        &["print", "x.gcode", "--max-error-us", "-1"],
        &["print", "x.gcode", "--log-level", "loud"],
        &["print", "x.gcode", "--io-process", "--io-attach", "x"],
        &["serve", "--retry", "0"],
        &["serve", "--simulated", "--config", "x.cfg"],
        &["serve", "-a"],
        &["serve", "--role", "planner"],
        &["frobnicate"],
    ] {
        let out = cadence(args);
        assert!(!out.status.success(), "{args:?} succeeded");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!err.contains("panicked"), "{args:?}: {err}");
        assert!(!err.trim().is_empty(), "{args:?}: no error message");
    }
}

#[test]
fn serve_and_print_document_the_io_process_options() {
    let out = cadence(&["serve", "--help"]);
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    for opt in [
        "--role",
        "--instance",
        "--parent-pid",
        "--idle-timeout",
        "--log-file",
    ] {
        assert!(text.contains(opt), "{opt} missing from:\n{text}");
    }
    let out = cadence(&["print", "--help"]);
    let text = String::from_utf8_lossy(&out.stdout);
    for opt in ["--io-process", "--io-attach", "--log-file", "--log-level"] {
        assert!(text.contains(opt), "{opt} missing from:\n{text}");
    }
}

#[test]
fn serve_with_a_missing_config_names_it() {
    let out = cadence(&["serve", "--role", "io", "--config", "/nonexistent/printer.cfg"]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("/nonexistent/printer.cfg"), "{err}");
    assert!(err.contains("cadence serve: error"), "{err}");
}

#[test]
fn decode_of_a_missing_file_names_it() {
    let out = cadence(&["decode", "/nonexistent/stream.bin"]);
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/stream.bin"));
}

#[test]
fn bench_plan_reports_figures() {
    let gcode = concat!(env!("CARGO_MANIFEST_DIR"), "/examples/square.gcode");
    let out = cadence(&["bench", "plan", gcode]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("queue_step") && text.contains("steps/s"), "{text}");
}
