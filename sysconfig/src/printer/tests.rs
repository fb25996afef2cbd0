//! Whole-config tests: the built-in printer, cross-section rules, warnings, and the error forms
//! that only appear when sections meet.

use super::*;
use proptest::prelude::*;
use std::io;

const MINIMAL: &str = "[mcu]\nserial: /dev/ttyACM0\n\
    [printer]\nkinematics: cartesian\nmax_velocity: 300\nmax_accel: 3000\n\
    [stepper_x]\nstep_pin: PA0\ndir_pin: PA1\nmicrosteps: 16\nrotation_distance: 40\nposition_max: 200\n\
    [stepper_y]\nstep_pin: PB0\ndir_pin: PB1\nmicrosteps: 16\nrotation_distance: 40\nposition_max: 200\n\
    [stepper_z]\nstep_pin: PC0\ndir_pin: PC1\nmicrosteps: 16\nrotation_distance: 8\nposition_max: 200\n";

fn parse(text: &str) -> Result<PrinterConfig, String> {
    parse_str(text, Path::new("printer.cfg")).map_err(|e| e.to_string())
}

fn ok(text: &str) -> PrinterConfig {
    parse(text).unwrap_or_else(|e| panic!("{e}"))
}

#[test]
fn builtin_simulated_printer_loads() {
    let cfg = builtin_simulated().unwrap_or_else(|e| panic!("{e}"));
    assert!(cfg.warnings.is_empty(), "{:?}", cfg.warnings);
    assert_eq!(cfg.source, PathBuf::from(SIMULATED_PRINTER_NAME));
    assert_eq!(cfg.printer.kinematics, Kinematics::Cartesian);
    assert_eq!((cfg.printer.max_velocity, cfg.printer.max_accel), (300.0, 3000.0));
    let names: Vec<_> = cfg.steppers.iter().map(|s| s.name.as_str()).collect();
    assert_eq!(names, ["stepper_x", "stepper_y", "stepper_z"]);
    let dist = |n: &str| cfg.stepper(n).map(StepperSection::step_dist);
    assert_eq!(dist("stepper_x"), Some(1.0 / 80.0));
    assert_eq!(dist("stepper_y"), Some(1.0 / 80.0));
    assert_eq!(dist("stepper_z"), Some(1.0 / 400.0));
    let e = cfg.extruder.as_ref().unwrap_or_else(|| panic!("no extruder"));
    assert!((1.0 / e.step_dist() - 95.52).abs() < 0.01);
    for s in &cfg.steppers {
        assert_eq!(
            (s.position_min, s.position_endstop, s.homing_positive_dir),
            (0.0, Some(0.0), false),
            "{}",
            s.name
        );
    }
    assert_eq!((cfg.stepper("stepper_x").map(|s| s.position_max)), Some(220.0));
    assert_eq!((cfg.stepper("stepper_z").map(|s| s.position_max)), Some(200.0));
    assert_eq!(cfg.mcus.len(), 1);
    assert!(cfg.mcus[0].is_simulated() && cfg.mcus[0].name == "mcu");
    assert_eq!(
        cfg.simulator,
        SimulatorSection {
            clock_freq: 50_000_000,
            time_scale: 1.0,
            bed_surface_z: 0.0,
            bed_tilt: [0.0, 0.0],
            bed_warp: 0.0,
            bed_warp_period: 100.0,
            gantry_tilt: Vec::new(),
            z_endstop_offsets: Vec::new(),
        }
    );
    // Every pin is one the simulated MCU has.
    let mut all: Vec<&PinRef> = Vec::new();
    for s in &cfg.steppers {
        all.extend([&s.motor.step_pin, &s.motor.dir_pin]);
        all.extend(s.motor.enable_pin.iter().chain(s.endstop_pin.iter()));
    }
    all.extend([
        &e.motor.step_pin,
        &e.motor.dir_pin,
        &e.heater.heater_pin,
        &e.heater.sensor_pin,
    ]);
    all.extend(e.motor.enable_pin.iter());
    assert_eq!(all.len(), 17);
    assert!(
        all.iter().all(|p| p.on_main_mcu() && is_simulator_pin(&p.pin)),
        "{all:?}"
    );
    assert!(
        SIMULATED_PRINTER_CFG.starts_with("# "),
        "the example opens with comments saying what it is"
    );
}

#[test]
fn minimal_config_defaults() {
    let cfg = ok(MINIMAL);
    assert!(cfg.extruder.is_none() && cfg.heater_bed.is_none() && cfg.warnings.is_empty());
    assert_eq!(cfg.simulator, SimulatorSection::default());
    assert_eq!(cfg.mcus[0].baud, 250_000);
    assert_eq!(cfg.stepper("stepper_x").and_then(|s| s.endstop_pin.clone()), None);
}

#[test]
fn kinematics_decides_which_steppers_are_read() {
    let corexy = ok(&MINIMAL.replace("kinematics: cartesian", "kinematics: corexy"));
    assert_eq!(corexy.printer.kinematics, Kinematics::CoreXY);
    assert_eq!(corexy.steppers.len(), 3);
    let without_z = MINIMAL.split("[stepper_z]").next().unwrap_or_default();
    assert_eq!(
        parse(without_z).map(|_| ()),
        Err("printer.cfg: Section 'stepper_z' must be specified (kinematics: cartesian)".to_string())
    );
    assert_eq!(
        parse(&MINIMAL.replace("kinematics: cartesian", "kinematics: none")).map(|_| ()),
        Err("printer.cfg:7: Section 'stepper_x' is not a valid config section".to_string())
    );
    let none = ok("[mcu]\nserial: x\n[printer]\nkinematics: none\nmax_velocity: 1\nmax_accel: 1\n");
    assert!(none.steppers.is_empty());
}

#[test]
fn missing_sections() {
    assert_eq!(
        parse("[printer]\n").map(|_| ()),
        Err("printer.cfg: Section 'mcu' must be specified".to_string())
    );
    assert_eq!(
        parse("[mcu]\nserial: x\n").map(|_| ()),
        Err("printer.cfg: Section 'printer' must be specified".to_string())
    );
}

#[test]
fn board_pins_aliases_resolve_before_pins_are_checked() {
    let aliased = MINIMAL
        .replace("step_pin: PC0", "step_pin: EXP1_1")
        .replace("dir_pin: PC1", "dir_pin: !EXP1_2");
    let cfg = ok(&format!(
        "{aliased}[board_pins]\naliases:\n  # EXP1\n  EXP1_1=PB5, EXP1_2=PA8,\n  EXP1_9=<GND>\n"
    ));
    let z = cfg.stepper("stepper_z").unwrap();
    assert_eq!(
        (
            z.motor.step_pin.pin.as_str(),
            z.motor.dir_pin.pin.as_str(),
            z.motor.dir_pin.invert
        ),
        ("PB5", "PA8", true)
    );
    let reserved = MINIMAL.replace("step_pin: PC0", "step_pin: EXP1_9");
    assert_eq!(
        parse(&format!("{reserved}[board_pins]\naliases: EXP1_9=<GND>\n")).map(|_| ()),
        Err(
            "printer.cfg:20: [stepper_z] step_pin: pin 'EXP1_9' is the board's reserved <GND>, not a pin"
                .to_string()
        )
    );
    // An alias and the pin it names are one pin.
    let twice = MINIMAL
        .replace("step_pin: PC0", "step_pin: EXP1_1")
        .replace("dir_pin: PC1", "dir_pin: PB5");
    let err = parse(&format!("{twice}[board_pins]\naliases: EXP1_1=PB5\n")).unwrap_err();
    assert!(err.contains("dir_pin") && err.contains("PB5"), "{err}");
    assert!(parse(&format!("{MINIMAL}[board_pins]\naliases: EXP1_1\n"))
        .unwrap_err()
        .contains("is not NAME=PIN"));
}

#[test]
fn pins_of_unsupported_providers_name_the_feature() {
    let tmc = MINIMAL.replace("rotation_distance: 40\nposition_max: 200\n[stepper_y]", "rotation_distance: 40\nposition_max: 200\nendstop_pin: tmc2209_stepper_x:virtual_endstop\nposition_endstop: 0\n[stepper_y]");
    let err = parse(&format!(
        "{tmc}[tmc2209 stepper_x]\nuart_pin: PD1\nrun_current: 0.5\n"
    ))
    .unwrap_err();
    assert_eq!(
        err,
        "printer.cfg:27: [tmc2209 stepper_x] tmc virtual endstop requires diag pin config (diag_pin)"
    );
    let scaled = MINIMAL.replace("step_pin: PC0", "step_pin: vref_scaled:PC0");
    let err = parse(&format!(
        "{scaled}[adc_scaled vref_scaled]\nvref_pin: PA5\nvssa_pin: PA6\n"
    ))
    .unwrap_err();
    assert_eq!(
        err,
        "printer.cfg:20: [stepper_z] step_pin: pin 'vref_scaled:PC0': adc_scaled only supports adc pins"
    );
    let cape = MINIMAL.replace("step_pin: PC0", "step_pin: replicape:stepper_z_step");
    let err = parse(&format!("{cape}[replicape]\n")).unwrap_err();
    assert_eq!(
        err,
        "printer.cfg:20: [stepper_z] step_pin: pin 'replicape:stepper_z_step' is on [replicape], whose pins \
         Cadence does not support yet"
    );
}

#[test]
fn unknown_sections_and_options_are_errors_ignored_ones_warnings() {
    assert_eq!(
        parse(&format!("{MINIMAL}[frobnicator]\n")).map(|_| ()),
        Err("printer.cfg:25: Section 'frobnicator' is not a valid config section".to_string())
    );
    assert_eq!(
        parse(&format!("{MINIMAL}[extruder10]\nstep_pin: PD0\n")).map(|_| ()),
        Err(
            "printer.cfg:25: [extruder10] is not supported by Cadence yet (more than 10 extruders)"
                .to_string()
        )
    );
    // A refused section is the first error, before the pins that depend on it.
    assert_eq!(
        parse(&format!(
            "{}[load_cell_probe]\npin: PD0\n",
            MINIMAL.replace(
                "rotation_distance: 8\n",
                "rotation_distance: 8\nendstop_pin: probe:z_virtual_endstop\n"
            )
        ))
        .map(|_| ()),
        Err(
            "printer.cfg:26: [load_cell_probe] is not supported by Cadence yet (load cell probe)".to_string()
        )
    );
    assert_eq!(
        parse(&MINIMAL.replace(
            "position_max: 200\n[stepper_y]",
            "position_max: 200\nfoo: 1\n[stepper_y]"
        ))
        .map(|_| ()),
        Err("printer.cfg:13: Option 'foo' is not valid in section 'stepper_x'".to_string())
    );
    let cfg = ok(&format!(
        "{MINIMAL}[gcode_macro START]\ngcode:\n  G28\n[led status]\nred_pin: PA5\n[gcode_macro END]\ngcode: M84\n"
    ));
    assert_eq!(
        cfg.warnings,
        ["printer.cfg:28: [led] is not implemented by Cadence yet; section ignored",]
    );
    let names: Vec<&str> = cfg.macros.iter().map(|m| m.name.as_str()).collect();
    assert_eq!(names, ["START", "END"]);
}

#[test]
fn gcode_macros_are_read_and_their_templates_checked() {
    let cfg = ok(&format!(
        "{MINIMAL}[gcode_macro start_print]\ndescription: Start\nvariable_bed: 60\nvariable_Name: 'x'\n\
         rename_existing: sp_old\ngcode:\n  M190 S{{params.BED|default(bed)}}\n  G28\n"
    ));
    let m = &cfg.macros[0];
    assert_eq!(
        (
            m.name.as_str(),
            m.description.as_deref(),
            m.rename_existing.as_deref()
        ),
        ("START_PRINT", Some("Start"), Some("SP_OLD"))
    );
    assert_eq!(
        m.variables,
        [
            ("bed".to_string(), "60".to_string()),
            ("name".to_string(), "'x'".to_string())
        ]
    );
    assert_eq!(m.gcode, "\nM190 S{params.BED|default(bed)}\nG28");
    let bad = parse(&format!("{MINIMAL}[gcode_macro X]\ngcode: {{% if %}}\n")).unwrap_err();
    assert!(
        bad.starts_with("printer.cfg:25: [gcode_macro X] gcode: "),
        "{bad}"
    );
    let bad = parse(&format!(
        "{MINIMAL}[gcode_macro X]\nvariable_v: oops\ngcode: G28\n"
    ))
    .unwrap_err();
    assert!(
        bad.starts_with("printer.cfg:25: [gcode_macro X] variable_v: 'oops' is not a literal"),
        "{bad}"
    );
    assert_eq!(
        parse(&format!("{MINIMAL}[gcode_macro X]\ndescription: no gcode\n")).map(|_| ()),
        Err("printer.cfg:25: Option 'gcode' in section 'gcode_macro X' must be specified".to_string())
    );
}

#[test]
fn simulator_section_without_simulated_mcu_warns() {
    let cfg = ok(&format!("{MINIMAL}[simulator]\nclock_freq: 16000000\n"));
    assert_eq!(cfg.simulator.clock_freq, 16_000_000);
    assert_eq!(
        cfg.warnings,
        ["printer.cfg:25: [simulator] has no effect: no [mcu] has 'serial: simulator'"]
    );
    assert_eq!(
        parse(&format!("{MINIMAL}[simulator]\ntime_scale: 0\n")).map(|_| ()),
        Err("printer.cfg:26: [simulator] time_scale: must be above 0, got 0".to_string())
    );
}

#[test]
fn pins_across_sections_and_mcus() {
    let text = MINIMAL
        .replace("step_pin: PC0", "step_pin: ebb:PC0")
        .replace("dir_pin: PC1", "dir_pin: ebb:PC1")
        + "[mcu ebb]\nserial: /dev/ttyACM1\n";
    let cfg = ok(&text);
    assert_eq!(
        cfg.mcus.iter().map(|m| m.name.as_str()).collect::<Vec<_>>(),
        ["mcu", "ebb"]
    );
    assert_eq!(
        cfg.stepper("stepper_z").map(|s| s.motor.step_pin.mcu.as_str()),
        Some("ebb")
    );
    assert_eq!(cfg.mcu("ebb").map(|m| m.serial.as_str()), Some("/dev/ttyACM1"));

    assert_eq!(
        parse(&MINIMAL.replace("step_pin: PC0", "step_pin: ebb:PC0")).map(|_| ()),
        Err("printer.cfg:20: [stepper_z] step_pin: pin 'ebb:PC0' refers to mcu 'ebb', but there is no [mcu ebb] \
             section"
            .to_string())
    );
    assert_eq!(
        parse(&MINIMAL.replace("dir_pin: PB1", "dir_pin: PA1")).map(|_| ()),
        Err("printer.cfg:15: [stepper_y] dir_pin: pin 'PA1' is also used by [stepper_x] dir_pin".to_string())
    );
    // One enable line for all steppers is fine when every user agrees on '!'.
    let shared = MINIMAL.replace("microsteps: 16\n", "microsteps: 16\nenable_pin: !PD7\n");
    assert!(ok(&shared)
        .steppers
        .iter()
        .all(|s| s.motor.enable_pin.as_ref().is_some_and(|p| p.invert)));
    let mixed = shared.replacen("enable_pin: !PD7", "enable_pin: PD7", 1);
    assert_eq!(
        parse(&mixed).map(|_| ()),
        Err("printer.cfg:18: [stepper_y] enable_pin: shared pin '!PD7' must have the same '!' as in [stepper_x] \
             enable_pin"
            .to_string())
    );
    // The simulated MCU has every board family's pin names, but no port M.
    let sim = MINIMAL.replace("/dev/ttyACM0", "simulator").replace("PC1", "PM1");
    let err = parse(&sim).map(|_| ()).unwrap_err();
    assert!(
        err.starts_with(
            "printer.cfg:21: [stepper_z] dir_pin: pin 'PM1': the simulated mcu 'mcu' has no such pin"
        ),
        "{err}"
    );
}

#[test]
fn includes_and_save_config_reach_the_typed_config() {
    let steppers = MINIMAL
        .split_once("[stepper_x]")
        .map(|(_, rest)| format!("[stepper_x]{rest}"))
        .unwrap_or_default();
    let main = "[mcu]\nserial: x\n[printer]\nkinematics: cartesian\nmax_velocity: 300\nmax_accel: 3000\n\
        [include steppers.cfg]\n\
        #*# <---------------------- SAVE_CONFIG ---------------------->\n\
        #*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.\n#*#\n\
        #*# [stepper_z]\n#*# position_endstop = 0.7\n#*# endstop_pin = ^PC3\n";
    let load_with = |steppers: &str| {
        let mut read = |p: &Path| {
            if p == Path::new("/cfg/steppers.cfg") {
                Ok(steppers.to_string())
            } else {
                Err(io::Error::from(io::ErrorKind::NotFound))
            }
        };
        let file =
            ini::parse_with(main, Path::new("/cfg/printer.cfg"), &mut read).unwrap_or_else(|e| panic!("{e}"));
        (PrinterConfig::from_ini(&file), file)
    };
    let (cfg, file) = load_with(&steppers);
    let cfg = cfg.unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(
        cfg.stepper("stepper_x").map(StepperSection::step_dist),
        Some(1.0 / 80.0)
    );
    assert_eq!(
        cfg.stepper("stepper_z").and_then(|s| s.position_endstop),
        Some(0.7)
    );
    assert_eq!(
        file.files(),
        [
            PathBuf::from("/cfg/printer.cfg"),
            PathBuf::from("/cfg/steppers.cfg")
        ]
    );

    // An error inside the include names the included file and its line.
    let (e, _) = load_with(&steppers.replacen("microsteps: 16", "microsteps: abc", 1));
    assert_eq!(
        e.map(|_| ()).map_err(|e| e.to_string()),
        Err("/cfg/steppers.cfg:4: [stepper_x] microsteps: expected an integer, got 'abc'".to_string())
    );
}

#[test]
fn heater_bed_and_extruder_pins_are_checked_together() {
    let text = format!(
        "{MINIMAL}[heater_bed]\nheater_pin: PH5\nsensor_type: EPCOS 100K B57560G104F\nsensor_pin: PK6\n\
         control: watermark\nmin_temp: 0\nmax_temp: 130\n"
    );
    let cfg = ok(&text);
    let bed = cfg.heater_bed.as_ref().unwrap_or_else(|| panic!("no bed"));
    assert_eq!(
        (bed.name.as_str(), bed.control),
        ("heater_bed", HeaterControl::Watermark { max_delta: 2.0 })
    );
    assert_eq!(
        parse(&text.replace("heater_pin: PH5", "heater_pin: PA0")).map(|_| ()),
        Err(
            "printer.cfg:26: [heater_bed] heater_pin: pin 'PA0' is also used by [stepper_x] step_pin"
                .to_string()
        )
    );
}

#[test]
fn config_error_accessors() {
    let e = parse_str(
        &MINIMAL.replace("microsteps: 16", "microsteps: x"),
        Path::new("printer.cfg"),
    );
    let e = e.err().unwrap_or_else(|| panic!("expected an error"));
    assert_eq!((e.section(), e.option()), (Some("stepper_x"), Some("microsteps")));
    assert_eq!(e.location().map(|l| l.line), Some(10));
    assert!(matches!(e.problem(), Some(ValueProblem::NotAnInteger(_))));
    let e = load(Path::new("/nonexistent/printer.cfg"))
        .err()
        .unwrap_or_else(|| panic!("expected an error"));
    assert!(matches!(e, ConfigError::Ini(ini::IniError::Read { .. })));
    assert!(
        e.to_string()
            .starts_with("/nonexistent/printer.cfg: cannot read config file"),
        "{e}"
    );
}

/// The built-in config's option lines, as (line index, key) pairs.
fn option_lines() -> Vec<(usize, String)> {
    SIMULATED_PRINTER_CFG
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.starts_with(['#', '[']) && l.contains(':'))
        .filter_map(|(i, l)| l.split_once(':').map(|(k, _)| (i, k.to_string())))
        .collect()
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 128, ..ProptestConfig::default() })]

    /// Replacing any one value of a valid config with arbitrary text never panics, and an error
    /// names the line that was changed (or the section, for an error that only appears later).
    #[test]
    fn any_one_bad_value_never_panics(pick in any::<prop::sample::Index>(), value in "[ -~]{0,12}") {
        let lines = option_lines();
        let (index, key) = &lines[pick.index(lines.len())];
        let mut text: Vec<String> = SIMULATED_PRINTER_CFG.lines().map(str::to_string).collect();
        text[*index] = format!("{key}: {value}");
        let _ = parse_str(&text.join("\n"), Path::new("p.cfg")).map_err(|e| e.to_string());
    }

    #[test]
    fn arbitrary_text_never_panics(text in "(?s).{0,300}") {
        let _ = parse_str(&text, Path::new("/nonexistent-dir/p.cfg"));
    }
}

const DELTA: &str = "[mcu]\nserial: /dev/ttyACM0\n\
[printer]\nkinematics: delta\nmax_velocity: 300\nmax_accel: 3000\ndelta_radius: 140\n\
[stepper_a]\nstep_pin: PA0\ndir_pin: PA1\nmicrosteps: 16\nrotation_distance: 40\nendstop_pin: PA2\n\
position_endstop: 250\narm_length: 270\n\
[stepper_b]\nstep_pin: PA3\ndir_pin: PA4\nmicrosteps: 16\nrotation_distance: 40\nendstop_pin: PA5\n\
position_endstop: 251\n\
[stepper_c]\nstep_pin: PA6\ndir_pin: PA7\nmicrosteps: 16\nrotation_distance: 40\nendstop_pin: PB0\n\
position_endstop: 249\narm_length: 271\nangle: 91\n";

#[test]
fn delta_geometry() {
    let cfg = ok(DELTA);
    let d = cfg.delta.expect("delta section");
    assert_eq!(d.delta_radius, 140.0);
    assert_eq!(d.print_radius, 140.0);
    assert_eq!(d.minimum_z_position, 0.0);
    assert_eq!(d.arm_length, [270.0, 270.0, 271.0]);
    assert_eq!(d.angles, [210.0, 330.0, 91.0]);
    let names: Vec<&str> = cfg.steppers.iter().map(|s| s.name.as_str()).collect();
    assert_eq!(names, ["stepper_a", "stepper_b", "stepper_c"]);
    assert_eq!(cfg.steppers[1].position_max, 251.0);
    assert!(cfg.steppers[0].homing_positive_dir);
    assert!(ok(MINIMAL).delta.is_none());
    // Towers B and C take A's position_endstop when they give none, as Klipper.
    let inherited = ok(&DELTA
        .replace("position_endstop: 251\n", "")
        .replace("position_endstop: 249\n", ""));
    let endstops: Vec<_> = inherited.steppers.iter().map(|s| s.position_endstop).collect();
    assert_eq!(endstops, [Some(250.0); 3]);
    assert_eq!(inherited.steppers[2].position_max, 250.0);
}

#[test]
fn delta_errors_name_the_option() {
    assert_eq!(
        parse(&DELTA.replace("delta_radius: 140\n", "")).map(|_| ()),
        Err("printer.cfg:3: Option 'delta_radius' in section 'printer' must be specified".to_string())
    );
    assert_eq!(
        parse(&DELTA.replace("arm_length: 270\n", "")).map(|_| ()),
        Err("printer.cfg:8: Option 'arm_length' in section 'stepper_a' must be specified".to_string())
    );
    assert_eq!(
        parse(&DELTA.replace("position_endstop: 250\n", "")).map(|_| ()),
        Err("printer.cfg:8: Option 'position_endstop' in section 'stepper_a' must be specified".to_string())
    );
    let short = parse(&DELTA.replace("arm_length: 271", "arm_length: 100")).map(|_| ());
    assert!(
        short
            .as_ref()
            .is_err_and(|e| e.contains("stepper_c") && e.contains("arm_length")),
        "{short:?}"
    );
}

/// MINIMAL with `[mcu probe_mcu]`, a `[probe]` on it (from line 26) and Z homing on the probe
/// (`endstop_pin` at line 24).
fn with_probe(probe_extra: &str) -> String {
    MINIMAL.replace(
        "rotation_distance: 8\nposition_max: 200\n",
        "rotation_distance: 8\nendstop_pin: probe:z_virtual_endstop\nposition_max: 200\n",
    ) + "[mcu probe_mcu]\nserial: /dev/ttyACM1\n[probe]\npin: ^probe_mcu:PA4\nz_offset: 1.5\n"
        + probe_extra
}

#[test]
fn probe_virtual_endstop_homes_z_at_z_offset() {
    let cfg = ok(&with_probe("samples: 3\n"));
    let z = cfg.stepper("stepper_z").unwrap_or_else(|| panic!("no stepper_z"));
    let pin = z.endstop_pin.as_ref().map(|p| (p.mcu.as_str(), p.pin.as_str()));
    assert_eq!(pin, Some((PROBE_PIN_MCU, Z_VIRTUAL_ENDSTOP)));
    assert_eq!((z.position_endstop, z.homing_positive_dir), (Some(1.5), false));
    let p = cfg.probe.as_ref().unwrap_or_else(|| panic!("no probe"));
    assert_eq!(
        (p.pin.mcu.as_str(), p.pin.pullup, p.samples),
        ("probe_mcu", true, 3)
    );
    assert!(cfg.warnings.is_empty(), "{:?}", cfg.warnings);
    // A probe beside an ordinary Z endstop.
    let cfg = ok(&(MINIMAL.replace(
        "rotation_distance: 8\nposition_max: 200\n",
        "rotation_distance: 8\nendstop_pin: PD5\nposition_endstop: 0\nposition_max: 200\n",
    ) + "[probe]\npin: PD6\nz_offset: 2\n"));
    assert_eq!(
        cfg.stepper("stepper_z").and_then(|z| z.position_endstop),
        Some(0.0)
    );
    assert_eq!(cfg.probe.map(|p| p.z_offset), Some(2.0));
}

#[test]
fn probe_config_errors_name_file_line_section_and_option() {
    let cases = [
        (
            with_probe("").replace("endstop_pin: probe:z_virtual_endstop\n", "endstop_pin: probe:z_virtual_endstop\nposition_endstop: 0\n"),
            "printer.cfg:25: Option 'position_endstop' is not valid in section 'stepper_z'",
        ),
        (
            with_probe("").split("[mcu probe_mcu]").next().unwrap_or_default().to_string(),
            "printer.cfg:24: [stepper_z] endstop_pin: pin 'probe:z_virtual_endstop': there is no [probe] section",
        ),
        (
            with_probe("").replace("z_offset: 1.5", "z_offset: -1"),
            "printer.cfg:24: [stepper_z] endstop_pin: the endstop position is [probe] z_offset: must be between \
             position_min (0) and position_max (200), got -1",
        ),
        (
            with_probe("").replace("step_pin: PA0\n", "step_pin: PA0\nendstop_pin: probe:z_virtual_endstop\n"),
            "printer.cfg:9: [stepper_x] endstop_pin: pin 'probe:z_virtual_endstop': the probe virtual endstop can \
             only be [stepper_z] endstop_pin",
        ),
        (
            with_probe("speed: 0\n"),
            "printer.cfg:31: [probe] speed: must be above 0, got 0",
        ),
        (
            with_probe("samples_result: mode\n"),
            "printer.cfg:31: [probe] samples_result: expected one of median, average, got 'mode'",
        ),
        (
            with_probe("").replace("z_offset: 1.5\n", ""),
            "printer.cfg:28: Option 'z_offset' in section 'probe' must be specified",
        ),
    ];
    for (text, want) in cases {
        assert_eq!(parse(&text).map(|_| ()), Err(want.to_string()), "{text}");
    }
}

#[test]
fn simulator_bed_surface() {
    let cfg = ok(&format!("{MINIMAL}[simulator]\nbed_surface_z: 1.25\n"));
    assert_eq!(cfg.simulator.bed_surface_z, 1.25);
    assert_eq!(
        parse(&format!("{MINIMAL}[simulator]\nbed_surface_z: x\n")).map(|_| ()),
        Err("printer.cfg:26: [simulator] bed_surface_z: expected a number, got 'x'".to_string())
    );
}

/// `[stepper_zN]` with the given pins, as a further Z motor.
fn extra_z(n: u32, port: char, extra: &str) -> String {
    format!(
        "[stepper_z{n}]\nstep_pin: P{port}0\ndir_pin: !P{port}1\nenable_pin: !P{port}2\nmicrosteps: 16\n\
         rotation_distance: 8\n{extra}"
    )
}

#[test]
fn further_motors_of_a_rail_are_read_in_index_order() {
    let text = format!(
        "{MINIMAL}{}{}{}[stepper_x1]\nstep_pin: PJ0\ndir_pin: PJ1\nmicrosteps: 32\nrotation_distance: 40\n",
        extra_z(1, 'G', ""),
        extra_z(2, 'H', "full_steps_per_rotation: 400\n"),
        extra_z(3, 'K', "")
    );
    let cfg = ok(&text);
    let names: Vec<(&str, usize)> = cfg
        .extra_steppers
        .iter()
        .map(|s| (s.name.as_str(), s.rail))
        .collect();
    assert_eq!(
        names,
        [
            ("stepper_x1", 0),
            ("stepper_z1", 2),
            ("stepper_z2", 2),
            ("stepper_z3", 2)
        ]
    );
    assert_eq!(cfg.extra_steppers[0].motor.step_dist(), 40.0 / (200.0 * 32.0));
    assert_eq!(cfg.extra_steppers[2].motor.step_dist(), 8.0 / (400.0 * 16.0));
    assert!(cfg.extra_steppers[1].motor.dir_pin.invert);
    // The planner steps them with their rail, after the rails.
    let (pc, _) = crate::planning::pipeline_config(&cfg, 1e6, 25e-6).unwrap_or_else(|e| panic!("{e}"));
    let specs: Vec<(&str, usize)> = pc.steppers.iter().map(|s| (s.name.as_str(), s.axis)).collect();
    assert_eq!(
        specs,
        [
            ("stepper_x", 0),
            ("stepper_y", 1),
            ("stepper_z", 2),
            ("stepper_x1", 0),
            ("stepper_z1", 2),
            ("stepper_z2", 2),
            ("stepper_z3", 2)
        ]
    );
}

#[test]
fn further_motor_errors_name_the_option() {
    // A gap in the indices: stepper_z2 is looked up only after stepper_z1.
    assert_eq!(
        parse(&format!("{MINIMAL}{}", extra_z(2, 'G', ""))).map(|_| ()),
        Err("printer.cfg:25: Section 'stepper_z2' is not a valid config section".to_string())
    );
    assert_eq!(
        parse(&format!("{MINIMAL}{}", extra_z(1, 'G', "endstop_pin: PG3\n"))).map(|_| ()),
        Err(
            "printer.cfg:31: [stepper_z1] endstop_pin: [stepper_z] has no endstop_pin: a motor's own endstop \
             needs the rail's homing options (position_endstop, homing_speed…) from there"
                .to_string()
        )
    );
    assert_eq!(
        parse(&format!("{MINIMAL}{}", extra_z(1, 'G', "position_max: 10\n"))).map(|_| ()),
        Err("printer.cfg:31: Option 'position_max' is not valid in section 'stepper_z1'".to_string())
    );
    let two_mcus = format!(
        "{MINIMAL}[mcu zboard]\nserial: /dev/ttyACM1\n{}",
        extra_z(1, 'G', "").replace("P", "zboard:P")
    );
    let err = parse(&two_mcus).map(|_| ()).unwrap_err();
    assert!(
        err.starts_with(
            "printer.cfg:28: [stepper_z1] step_pin: must be on the same mcu as [stepper_z]'s step_pin ('mcu')"
        ),
        "{err}"
    );
    assert!(err.contains("multi-mcu homing"), "{err}");
    // A pin shared with the rail's motor is refused like any pin used twice.
    let shared = format!(
        "{MINIMAL}{}",
        extra_z(1, 'G', "").replace("step_pin: PG0", "step_pin: PC0")
    );
    assert!(parse(&shared).is_err());
}

/// MINIMAL with a Z endstop (`^PC3` at 0, lines 25-26), then `extras` (from line 27).
fn z_homed(extras: &str) -> Result<PrinterConfig, String> {
    parse(&format!(
        "{MINIMAL}endstop_pin: ^PC3\nposition_endstop: 0\n{extras}"
    ))
}

#[test]
fn further_motors_may_have_their_own_endstops() {
    let cfg = z_homed(&format!(
        "{}{}{}",
        extra_z(1, 'G', "endstop_pin: ^!PG3\n"),
        extra_z(2, 'H', ""),
        extra_z(3, 'K', "endstop_pin: ^PC3\n")
    ))
    .unwrap_or_else(|e| panic!("{e}"));
    let own: Vec<(&str, Option<String>)> = cfg
        .extra_steppers
        .iter()
        .map(|s| (s.name.as_str(), s.endstop_pin.as_ref().map(ToString::to_string)))
        .collect();
    // stepper_z1 on its own switch; stepper_z2 without one and stepper_z3 naming the rail's
    // pin stop on [stepper_z]'s.
    assert_eq!(
        own,
        [
            ("stepper_z1", Some("^!PG3".to_string())),
            ("stepper_z2", None),
            ("stepper_z3", None)
        ]
    );
    // Its own endstop may sit on another MCU (the trigger is relayed to the motors' MCU).
    let cfg = z_homed(&format!(
        "[mcu zboard]\nserial: /dev/ttyACM1\n{}",
        extra_z(1, 'G', "endstop_pin: zboard:PA3\n")
    ))
    .unwrap_or_else(|e| panic!("{e}"));
    let pin = cfg.extra_steppers[0]
        .endstop_pin
        .as_ref()
        .map(|p| (p.mcu.as_str(), p.pin.as_str()));
    assert_eq!(pin, Some(("zboard", "PA3")));
}

#[test]
fn further_motor_endstop_errors_name_file_line_section_and_option() {
    let cases = [
        (
            extra_z(1, 'G', "endstop_pin: PC3\n"),
            "printer.cfg:33: [stepper_z1] endstop_pin: shares [stepper_z]'s endstop pin '^PC3' and must \
             specify the same pullup/invert settings",
        ),
        (
            extra_z(1, 'G', "endstop_pin: PA0\n"),
            "printer.cfg:33: [stepper_z1] endstop_pin: pin 'PA0' is also used by [stepper_x] step_pin",
        ),
        (
            extra_z(1, 'G', "endstop_pin: !^PG3\n"),
            "printer.cfg:33: [stepper_z1] endstop_pin: invalid pin '!^PG3': '^' or '~' must come before '!'",
        ),
        (
            extra_z(1, 'G', "endstop_pin: tmc2209_stepper_z1:virtual_endstop\n"),
            "printer.cfg:33: [stepper_z1] endstop_pin: pin 'tmc2209_stepper_z1:virtual_endstop': a further \
             motor's own endstop must be a pin of an [mcu] (the probe's and a driver's virtual endstops are \
             not supported there by Cadence yet)",
        ),
        (
            extra_z(1, 'G', "endstop_pin: nowhere:PG3\n"),
            "printer.cfg:33: [stepper_z1] endstop_pin: ",
        ),
    ];
    for (extra, want) in cases {
        let got = z_homed(&extra).map(|_| ()).unwrap_err();
        assert!(got.starts_with(want), "{got}\nwant: {want}");
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 128, ..ProptestConfig::default() })]

    /// Any `[stepper_z1] endstop_pin` text never panics: it is read, or the error names
    /// `[stepper_z1] endstop_pin` at its line.
    #[test]
    fn further_motor_endstop_pin_never_panics(pin in "[!^~ a-zA-Z0-9_:.]{0,16}") {
        match z_homed(&extra_z(1, 'G', &format!("endstop_pin: {pin}\n"))) {
            Ok(cfg) => prop_assert_eq!(cfg.extra_steppers.len(), 1),
            Err(e) => prop_assert!(
                e.starts_with("printer.cfg:33: [stepper_z1] endstop_pin: "),
                "{}",
                e
            ),
        }
    }
}

#[test]
fn simulated_z_endstop_offsets_are_read_per_motor() {
    let sim = |v: &str| {
        parse(&format!(
            "{}[simulator]\ngantry_tilt: 0, 0.4\nz_endstop_offsets: {v}\n",
            MINIMAL.replace("/dev/ttyACM0", "simulator")
        ))
        .map(|c| c.simulator.z_endstop_offsets)
    };
    assert_eq!(sim("0, 0.25,-0.1"), Ok(vec![0.0, 0.25, -0.1]));
    assert_eq!(
        sim("0, x"),
        Err("printer.cfg:27: [simulator] z_endstop_offsets: expected a number, got 'x'".to_string())
    );
}

#[test]
fn safe_z_home_and_homing_override_are_read() {
    let cfg = ok(&format!(
        "{MINIMAL}[safe_z_home]\nhome_xy_position: 100, 120.5\nz_hop: 10\nmove_to_previous: True\n"
    ));
    assert_eq!(
        cfg.safe_z_home,
        Some(SafeZHomeSection {
            home_xy_position: [100.0, 120.5],
            speed: 50.0,
            z_hop: 10.0,
            z_hop_speed: 15.0,
            move_to_previous: true,
        })
    );
    let cfg = ok(&format!(
        "{MINIMAL}[homing_override]\naxes: z\nset_position_z: 0\ngcode:\n  G28 X\n  G28 Z\n"
    ));
    let o = cfg.homing_override.unwrap_or_else(|| panic!("no override"));
    assert_eq!(
        (o.axes, o.set_position),
        ([false, false, true], [None, None, Some(0.0)])
    );
    assert_eq!(o.script.name, HOMING_OVERRIDE_MACRO);
    assert!(o.script.gcode.contains("G28 Z"), "{}", o.script.gcode);
}

#[test]
fn homing_section_errors() {
    let errors = [
        (
            "[safe_z_home]\nspeed: 5\n",
            "printer.cfg:25: Option 'home_xy_position' in section 'safe_z_home' must be specified",
        ),
        (
            "[safe_z_home]\nhome_xy_position: 100\n",
            "printer.cfg:26: [safe_z_home] home_xy_position: must be two numbers 'X, Y', got '100'",
        ),
        (
            "[safe_z_home]\nhome_xy_position: 1,2\nz_hop_speed: 0\n",
            "printer.cfg:27: [safe_z_home] z_hop_speed: must be above 0, got 0",
        ),
        (
            "[homing_override]\naxes: z\n",
            "printer.cfg:25: Option 'gcode' in section 'homing_override' must be specified",
        ),
        // A broken script fails the load, naming its section.
        ("[homing_override]\ngcode: {% if %}\n", "homing_override"),
    ];
    for (extra, want) in errors {
        let err = parse(&format!("{MINIMAL}{extra}")).map(|_| ()).unwrap_err();
        assert!(err.contains(want), "{extra}: {err}");
    }
    let both = format!("{MINIMAL}[safe_z_home]\nhome_xy_position: 1,2\n[homing_override]\ngcode: G28\n");
    let err = parse(&both).map(|_| ()).unwrap_err();
    assert!(
        err.starts_with("printer.cfg:25: ") && err.contains("cannot be used together with [homing_override]"),
        "{err}"
    );
}
