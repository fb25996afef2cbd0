//! The reference Klipper configs in /work/shared/data/printers/ must load, with Klipper's
//! numbers (80 steps/mm on X). Skipped with a note when the shared data is absent.

use std::path::{Path, PathBuf};

use sysconfig::printer::{self, HeaterControl, Kinematics};

fn printers_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/printers")
}

fn reference(name: &str) -> Option<PathBuf> {
    let path = printers_dir().join(name);
    if path.exists() {
        Some(path)
    } else {
        eprintln!("note: {} is absent; test skipped", path.display());
        None
    }
}

fn check(name: &str, kinematics: Kinematics, max_velocity: f64) {
    let Some(path) = reference(name) else { return };
    let cfg = printer::load(&path).unwrap_or_else(|e| panic!("{e}"));
    assert!(cfg.warnings.is_empty(), "{:?}", cfg.warnings);
    assert_eq!(cfg.source, path);
    assert_eq!(cfg.printer.kinematics, kinematics);
    assert_eq!(
        (cfg.printer.max_velocity, cfg.printer.max_accel),
        (max_velocity, 3000.0)
    );
    assert_eq!(
        (cfg.printer.max_z_velocity, cfg.printer.max_z_accel),
        (25.0, 30.0)
    );
    assert_eq!(
        (
            cfg.printer.minimum_cruise_ratio,
            cfg.printer.square_corner_velocity
        ),
        (0.5, 5.0)
    );

    let names: Vec<_> = cfg.steppers.iter().map(|s| s.name.as_str()).collect();
    assert_eq!(names, ["stepper_x", "stepper_y", "stepper_z"]);
    let x = &cfg.steppers[0];
    assert_eq!(x.step_dist(), 1.0 / 80.0);
    assert_eq!(
        (x.motor.step_pin.pin.as_str(), x.motor.dir_pin.invert),
        ("PF0", false)
    );
    assert!(x
        .motor
        .enable_pin
        .as_ref()
        .is_some_and(|p| p.pin == "PD7" && p.invert));
    assert!(x.endstop_pin.as_ref().is_some_and(|p| p.pin == "PE5" && p.pullup));
    assert!(cfg.steppers[1].motor.dir_pin.invert);
    let z = &cfg.steppers[2];
    assert_eq!(z.step_dist(), 1.0 / 400.0);
    assert_eq!(
        (z.position_endstop, z.position_max, z.homing_positive_dir),
        (Some(0.5), 200.0, false)
    );
    assert_eq!(
        (z.homing_speed, z.second_homing_speed, z.homing_retract_dist),
        (5.0, 2.5, 5.0)
    );

    let e = cfg.extruder.as_ref().unwrap_or_else(|| panic!("no [extruder]"));
    assert!(
        (1.0 / e.step_dist() - 95.522).abs() < 0.001,
        "{}",
        1.0 / e.step_dist()
    );
    assert_eq!((e.nozzle_diameter, e.filament_diameter), (0.5, 3.5));
    assert_eq!(
        (e.max_extrude_cross_section, e.max_extrude_only_distance),
        (50.0, 500.0)
    );
    // Extrude-only defaults follow a 4·nozzle² bead, not max_extrude_cross_section (Klipper).
    let ratio = 4.0 * 0.5 * 0.5 / e.filament_area();
    assert!((e.max_extrude_only_velocity - max_velocity * ratio).abs() < 1e-9);
    assert!((e.max_extrude_only_accel - 3000.0 * ratio).abs() < 1e-9);
    assert_eq!(
        e.heater.control,
        HeaterControl::Pid {
            kp: 22.2,
            ki: 1.08,
            kd: 114.0
        }
    );
    assert_eq!((e.heater.min_temp, e.heater.max_temp), (0.0, 320.0));

    let bed = cfg
        .heater_bed
        .as_ref()
        .unwrap_or_else(|| panic!("no [heater_bed]"));
    assert_eq!(bed.control, HeaterControl::Watermark { max_delta: 2.0 });
    assert_eq!(bed.sensor_type, "EPCOS 100K B57560G104F");

    assert_eq!(cfg.mcus.len(), 1);
    assert_eq!(
        (cfg.mcus[0].name.as_str(), cfg.mcus[0].serial.as_str()),
        ("mcu", "/dev/ttyACM0")
    );
    assert!(!cfg.mcus[0].is_simulated());
}

#[test]
fn benchy_cartesian_loads() {
    check("benchy-cartesian.cfg", Kinematics::Cartesian, 500.0);
}

#[test]
fn benchy_corexy_loads() {
    check("benchy-corexy.cfg", Kinematics::CoreXY, 300.0);
}

#[test]
fn every_shared_printer_config_loads() {
    let Ok(entries) = std::fs::read_dir(printers_dir()) else {
        eprintln!("note: {} is absent; test skipped", printers_dir().display());
        return;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        if path.extension().is_some_and(|e| e == "cfg") {
            if let Err(e) = printer::load(&path) {
                panic!("{e}");
            }
        }
    }
}

#[test]
fn builtin_simulated_printer_loads_from_the_examples_file_too() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/simulated-cartesian.cfg");
    let from_file = printer::load(&path).unwrap_or_else(|e| panic!("{e}"));
    let builtin = printer::builtin_simulated().unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(from_file.steppers, builtin.steppers);
    assert_eq!(from_file.extruder, builtin.extruder);
    assert_eq!(from_file.steppers[0].step_dist(), 1.0 / 80.0);
}
