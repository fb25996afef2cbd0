//! End to end: `cadence print` drives the simulated MCU process over a real pty; the MCU's
//! step trace proves what happened on the pins.

use std::time::Duration;

use cadence_tests::{assert_success, cadence, check_trace, scratch, workspace};

const TIMEOUT: Duration = Duration::from_secs(120);

#[test]
fn square_prints_exactly_on_the_simulated_mcu() {
    let dir = scratch("square");
    let trace = dir.join("square.trace");
    let gcode = workspace().join("examples/square.gcode");
    let run = cadence(
        &[
            "print",
            gcode.to_str().unwrap(),
            "--trace",
            trace.to_str().unwrap(),
        ],
        TIMEOUT,
    );
    assert_success(&run);
    assert!(
        run.stdout.contains("min lead margin"),
        "summary missing:\n{}",
        run.stdout
    );

    let cfg = sysconfig::printer::builtin_simulated().expect("built-in printer");
    let check = check_trace(&trace);
    assert!(check.queue_steps > 0, "no queue_step was received");
    assert!(
        check.min_lead_ms >= 100.0,
        "a queue_step arrived with only {:.2} ms lead",
        check.min_lead_ms
    );
    let net = &check.net;

    // G28 homes for real: the simulated carriages start 10% of their travel away from their
    // endstops (src/hardware.rs), so the net steps of each axis take it from there to the final
    // position of examples/square.gcode (X10 Y10 Z5); the extruder is not homed.
    let start = |axis: &str| {
        let s = cfg.steppers.iter().find(|s| s.name == axis).unwrap();
        s.position_endstop.unwrap_or(0.0) + 0.1 * (s.position_max - s.position_min)
    };
    let step_dist = |axis: &str| cfg.steppers.iter().find(|s| s.name == axis).unwrap().step_dist();
    let e_dist = cfg.extruder.as_ref().expect("extruder").step_dist();
    let expected = [
        (0u8, (10.0 - start("stepper_x")) / step_dist("stepper_x")),
        (1, (10.0 - start("stepper_y")) / step_dist("stepper_y")),
        (2, (5.0 - start("stepper_z")) / step_dist("stepper_z")),
        (3, (4.0 + 4.0 - 0.8) / e_dist),
    ];
    for (oid, want) in expected {
        let got = net.get(&oid).copied().unwrap_or(0) as f64;
        // ±1 step of rounding, ±1 of endstop sampling.
        assert!(
            (got - want).abs() <= 2.0,
            "oid {oid}: {got} net steps, commanded {want:.2}"
        );
    }
    assert!(
        run.stdout.contains("homing z"),
        "no homing report:\n{}",
        run.stdout
    );
}

#[test]
fn missing_gcode_file_is_a_clear_error() {
    let run = cadence(&["print", "/nonexistent/x.gcode"], TIMEOUT);
    assert_eq!(run.code, Some(1));
    assert!(run.stderr.contains("/nonexistent/x.gcode"), "{}", run.stderr);
    assert!(!run.stderr.contains("panicked"), "{}", run.stderr);
}

#[test]
fn bad_gcode_line_names_line_and_text() {
    let dir = scratch("badline");
    let g = dir.join("bad.gcode");
    std::fs::write(&g, "G28\nG1 X10 F3000\nG1 X1..2\n").unwrap();
    let out = dir.join("out.bin");
    let run = cadence(
        &["print", g.to_str().unwrap(), "--batch", out.to_str().unwrap()],
        TIMEOUT,
    );
    assert_eq!(run.code, Some(1), "{}", run.stderr);
    assert!(
        run.stderr.contains(":3") || run.stderr.contains("line 3"),
        "{}",
        run.stderr
    );
    assert!(run.stderr.contains("X1..2"), "{}", run.stderr);
    assert!(!run.stderr.contains("panicked"), "{}", run.stderr);
}

#[test]
fn unknown_command_is_reported_and_skipped_unless_strict() {
    let dir = scratch("unknown");
    let g = dir.join("unknown.gcode");
    std::fs::write(
        &g,
        "G28\nG1 X10 F3000\nM73 P10 R5\nFOO_BAR A=1\nG1 X20\nFOO_BAR\n",
    )
    .unwrap();
    let out = dir.join("out.bin");
    let print = |extra: &[&str]| {
        let mut args = vec!["print", g.to_str().unwrap(), "--batch", out.to_str().unwrap()];
        args.extend_from_slice(extra);
        cadence(&args, TIMEOUT)
    };
    // Default, as Klipper: `Unknown command:"FOO_BAR"` once per name, the moves all made.
    let run = print(&[]);
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    assert_eq!(
        run.stderr.matches("Unknown command:\"FOO_BAR\"").count(),
        1,
        "{}",
        run.stderr
    );
    assert!(run.stderr.contains("unknown.gcode:4"), "{}", run.stderr);
    assert!(run.stdout.contains("moves 2"), "{}", run.stdout);

    // --strict: an error naming the file, the line and the command.
    let run = print(&["--strict"]);
    assert_eq!(run.code, Some(1), "{}", run.stderr);
    assert!(
        run.stderr
            .contains("unknown.gcode: line 3: Unknown command:\"M73\""),
        "{}",
        run.stderr
    );
    assert!(!run.stderr.contains("panicked"), "{}", run.stderr);

    // `[gcode] unknown_commands: error` is the same strict mode.
    let cfg = dir.join("printer.cfg");
    let text = format!(
        "{}\n[gcode]\nunknown_commands: error\n",
        sysconfig::printer::SIMULATED_PRINTER_CFG
    );
    std::fs::write(&cfg, text).unwrap();
    let run = print(&["--config", cfg.to_str().unwrap()]);
    assert_eq!(run.code, Some(1), "{}", run.stderr);
    assert!(run.stderr.contains("line 3"), "{}", run.stderr);
}

#[test]
fn decode_check_proves_a_batch_stream_and_refuses_other_motion() {
    let dir = scratch("check");
    let g = workspace().join("examples/square.gcode");
    let cfg = workspace().join("examples/simulated-toolboard.cfg");
    let out = dir.join("square.bin");
    let (g_s, cfg_s, out_s) = (g.to_str().unwrap(), cfg.to_str().unwrap(), out.to_str().unwrap());
    // Steppers on two MCUs: one stream each (X, Y on `mcu`; Z, E on `toolboard`).
    let run = cadence(&["print", g_s, "--config", cfg_s, "--batch", out_s], TIMEOUT);
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    let board = dir.join("square-toolboard.bin");
    for (stream, mcu, names) in [
        (&out, "mcu", ["stepper_x", "stepper_y"]),
        (&board, "toolboard", ["stepper_z", "extruder"]),
    ] {
        let run = cadence(
            &[
                "decode",
                stream.to_str().unwrap(),
                "--check",
                g_s,
                "--config",
                cfg_s,
                "--mcu",
                mcu,
            ],
            TIMEOUT,
        );
        assert_eq!(run.code, Some(0), "{}", run.stderr);
        for name in names {
            assert!(
                run.stdout
                    .lines()
                    .any(|l| l.contains(name) && l.ends_with(": ok")),
                "{name}:\n{}",
                run.stdout
            );
        }
    }
    // Other motion: Y's steps no longer match.
    let moved = dir.join("moved.gcode");
    let text = std::fs::read_to_string(&g).unwrap();
    assert!(
        text.contains("G1 X10 Y10 Z5"),
        "examples/square.gcode changed shape"
    );
    std::fs::write(&moved, text.replace("G1 X10 Y10 Z5", "G1 X10 Y11 Z5")).unwrap();
    let run = cadence(
        &[
            "decode",
            out_s,
            "--check",
            moved.to_str().unwrap(),
            "--config",
            cfg_s,
        ],
        TIMEOUT,
    );
    assert_eq!(run.code, Some(1), "{}", run.stdout);
    assert!(run.stderr.contains("stepper_y: step "), "{}", run.stderr);
    // A tighter bound than the stream was compressed with.
    let run = cadence(
        &[
            "decode",
            out_s,
            "--check",
            g_s,
            "--config",
            cfg_s,
            "--max-error-us",
            "10",
        ],
        TIMEOUT,
    );
    assert_eq!(run.code, Some(1), "{}", run.stdout);
    assert!(run.stderr.contains("(max 500)"), "{}", run.stderr);
    assert!(!run.stderr.contains("panicked"), "{}", run.stderr);
}

#[test]
fn heaters_fan_and_display_are_recorded_in_the_summary() {
    let dir = scratch("accessories");
    let g = dir.join("acc.gcode");
    std::fs::write(
        &g,
        "M140 S60\nM109 S215\nG28\nM106 S255\nG1 X10 Y10 F3000\nM117 Layer 1\nM114\nM107\n",
    )
    .unwrap();
    let out = dir.join("out.bin");
    let run = cadence(
        &["print", g.to_str().unwrap(), "--batch", out.to_str().unwrap()],
        TIMEOUT,
    );
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    for want in [
        "heaters (G-code): extruder last target 215 °C (1 commands, 1 waits), \
         heater_bed last target 60 °C (1 commands, 0 waits)",
        "part fan (G-code): 2 changes, last 0 %",
        "M117 (line 6): Layer 1",
        "M114 (line 7): X:10.000 Y:10.000 Z:0.000 E:0.000",
    ] {
        assert!(run.stdout.contains(want), "{want}:\n{}", run.stdout);
    }
}

#[test]
fn config_error_names_section_and_option() {
    let dir = scratch("badcfg");
    let cfg = dir.join("printer.cfg");
    let text =
        sysconfig::printer::SIMULATED_PRINTER_CFG.replace("rotation_distance: 40", "rotation_distance: -40");
    assert_ne!(
        text,
        sysconfig::printer::SIMULATED_PRINTER_CFG,
        "example config changed shape"
    );
    std::fs::write(&cfg, text).unwrap();
    let g = workspace().join("examples/square.gcode");
    let run = cadence(
        &["print", g.to_str().unwrap(), "--config", cfg.to_str().unwrap()],
        TIMEOUT,
    );
    assert_eq!(run.code, Some(1), "{}", run.stderr);
    assert!(run.stderr.contains("rotation_distance"), "{}", run.stderr);
    assert!(run.stderr.contains("stepper_"), "{}", run.stderr);
}

#[test]
fn batch_then_decode_round_trip() {
    let dir = scratch("batch");
    let out = dir.join("square.bin");
    let g = workspace().join("examples/square.gcode");
    let run = cadence(
        &["print", g.to_str().unwrap(), "--batch", out.to_str().unwrap()],
        TIMEOUT,
    );
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    let run = cadence(&["decode", out.to_str().unwrap()], TIMEOUT);
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    let lines: Vec<&str> = run.stdout.lines().collect();
    assert!(
        lines.first().is_some_and(|l| l.starts_with("allocate_oids")),
        "{:?}",
        lines.first()
    );
    assert!(lines.iter().any(|l| l.starts_with("config_stepper oid=3")));
    assert!(lines.iter().any(|l| l.starts_with("finalize_config")));
    assert!(lines.iter().filter(|l| l.starts_with("queue_step")).count() > 10);
}

#[test]
fn time_scaled_print_keeps_the_lead_in_mcu_time() {
    let dir = scratch("scaled");
    let trace = dir.join("scaled.trace");
    let gcode = workspace().join("examples/square.gcode");
    let run = cadence(
        &[
            "print",
            gcode.to_str().unwrap(),
            "--time-scale",
            "5",
            "--trace",
            trace.to_str().unwrap(),
        ],
        TIMEOUT,
    );
    assert_success(&run);
    let check = check_trace(&trace);
    assert_eq!(check.time_scale, 5.0);
    assert!(
        check.min_lead_ms >= 100.0,
        "{:.2} ms lead (MCU time)",
        check.min_lead_ms
    );
    let steps = check.steps;
    assert!(steps > 1000, "{steps} steps");
}

#[test]
fn batch_with_an_explicit_dictionary_matches_the_default() {
    let dir = scratch("dict");
    let dict = dir.join("mcu.dict");
    std::fs::write(&dict, firmware::dictionary_bytes(50_000_000)).unwrap();
    let g = workspace().join("examples/square.gcode");
    let a = dir.join("a.bin");
    let b = dir.join("b.bin");
    let run = cadence(
        &["print", g.to_str().unwrap(), "--batch", a.to_str().unwrap()],
        TIMEOUT,
    );
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    let run = cadence(
        &[
            "print",
            g.to_str().unwrap(),
            "--batch",
            b.to_str().unwrap(),
            "--dictionary",
            dict.to_str().unwrap(),
        ],
        TIMEOUT,
    );
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    // A dictionary that is not one is refused clearly.
    std::fs::write(&dict, b"not zlib").unwrap();
    let run = cadence(
        &[
            "print",
            g.to_str().unwrap(),
            "--batch",
            b.to_str().unwrap(),
            "--dictionary",
            dict.to_str().unwrap(),
        ],
        TIMEOUT,
    );
    assert_eq!(run.code, Some(1));
    assert!(run.stderr.contains("mcu.dict"), "{}", run.stderr);
}
