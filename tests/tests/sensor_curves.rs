//! End to end: the simulated printer's sensors read as the sensors configured. A hotend on a
//! custom `[thermistor]` with an inline resistor (and an inverted heater pin), a bed on a PT1000 and a chamber sensor on a
//! PT100 behind its amplifier (none of them the simulator's default β3950 thermistor, each of
//! which would read far off, most out of range) heat to their targets or read the room, as
//! `M105` reports them. The heat-up waits are checked in MCU time (M109/M190 return), never
//! in wall time.

use std::path::Path;
use std::time::Duration;

use cadence_tests::{print_live, scratch};

/// The built-in simulated printer without endstops (G28 declares the axes homed), its sensors
/// replaced: the hotend (its heater pin inverted) on a custom NTC behind a 4.7 kΩ inline resistor, the bed on a PT1000,
/// and a PT100 (INA826 amplifier) chamber sensor reported as `C`.
fn config(dir: &Path) -> String {
    let mut text = without_endstops();
    // An inverted heater pin (the heater on while the pin is low), as on Duet boards.
    text = text.replacen("heater_pin: PE0\n", "heater_pin: !PE0\n", 1);
    text = text.replacen(
        "sensor_type: Generic 3950\nsensor_pin: PF0\n",
        "sensor_type: my_ntc\nsensor_pin: PF0\ninline_resistor: 4700\n",
        1,
    );
    text = text.replacen(
        "sensor_type: Generic 3950\nsensor_pin: PF1\n",
        "sensor_type: PT1000\nsensor_pin: PF1\n",
        1,
    );
    assert!(
        !text.contains("sensor_type: Generic 3950"),
        "the built-in printer's sensors changed: adapt this test"
    );
    text.push_str(
        "\n[thermistor my_ntc]\ntemperature1: 25\nresistance1: 120000\ntemperature2: 180\n\
         resistance2: 900\ntemperature3: 260\nresistance3: 160\n\n\
         [temperature_sensor chamber]\nsensor_type: PT100 INA826\nsensor_pin: PF3\n\
         gcode_id: C\nmin_temp: 0\nmax_temp: 80\n",
    );
    let path = dir.join("printer.cfg");
    std::fs::write(&path, &text).unwrap();
    path.to_string_lossy().into_owned()
}

/// The built-in simulated printer without endstops (G28 declares the axes homed).
fn without_endstops() -> String {
    sysconfig::printer::SIMULATED_PRINTER_CFG
        .lines()
        .filter(|l| !l.starts_with("endstop_pin:") && !l.starts_with("homing_speed:"))
        .map(|l| format!("{l}\n"))
        .collect()
}

/// `ID:current` of `id` in an M105 line.
fn reading(line: &str, id: &str) -> f64 {
    line.split_whitespace()
        .find_map(|w| w.strip_prefix(&format!("{id}:")))
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no {id} in {line}"))
}

#[test]
fn configured_sensors_read_their_simulated_temperatures() {
    let dir = scratch("sensor-curves");
    let cfg = config(&dir);
    let gcode = dir.join("heat.gcode");
    std::fs::write(&gcode, "M140 S60\nM190 S60\nM105\nM104 S200\nM109 S200\nM105\n").unwrap();
    let run = print_live(&gcode, Path::new(&cfg), "5", Duration::from_secs(300));
    assert_eq!(run.code, Some(0), "{}\n{}", run.stdout, run.stderr);
    let m105: Vec<&str> = run.stdout.lines().filter(|l| l.contains("M105: ")).collect();
    assert_eq!(m105.len(), 2, "{}", run.stdout);
    // The bed heated (the hotend not yet); the chamber, the amplified PT100, reads the room.
    assert!((reading(m105[0], "B") - 60.0).abs() < 3.0, "{}", m105[0]);
    assert!((reading(m105[0], "T0") - 25.0).abs() < 2.0, "{}", m105[0]);
    assert!((reading(m105[0], "C") - 25.0).abs() < 2.0, "{}", m105[0]);
    // Then the hotend too, as its own sensor reads it.
    assert!((reading(m105[1], "T0") - 200.0).abs() < 3.0, "{}", m105[1]);
    assert!((reading(m105[1], "B") - 60.0).abs() < 3.0, "{}", m105[1]);
    assert!((reading(m105[1], "C") - 25.0).abs() < 2.0, "{}", m105[1]);
}

/// A bed on a `[thermistor]` whose three points bend the Steinhart–Hart fit the wrong way
/// (c3 < 0: the Makibox bed thermistor of Klipper's `printer-robo3d-r2-2017.cfg`, which had no
/// resistance at all for some temperatures and shut the MCU down with `ADC out of range` at
/// the first reading) reads and heats through the β of its outer points, as on Klipper.
#[test]
fn a_thermistor_whose_points_fit_no_steinhart_hart_curve_reads_through_its_beta() {
    let dir = scratch("sensor-curves-beta");
    let mut text = without_endstops();
    text = text.replacen(
        "sensor_type: Generic 3950\nsensor_pin: PF1\n",
        "sensor_type: makibox_bed\nsensor_pin: PF1\n",
        1,
    );
    assert!(
        text.contains("makibox_bed"),
        "the built-in printer's bed sensor changed"
    );
    text.push_str(
        "\n[thermistor makibox_bed]\ntemperature1: 25\nresistance1: 100000\ntemperature2: 50\n\
         resistance2: 29536\ntemperature3: 125\nresistance3: 1908\n",
    );
    let cfg = dir.join("printer.cfg");
    std::fs::write(&cfg, &text).unwrap();
    let gcode = dir.join("heat.gcode");
    std::fs::write(&gcode, "M140 S50\nM190 S50\nM105\n").unwrap();
    let run = print_live(&gcode, &cfg, "5", Duration::from_secs(300));
    assert_eq!(run.code, Some(0), "{}\n{}", run.stdout, run.stderr);
    let m105: Vec<&str> = run.stdout.lines().filter(|l| l.contains("M105: ")).collect();
    assert_eq!(m105.len(), 1, "{}", run.stdout);
    assert!((reading(m105[0], "B") - 50.0).abs() < 3.0, "{}", m105[0]);
}
