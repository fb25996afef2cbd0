//! The `cadence` library used directly (no executable): a printer opened on the built-in
//! simulated printer (its MCU a `cadence-mcu` child process on a real pty), homed, fed G-code
//! one command at a time and from a file, stopped from another thread, and closed with every
//! stepper's position read back from the MCU. Also runs the embedding example
//! (`examples/embed.rs`) as built by `cargo test --workspace`.
//!
//! The tests take turns (a lock): each runs a simulated MCU process and real-time threads, and
//! homing's 25 ms trsync budget must not compete with another test's homing on this VM.

use std::sync::Mutex;
use std::time::{Duration, Instant};

use cadence::{Event, Printer, PrinterError, PrinterOptions, PrinterSource, PrinterState};
use cadence_tests::{assert_success, bin, run, workspace};

/// Counts allocations per thread, so the summary's "allocations after warm-up" means something.
#[global_allocator]
static ALLOC: rt_core::alloc_count::CountingAlloc = rt_core::alloc_count::CountingAlloc;

static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

fn turn() -> std::sync::MutexGuard<'static, ()> {
    ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner())
}

fn open() -> Printer {
    let opts = PrinterOptions {
        log_to_stderr: true,
        ..PrinterOptions::default()
    };
    Printer::open(PrinterSource::Simulated, opts).expect("open the simulated printer")
}

#[test]
fn the_embedding_example_runs() {
    let _turn = turn();
    let example = bin("examples/embed");
    let out = run(&mut std::process::Command::new(example), Duration::from_secs(120));
    assert_success(&out);
    for want in [
        "homing x: mcus mcu",
        "status: Ready, toolhead X20.000 Y20.000 Z5.000, homed [true, true, true]",
        "lead margin: min",
        "event: homed 3 axes",
        "event: shut down (closed)",
    ] {
        assert!(out.stdout.contains(want), "missing {want:?} in:\n{}", out.stdout);
    }
    assert!(!out.stdout.contains("MISMATCH"), "{}", out.stdout);
}

#[test]
fn home_stream_and_close_read_the_positions_back() {
    let _turn = turn();
    let mut printer = open();
    let events = printer.events().expect("events");
    let homing = printer.home([true, true, true]).expect("home");
    assert_eq!(homing.axes.len(), 3, "{homing}");
    for a in &homing.axes {
        assert_eq!(a.position, 0.0, "{homing}");
        assert_eq!(a.passes.len(), 2, "{homing}");
    }
    assert_eq!(printer.status().homed, [true, true, true]);

    printer.send_line("G1 X30 Y40 Z2 F6000").expect("send");
    printer.send_line("G1 X35").expect("send");
    printer.wait_moves().expect("wait");
    let status = printer.status();
    assert_eq!(status.state, PrinterState::Ready);
    assert_eq!(&status.position[..3], &[35.0, 40.0, 2.0]);
    assert!(status.print_time >= status.planned_until);
    assert_eq!(status.mcus.len(), 1);
    assert!(status.mcus[0].1.queue.bytes_write > 0);

    // A file on the same timeline.
    printer
        .run_gcode_file(&workspace().join("examples/square.gcode"))
        .expect("file");
    printer.wait_moves().expect("wait");
    let latency = printer.latency();
    assert!(latency.lead_margin.count > 0);
    assert_eq!(latency.lead_margin.negative, 0, "a step message left late");
    assert!(latency.lead_ms(latency.lead_margin.min) >= 100.0);

    let report = printer.close().expect("close");
    let rows = &report.summary.rows;
    assert_eq!(rows.len(), 4);
    for (name, _, mcu, host, _) in rows {
        assert_eq!(mcu, host, "{name}: the MCU's position differs from the host's");
    }
    let states: Vec<PrinterState> = events
        .try_iter()
        .filter_map(|e| match e {
            Event::State(s) => Some(s),
            _ => None,
        })
        .collect();
    assert_eq!(states.first(), Some(&PrinterState::Ready));
    assert!(states.contains(&PrinterState::Printing));
    assert_eq!(
        states.last(),
        Some(&PrinterState::Shutdown {
            reason: "closed".to_string()
        })
    );
}

#[test]
fn a_bad_line_is_refused_and_the_session_goes_on_but_a_refused_command_ends_it() {
    let _turn = turn();
    let printer = open();
    match printer.send_line("G1 X(") {
        Err(PrinterError::Gcode(e)) => assert!(e.to_string().contains("G1 X("), "{e}"),
        other => panic!("expected a G-code error, got {other:?}"),
    }
    printer.send_line("G92 X10").expect("a good line after a bad one");
    printer.wait_moves().expect("still running");
    // An unknown command is reported and skipped, as Klipper does.
    printer.send_line("NO_SUCH_COMMAND").expect("queued");
    printer
        .wait_moves()
        .expect("an unknown command does not end the session");

    printer
        .send_line("SET_VELOCITY_LIMIT VELOCITY=-1")
        .expect("queued");
    match printer.wait_moves() {
        Err(PrinterError::Shutdown { reason }) => {
            assert!(reason.contains("SET_VELOCITY_LIMIT"), "{reason}");
            assert!(
                reason.contains("session: line 3"),
                "the reason names the command: {reason}"
            );
        }
        other => panic!("expected a shutdown, got {other:?}"),
    }
    assert!(matches!(printer.handle().state(), PrinterState::Shutdown { .. }));
    assert!(matches!(
        printer.send_line("G1 X1"),
        Err(PrinterError::Shutdown { .. })
    ));
    let err = printer.close().expect_err("the session failed");
    assert!(err.reason.contains("SET_VELOCITY_LIMIT"), "{}", err.reason);
}

#[test]
fn run_command_fails_a_refused_command_alone_and_the_printer_stays_ready() {
    let _turn = turn();
    let printer = open();
    printer.run_command("G28").expect("home");
    // An unknown command is reported and skipped, as on Klipper: no error.
    printer
        .run_command("NO_SUCH_COMMAND_EITHER")
        .expect("an unknown command is skipped");
    for bad in ["G1 X100000", "G1 X("] {
        match printer.run_command(bad) {
            Err(PrinterError::Command { message }) => assert!(!message.is_empty(), "{bad}"),
            other => panic!("{bad}: expected a command error, got {other:?}"),
        }
        assert!(
            !matches!(printer.handle().state(), PrinterState::Shutdown { .. }),
            "{bad} shut the printer down"
        );
    }
    printer
        .run_command("G1 X10 F3000")
        .expect("a good command after bad ones");
    printer.flush().expect("flush");
    printer.wait_moves().expect("moves run");
    assert_eq!(printer.status().position[0], 10.0);
    printer.close().expect("close");
}

#[test]
fn stop_and_emergency_stop_from_another_thread() {
    let _turn = turn();
    for emergency in [false, true] {
        let printer = open();
        let handle = printer.handle();
        printer.home([true, false, false]).expect("home X");
        // 200 mm at 5 mm/s: 40 s of motion, stopped long before its end.
        printer.send_line("G1 X200 F300").expect("send");
        let stopper = std::thread::spawn(move || {
            let deadline = Instant::now() + Duration::from_secs(30);
            while handle.state() != PrinterState::Printing && Instant::now() < deadline {
                std::thread::sleep(Duration::from_millis(10));
            }
            std::thread::sleep(Duration::from_millis(500));
            if emergency {
                handle.emergency_stop();
            } else {
                handle.stop();
            }
            handle
        });
        let waited = printer.wait_moves();
        let handle = stopper.join().expect("stopper thread");
        let reason = match waited {
            Err(PrinterError::Shutdown { reason }) => reason,
            other => panic!("expected a shutdown, got {other:?}"),
        };
        let want = if emergency {
            "emergency stop"
        } else {
            "stopped by the host"
        };
        assert!(reason.contains(want), "{reason}");
        assert_eq!(
            handle.state(),
            PrinterState::Shutdown {
                reason: reason.clone()
            }
        );
        let err = printer.close().expect_err("a stopped session fails");
        assert!(err.reason.contains(want), "{}", err.reason);
        if emergency {
            let mcu = &err.link_stats;
            assert_eq!(mcu.len(), 1, "the link statistics come back anyway");
        }
    }
}

#[test]
fn open_errors_say_what_and_where() {
    use cadence::printer::OpenError;
    let missing = workspace().join("no-such-printer.cfg");
    match Printer::open(PrinterSource::ConfigFile(missing), PrinterOptions::default()) {
        Err(OpenError::Config(e)) => assert!(e.to_string().contains("no-such-printer.cfg"), "{e}"),
        other => panic!("expected a config error, got {other:?}"),
    }
    let opts = PrinterOptions {
        time_scale: Some(500.0),
        ..PrinterOptions::default()
    };
    match Printer::open(PrinterSource::Simulated, opts) {
        Err(
            e @ OpenError::Option {
                what: "time_scale", ..
            },
        ) => {
            assert!(e.to_string().contains("(0, 50]"), "{e}")
        }
        other => panic!("expected an option error, got {other:?}"),
    }
}

/// A mesh calibrated or a profile saved or removed is pending for SAVE_CONFIG at once (the
/// `configfile.save_config_pending` of Klipper's status), not only when SAVE_CONFIG runs.
#[test]
fn a_bed_mesh_profile_is_pending_for_save_config_as_soon_as_it_is_made() {
    use sysconfig::autosave::SectionChange;
    let _turn = turn();
    let dir = cadence_tests::scratch("library-mesh-pending");
    let text = std::fs::read_to_string(workspace().join("examples/simulated-probe.cfg")).expect("example");
    let text = text
        .replace("[mcu probe_mcu]\nserial: simulator\n", "")
        .replace("pin: ^probe_mcu:PA4", "pin: ^PA4")
        .replace("bed_surface_z: 0", "bed_surface_z: 0\nbed_tilt_x: 0.01");
    let cfg = dir.join("printer.cfg");
    std::fs::write(
        &cfg,
        format!("{text}\n[bed_mesh]\nmesh_min: 10, 10\nmesh_max: 30, 30\nprobe_count: 3, 3\nhorizontal_move_z: 3\n"),
    )
    .expect("write config");
    let opts = PrinterOptions {
        log_to_stderr: true,
        ..PrinterOptions::default()
    };
    let printer = Printer::open(PrinterSource::ConfigFile(cfg), opts).expect("open");
    let pending =
        |p: &Printer| -> Vec<(String, SectionChange)> { p.status().save_config_pending.items().to_vec() };
    assert!(pending(&printer).is_empty());
    printer.home([true, true, true]).expect("home");
    printer.run_command("BED_MESH_CALIBRATE").expect("calibrate");
    let after = pending(&printer);
    assert_eq!(after.len(), 1, "{after:?}");
    assert_eq!(after[0].0, "bed_mesh default");
    let SectionChange::Set(opts) = &after[0].1 else {
        panic!("{after:?}");
    };
    assert!(opts.iter().any(|(k, _)| k == "points"), "{opts:?}");
    printer.run_command("BED_MESH_PROFILE SAVE=copy").expect("save");
    printer
        .run_command("BED_MESH_PROFILE REMOVE=default")
        .expect("remove");
    let after = pending(&printer);
    let names: Vec<(&str, bool)> = after
        .iter()
        .map(|(s, c)| (s.as_str(), matches!(c, SectionChange::Remove)))
        .collect();
    assert_eq!(
        names,
        [("bed_mesh copy", false), ("bed_mesh default", true)],
        "{after:?}"
    );
    printer.close().expect("close");
}
