//! Klipper's host-side G-code objects end to end: `[save_variables]` (the file Klipper writes),
//! `[display_status]` (M73, SET_DISPLAY_TEXT, M117 in templates), `[force_move]`
//! (SET_KINEMATIC_POSITION), SAVE_GCODE_STATE / RESTORE_GCODE_STATE and `[delayed_gcode]` in a
//! batch print; `[delayed_gcode]` and `[idle_timeout]` on a live session's timeline through the
//! library.

use std::time::{Duration, Instant};

use cadence::{Event, Printer, PrinterOptions, PrinterSource};
use cadence_tests::{print_batch, scratch, simulated_config as config};

const TIMEOUT: Duration = Duration::from_secs(120);

#[test]
fn host_objects_in_a_batch_print() {
    let dir = scratch("dialect-host-batch");
    let vars = dir.join("vars.cfg");
    let cfg = config(
        &dir,
        &format!(
            "[save_variables]\nfilename: {}\n[display_status]\n[force_move]\nenable_force_move: True\n\
             [delayed_gcode later]\ngcode:\n  {{action_respond_info(\"later ran\")}}\n  G1 X30\n\
             [gcode_macro REPORT]\ngcode:\n  {{action_respond_info(\"progress \" ~ printer.display_status.progress \
             ~ \" msg \" ~ printer.display_status.message ~ \" count \" ~ printer.save_variables.variables.count)}}\n",
            vars.display()
        ),
    );
    // A value saved by an earlier print is read back.
    std::fs::write(&vars, "[Variables]\nold = 'kept'\n").unwrap();
    let g = dir.join("host.gcode");
    std::fs::write(
        &g,
        "G28\nSET_KINEMATIC_POSITION X=5 Y=5 Z=5\nM73 P25\nSET_DISPLAY_TEXT MSG=\"hello\"\n\
         SAVE_VARIABLE VARIABLE=count VALUE=3\nREPORT\nSAVE_GCODE_STATE NAME=s\nG91\nG1 X10 F6000\n\
         RESTORE_GCODE_STATE NAME=s MOVE=1\nUPDATE_DELAYED_GCODE ID=later DURATION=0.5\n\
         SET_IDLE_TIMEOUT TIMEOUT=30\nG1 X50 F600\nG1 X60\nM117 done\nREPORT\n",
    )
    .unwrap();
    let out = dir.join("out.bin");
    let run = print_batch(&g, &cfg, &out, TIMEOUT);
    assert_eq!(run.code, Some(0), "{}\n{}", run.stdout, run.stderr);
    for said in [
        "REPORT: progress 0.25 msg hello count 3",
        "idle_timeout: Timeout set to 30.00 s",
        "REPORT: progress 0.25 msg done count 3",
        "delayed_gcode later: later ran",
    ] {
        assert!(run.stderr.contains(said), "{said}: {}", run.stderr);
    }
    assert!(!run.stderr.contains("Unknown command"), "{}", run.stderr);
    assert_eq!(
        std::fs::read_to_string(&vars).unwrap(),
        "[Variables]\ncount = 3\nold = 'kept'\n\n"
    );
    // X from 5 (SET_KINEMATIC_POSITION): +10, back to 5, to 50, to 60, and the timer's 30:
    // 105 mm at 80 steps/mm, and no step for the position set without moving.
    assert!(run.stdout.contains("moves 5"), "{}", run.stdout);
    assert!(run.stdout.contains("stepper_x  8400 steps"), "{}", run.stdout);
}

#[test]
fn delayed_gcode_and_idle_timeout_run_on_a_quiet_session() {
    let dir = scratch("dialect-host-session");
    let cfg = config(
        &dir,
        "[delayed_gcode tick]\ninitial_duration: 0.3\ngcode:\n  {action_respond_info(\"tick \" ~ printer.idle_timeout.state)}\n\
         [idle_timeout]\ntimeout: 600\ngcode:\n  {action_respond_info(\"idle timeout ran\")}\n  M84\n",
    );
    let opts = PrinterOptions {
        log_to_stderr: true,
        ..PrinterOptions::default()
    };
    let mut printer = Printer::open(PrinterSource::ConfigFile(cfg), opts).expect("open");
    let events = printer.events().expect("events");
    // No motion (a busy VM must not make this a test of the lead): one command, then quiet.
    printer
        .run_command("SET_IDLE_TIMEOUT TIMEOUT=1")
        .expect("a command");
    let deadline = Instant::now() + Duration::from_secs(60);
    let mut said = Vec::new();
    while Instant::now() < deadline && !said.iter().any(|s: &String| s.contains("idle timeout ran")) {
        match events.recv_timeout(Duration::from_millis(200)) {
            Ok(Event::Warning(w)) => said.push(w),
            Ok(other) => said.push(format!("{other:?}")),
            Err(_) => {}
        }
    }
    let at = |want: &str| said.iter().position(|s| s.contains(want));
    assert!(at("idle_timeout: Timeout set to 1.00 s").is_some(), "{said:?}");
    assert!(
        at("tick Printing").is_some() || at("tick Ready").is_some(),
        "{said:?}"
    );
    assert!(at("idle timeout ran").is_some(), "{said:?}");
    printer.close().expect("close");
}
