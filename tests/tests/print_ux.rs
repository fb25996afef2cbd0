//! `cadence print` as a person meets it: Ctrl-C / SIGTERM (a real signal to a real child
//! process, also with SIGINT inherited as ignored) end the print cleanly with the interrupted
//! note, the full summary and exit status 130/143; the summary in plain words, `--json`; an
//! empty file, a UTF-8 byte-order mark and control bytes in a bad line.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use cadence_tests::{assert_exit, assert_success, bin, cadence, run_then, scratch, workspace, Run};
use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;

const TIMEOUT: Duration = Duration::from_secs(180);

/// A G-code file that prints for minutes: homing, then `n` long zig-zag moves.
fn long_print(dir: &Path, n: usize) -> PathBuf {
    let mut text = String::from("G28\nG90\nG1 Z1 F600\n");
    for i in 0..n {
        let x = if i % 2 == 0 { 150 } else { 30 };
        text.push_str(&format!("G1 X{x} Y{} F1200\n", 30 + i % 100));
    }
    let path = dir.join("long.gcode");
    std::fs::write(&path, text).expect("write G-code");
    path
}

/// Starts `cmd`, sends `sig` once it has run `after`, and waits (bounded) for it to end.
fn signalled(cmd: &mut Command, sig: Signal, after: Duration) -> Run {
    run_then(cmd, TIMEOUT, |child| {
        std::thread::sleep(after);
        let pid = Pid::from_raw(i32::try_from(child.id()).expect("pid"));
        kill(pid, sig).expect("send the signal");
    })
}

/// The line number of the "interrupted … at line N" note.
fn interrupted_line(run: &Run, sig: &str) -> u64 {
    let note = format!("cadence: interrupted ({sig}) at line ");
    let line = run
        .stderr
        .lines()
        .find_map(|l| l.strip_prefix(note.as_str()))
        .unwrap_or_else(|| panic!("no interrupted note:\n{}", run.stderr));
    line.split_whitespace()
        .next()
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("bad note: {line}"))
}

/// What every interrupted print must show: the note before the end of the file, then the same
/// summary as a finished print, positions checked.
fn check_interrupted(run: &Run, sig: &str, code: i32, total_lines: u64) {
    assert_exit(run, code);
    let line = interrupted_line(run, sig);
    assert!(line < total_lines, "interrupted at line {line} of {total_lines}");
    assert!(run.stdout.contains("  printed "), "{}", run.stdout);
    assert!(
        run.stdout
            .contains("final position matches the MCU's step count on all 4 steppers"),
        "{}",
        run.stdout
    );
    assert!(run.stdout.contains("Details:"), "{}", run.stdout);
}

#[test]
fn sigint_stops_the_print_with_the_summary_and_exit_130() {
    let dir = scratch("ux-sigint");
    let gcode = long_print(&dir, 2000);
    let mut cmd = Command::new(bin("cadence"));
    cmd.arg("print").arg(&gcode);
    let run = signalled(&mut cmd, Signal::SIGINT, Duration::from_secs(4));
    check_interrupted(&run, "SIGINT", 130, 2003);
}

#[test]
fn sigterm_stops_the_print_with_the_summary_and_exit_143() {
    let dir = scratch("ux-sigterm");
    let gcode = long_print(&dir, 2000);
    let mut cmd = Command::new(bin("cadence"));
    cmd.arg("print").arg(&gcode);
    let run = signalled(&mut cmd, Signal::SIGTERM, Duration::from_secs(4));
    check_interrupted(&run, "SIGTERM", 143, 2003);
}

#[test]
fn sigint_stops_the_print_even_when_inherited_as_ignored() {
    let dir = scratch("ux-sigint-ignored");
    let gcode = long_print(&dir, 2000);
    // The shell ignores SIGINT and execs cadence, which inherits the ignored disposition (as
    // a job started with `&` from a non-interactive shell does).
    let mut cmd = Command::new("sh");
    cmd.arg("-c")
        .arg("trap '' INT; exec \"$0\" print \"$1\"")
        .arg(bin("cadence"))
        .arg(&gcode);
    let run = signalled(&mut cmd, Signal::SIGINT, Duration::from_secs(4));
    check_interrupted(&run, "SIGINT", 130, 2003);
}

#[test]
fn summary_speaks_plainly_and_json_has_all_of_it() {
    let gcode = workspace().join("examples/square.gcode");
    let run = cadence(&["print", gcode.to_str().unwrap()], TIMEOUT);
    assert_success(&run);
    let lines: Vec<&str> = run.stdout.lines().collect();
    assert!(lines[1].starts_with("  printed "), "{}", run.stdout);
    assert!(lines[1].contains(" moves ("), "{}", run.stdout);
    assert!(
        lines[2].starts_with("  all motion was sent at least ")
            && lines[2].ends_with("(the safe minimum is 100 ms)"),
        "{}",
        run.stdout
    );
    assert!(
        !run.stdout.contains(" us "),
        "µs written one way:\n{}",
        run.stdout
    );

    let run = cadence(&["print", gcode.to_str().unwrap(), "--json"], TIMEOUT);
    assert_success(&run);
    let v: serde_json::Value = serde_json::from_str(run.stdout.trim()).expect("JSON summary");
    assert!(v["moves"].as_u64().unwrap_or(0) > 0, "{v}");
    assert!(v["min_lead_ms"].as_f64().unwrap_or(0.0) >= 100.0, "{v}");
    let steppers = v["steppers"].as_array().expect("steppers");
    assert_eq!(steppers.len(), 4, "{v}");
    assert!(steppers.iter().all(|s| s["matches"] == true), "{v}");
    assert!(
        v["summary"][0].as_str().unwrap_or("").starts_with("printed "),
        "{v}"
    );
}

#[test]
fn empty_file_is_warned_about() {
    let dir = scratch("ux-empty");
    let gcode = dir.join("empty.gcode");
    std::fs::write(&gcode, "").expect("write");
    let run = cadence(&["print", gcode.to_str().unwrap()], TIMEOUT);
    assert_success(&run);
    assert!(
        run.stderr.contains("empty.gcode is empty: nothing to print"),
        "{}",
        run.stderr
    );
}

#[test]
fn a_byte_order_mark_is_skipped_and_control_bytes_are_escaped() {
    let dir = scratch("ux-bom");
    let square = std::fs::read(workspace().join("examples/square.gcode")).expect("square");
    let with_bom = dir.join("bom.gcode");
    let mut bytes = b"\xEF\xBB\xBF".to_vec();
    bytes.extend_from_slice(&square);
    std::fs::write(&with_bom, bytes).expect("write");
    let (a, b) = (dir.join("plain.bin"), dir.join("bom.bin"));
    let gcode = workspace().join("examples/square.gcode");
    assert_success(&cadence(
        &["print", gcode.to_str().unwrap(), "--batch", a.to_str().unwrap()],
        TIMEOUT,
    ));
    assert_success(&cadence(
        &[
            "print",
            with_bom.to_str().unwrap(),
            "--batch",
            b.to_str().unwrap(),
        ],
        TIMEOUT,
    ));
    assert_eq!(
        std::fs::read(&a).expect("a"),
        std::fs::read(&b).expect("b"),
        "the BOM changed the wire stream"
    );

    let binary = dir.join("binary.gcode");
    std::fs::write(&binary, b"G28\nG1 X1\x1b[2J\x07\n").expect("write");
    let run = cadence(
        &["print", binary.to_str().unwrap(), "--batch", a.to_str().unwrap()],
        TIMEOUT,
    );
    assert_exit(&run, 1);
    assert!(
        !run.stderr.contains('\x1b') && !run.stderr.contains('\x07'),
        "{:?}",
        run.stderr
    );
    assert!(run.stderr.contains("\\x1b"), "{}", run.stderr);
}

#[test]
fn sigint_during_a_heater_wait_ends_the_wait_and_the_print() {
    let dir = scratch("ux-sigint-m109");
    // At --time-scale 1 the built-in hotend needs well over a minute to reach 200 °C.
    let gcode = dir.join("heat.gcode");
    std::fs::write(&gcode, "M109 S200\nG28\nG1 X50 F3000\n").expect("write G-code");
    let mut cmd = Command::new(bin("cadence"));
    cmd.arg("print").arg(&gcode);
    let run = signalled(&mut cmd, Signal::SIGINT, Duration::from_secs(4));
    assert_exit(&run, 130);
    assert!(
        run.stderr
            .contains("cadence: M109 interrupted: the wait ends here"),
        "{}",
        run.stderr
    );
    assert_eq!(interrupted_line(&run, "SIGINT"), 1, "{}", run.stderr);
    assert!(run.stdout.contains("Details:"), "{}", run.stdout);
    assert!(!run.stdout.contains("homing x"), "G28 never ran: {}", run.stdout);
}

#[test]
fn a_live_print_reports_an_unknown_command_and_goes_on() {
    let dir = scratch("ux-unknown");
    let gcode = dir.join("unknown.gcode");
    std::fs::write(&gcode, "FOO_BAR X=1\nM105\n").expect("write G-code");
    let run = cadence(&["print", gcode.to_str().unwrap(), "--no-progress"], TIMEOUT);
    assert_success(&run);
    assert!(
        run.stderr
            .contains("unknown.gcode:1: Unknown command:\"FOO_BAR\""),
        "{}",
        run.stderr
    );
}
