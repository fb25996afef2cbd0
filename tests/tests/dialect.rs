//! Klipper's G-code dialect and the config tools end to end, through the `cadence` binary:
//! unknown commands reported and skipped (strict on request), `[respond]`, `check-config` and
//! `dictionary`.

use std::time::Duration;

use cadence_tests::{cadence, print_batch, scratch, simulated_config as config};

const TIMEOUT: Duration = Duration::from_secs(120);

#[test]
fn slicer_start_code_prints_with_unknown_commands_reported() {
    let dir = scratch("dialect-slicer");
    let g = dir.join("slicer.gcode");
    std::fs::write(
        &g,
        "M73 P0 R10\nM201 X1000 Y1000\nM205 X8 Y8\nM115\nG28\nT0\nM900 K0.04\nG1 X20 Y20 F3000\n\
         M486 S0\nG1 X40 E1\nM201 X500\nM486 S-1\nG1 Y40\n",
    )
    .unwrap();
    let out = dir.join("out.bin");
    let (g_s, out_s) = (g.to_str().unwrap(), out.to_str().unwrap());
    let run = cadence(&["print", g_s, "--batch", out_s], TIMEOUT);
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    for name in ["M73", "M201", "M205", "M115", "T0", "M900", "M486"] {
        let said = format!("Unknown command:\"{name}\"");
        assert_eq!(run.stderr.matches(&said).count(), 1, "{name}: {}", run.stderr);
    }
    assert!(
        run.stderr.contains("slicer.gcode:2: Unknown command:\"M201\""),
        "{}",
        run.stderr
    );
    assert!(run.stdout.contains("moves 3"), "{}", run.stdout);
    let strict = cadence(&["print", g_s, "--batch", out_s, "--strict"], TIMEOUT);
    assert_eq!(strict.code, Some(1), "{}", strict.stderr);
    assert!(
        strict.stderr.contains("line 1: Unknown command:\"M73\""),
        "{}",
        strict.stderr
    );
}

#[test]
fn respond_answers_with_the_section_and_is_unknown_without() {
    let dir = scratch("dialect-respond");
    let g = dir.join("respond.gcode");
    std::fs::write(
        &g,
        "G28\nRESPOND MSG=\"homed, printing\"\nRESPOND TYPE=command MSG=hi\nM118 layer 1\nTELL\n",
    )
    .unwrap();
    let out = dir.join("out.bin");
    let macro_cfg = "[gcode_macro TELL]\ngcode:\n  RESPOND PREFIX=tell: MSG={printer.toolhead.homed_axes}";
    let cfg = config(&dir, &format!("[respond]\n{macro_cfg}"));
    let print = |cfg: &std::path::Path| print_batch(&g, cfg, &out, TIMEOUT);
    let run = print(&cfg);
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    for said in ["echo: homed, printing", "// hi", "echo: layer 1", "tell: xyz"] {
        assert!(run.stderr.contains(said), "{said}: {}", run.stderr);
    }
    // Without [respond], as on Klipper: unknown commands.
    let cfg = config(&dir, macro_cfg);
    let run = print(&cfg);
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    assert!(
        run.stderr.contains("Unknown command:\"RESPOND\""),
        "{}",
        run.stderr
    );
    assert!(run.stderr.contains("Unknown command:\"M118\""), "{}", run.stderr);
    // A bad TYPE stops the print with Klipper's message, naming line and macro.
    std::fs::write(&g, "G28\nRESPOND TYPE=loud MSG=x\n").unwrap();
    let run = print(&config(&dir, "[respond]"));
    assert_eq!(run.code, Some(1), "{}", run.stderr);
    assert!(
        run.stderr
            .contains("respond.gcode:2: RESPOND TYPE 'loud' is invalid"),
        "{}",
        run.stderr
    );
}

#[test]
fn check_config_lists_every_error_and_the_ignored_sections() {
    let dir = scratch("dialect-check");
    let good = config(&dir, "[display_glyph heart]\n[idle_timeout]\ntimeout: 600");
    let run = cadence(&["check-config", good.to_str().unwrap()], TIMEOUT);
    assert_eq!(run.code, Some(0), "{}\n{}", run.stdout, run.stderr);
    assert!(run.stdout.contains("0 errors"), "{}", run.stdout);
    assert!(
        run.stdout
            .contains("ignored (accepted, no effect in Cadence):\n  [display_glyph heart]"),
        "{}",
        run.stdout
    );
    assert!(run.stdout.contains("mcu 'mcu': "), "{}", run.stdout);

    let bad = dir.join("bad.cfg");
    let text = format!(
        "{}\n[dual_carriage]\naxis: x\n[stepper_yy]\n[gcode_arcs]\nresolution: -1\n[neopixel x]\npin: PA9\n",
        sysconfig::printer::SIMULATED_PRINTER_CFG
    );
    std::fs::write(&bad, &text).unwrap();
    let line_of = |needle: &str| text.lines().position(|l| l == needle).unwrap() + 1;
    let run = cadence(&["check-config", bad.to_str().unwrap()], TIMEOUT);
    assert_eq!(run.code, Some(1), "{}\n{}", run.stdout, run.stderr);
    let at = |needle: &str| format!("bad.cfg:{}", line_of(needle));
    assert!(
        run.stdout.contains(&format!(
            "{}: [dual_carriage] is not supported",
            at("[dual_carriage]")
        )),
        "{}",
        run.stdout
    );
    assert!(
        run.stdout
            .contains(&format!("{}: Section 'stepper_yy'", at("[stepper_yy]"))),
        "{}",
        run.stdout
    );
    assert!(
        run.stdout
            .contains(&format!("{}: [gcode_arcs] resolution", at("resolution: -1"))),
        "{}",
        run.stdout
    );
    assert!(run.stdout.contains("3 errors"), "{}", run.stdout);
    assert!(
        run.stdout
            .contains("refused (not supported by Cadence yet):\n  [dual_carriage]"),
        "{}",
        run.stdout
    );
    assert!(run.stdout.contains("[neopixel x]"), "{}", run.stdout);
    assert!(!run.stderr.contains("panicked"), "{}", run.stderr);
}

#[test]
fn dictionary_from_the_simulator_saves_and_reads_back() {
    let dir = scratch("dialect-dict");
    let saved = dir.join("mcu.dict");
    let run = cadence(
        &["dictionary", "--simulator", "--output", saved.to_str().unwrap()],
        TIMEOUT,
    );
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    let run = cadence(&["dictionary", "--file", saved.to_str().unwrap()], TIMEOUT);
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    assert!(run.stdout.contains("CLOCK_FREQ"), "{}", run.stdout);
    assert!(run.stdout.contains("queue_step oid=%c"), "{}", run.stdout);
    // The built-in one is the simulator's, and the saved JSON is what batch mode takes.
    let builtin = cadence(&["dictionary", "--json"], TIMEOUT);
    assert_eq!(builtin.code, Some(0), "{}", builtin.stderr);
    assert_eq!(builtin.stdout, std::fs::read_to_string(&saved).unwrap());
    let g = dir.join("sq.gcode");
    std::fs::write(&g, "G28\nG1 X10 Y10 F3000\n").unwrap();
    let out = dir.join("out.bin");
    let run = cadence(
        &[
            "print",
            g.to_str().unwrap(),
            "--batch",
            out.to_str().unwrap(),
            "--dictionary",
            saved.to_str().unwrap(),
        ],
        TIMEOUT,
    );
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    let run = cadence(&["dictionary", "--serial", "/nonexistent/tty"], TIMEOUT);
    assert_eq!(run.code, Some(1), "{}", run.stderr);
    assert!(run.stderr.contains("/nonexistent/tty"), "{}", run.stderr);
}

#[test]
fn config_tool_arguments_are_clear_errors() {
    for args in [
        &["check-config"][..],
        &["check-config", "/nonexistent/printer.cfg"],
        &["dictionary", "--file", "x.dict", "--simulator"],
        &["dictionary", "--baud", "115200"],
        &["dictionary", "--file", "/nonexistent/x.dict"],
    ] {
        let run = cadence(args, TIMEOUT);
        assert_ne!(run.code, Some(0), "{args:?} succeeded");
        assert!(!run.stderr.contains("panicked"), "{args:?}: {}", run.stderr);
        assert!(
            !(run.stderr.trim().is_empty() && run.stdout.trim().is_empty()),
            "{args:?}: no message"
        );
    }
}

#[test]
fn decode_check_runs_macros_as_the_print_did() {
    let dir = scratch("dialect-decode-macros");
    let macros = "[gcode_macro PRINT_START]\nvariable_lift: 2\ngcode:\n  G28\n  G1 Z{lift} F600\n  \
                  PURGE LEN={params.LEN|default(20)}\n\
                  [gcode_macro PURGE]\ngcode:\n  G1 X10 Y5 F3000\n  G1 X{10 + params.LEN|float} E2\n";
    let cfg = config(&dir, macros);
    let g = dir.join("macros.gcode");
    std::fs::write(&g, "M83\nPRINT_START LEN=30\nG1 X20 Y20 E1\nPURGE\n").unwrap();
    let out = dir.join("out.bin");
    let (g_s, cfg_s, out_s) = (g.to_str().unwrap(), cfg.to_str().unwrap(), out.to_str().unwrap());
    let run = cadence(&["print", g_s, "--config", cfg_s, "--batch", out_s], TIMEOUT);
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    let check = cadence(&["decode", out_s, "--check", g_s, "--config", cfg_s], TIMEOUT);
    assert_eq!(check.code, Some(0), "{}\n{}", check.stdout, check.stderr);
    for stepper in ["stepper_x", "stepper_y", "stepper_z", "extruder"] {
        let line = check.stdout.lines().find(|l| l.trim_start().starts_with(stepper));
        assert!(
            line.is_some_and(|l| l.ends_with(": ok")),
            "{stepper}: {}",
            check.stdout
        );
    }
    // The same G-code without the macros plans less motion: the check refuses the stream.
    let plain = config(&dir, "");
    let plain_s = plain.to_str().unwrap();
    let check = cadence(&["decode", out_s, "--check", g_s, "--config", plain_s], TIMEOUT);
    assert_eq!(check.code, Some(1), "{}\n{}", check.stdout, check.stderr);
}

#[test]
fn exclude_object_drops_an_excluded_objects_moves() {
    let dir = scratch("dialect-exclude");
    let g = dir.join("two.gcode");
    std::fs::write(
        &g,
        "EXCLUDE_OBJECT_DEFINE NAME=a CENTER=15,15 POLYGON=[[10,10],[20,10],[20,20]]\n\
         EXCLUDE_OBJECT_DEFINE NAME=b CENTER=45,45\nEXCLUDE_OBJECT NAME=b\nG28\nM83\n\
         EXCLUDE_OBJECT_START NAME=a\nG1 X10 Y10 F3000\nG1 X20 E1\nEXCLUDE_OBJECT_END NAME=a\n\
         EXCLUDE_OBJECT_START NAME=b\nG1 X40 Y40\nG1 X50 E1\nG1 Y50 E1\nEXCLUDE_OBJECT_END NAME=b\n\
         G1 X0 Y0\n",
    )
    .unwrap();
    let out = dir.join("out.bin");
    let print = |cfg: &std::path::Path| print_batch(&g, cfg, &out, TIMEOUT);
    let run = print(&config(&dir, "[exclude_object]"));
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    assert!(run.stdout.contains("moves 3,"), "{}", run.stdout);
    assert!(!run.stderr.contains("Unknown command"), "{}", run.stderr);
    // Without the section, as on Klipper: unknown commands, every object printed.
    let run = print(&config(&dir, ""));
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    assert!(run.stdout.contains("moves 6,"), "{}", run.stdout);
    assert!(
        run.stderr.contains("Unknown command:\"EXCLUDE_OBJECT_DEFINE\""),
        "{}",
        run.stderr
    );
}
