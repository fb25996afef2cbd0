//! End to end on the simulated printer: SPI temperature chips as Klipper's example configs use
//! them — the hotend read by a MAX31865 (platinum RTD, hardware SPI), the bed by a MAX6675 on
//! software SPI pins, `[temperature_sensor]`s on a MAX31855 and a MAX31856 — each a simulated
//! chip answering `config_thermocouple`/`query_thermocouple`'s reads in its datasheet's format;
//! M109/M190 wait on them as on a thermistor. An open thermocouple sets the chip's fault bit
//! and the MCU shuts down after three faulty reads ("Thermocouple reader fault"), the error
//! naming the chip's fault. Times are MCU time (a time-scaled simulator); bounds are generous.

use std::path::{Path, PathBuf};
use std::time::Duration;

use cadence_tests::{print_scaled, scratch, value_after, Run};

const TIMEOUT: Duration = Duration::from_secs(240);

/// The built-in simulated printer without endstops, its heaters read by SPI chips.
fn config(dir: &Path) -> PathBuf {
    let text: String = sysconfig::printer::SIMULATED_PRINTER_CFG
        .lines()
        .filter(|l| !l.starts_with("endstop_pin:") && !l.starts_with("homing_speed:"))
        .map(|l| format!("{l}\n"))
        .collect();
    let text = text
        .replacen(
            "sensor_type: Generic 3950\nsensor_pin: PF0\n",
            "sensor_type: MAX31865\nsensor_pin: PA4\nspi_bus: spi1\nrtd_nominal_r: 100\n\
             rtd_reference_r: 430\nrtd_num_of_wires: 2\nrtd_use_50Hz_filter: True\n",
            1,
        )
        .replacen(
            "sensor_type: Generic 3950\nsensor_pin: PF1\n",
            "sensor_type: MAX6675\nsensor_pin: PA5\nspi_software_miso_pin: PA6\n\
             spi_software_sclk_pin: PA7\nspi_software_mosi_pin: PA3\n",
            1,
        );
    assert!(text.contains("MAX31865") && text.contains("MAX6675"), "{text}");
    let text = format!(
        "{text}\n[temperature_sensor k_therm]\nsensor_type: MAX31855\nsensor_pin: PB4\nspi_bus: spi2\n\
         \n[temperature_sensor tc]\nsensor_type: MAX31856\nsensor_pin: PB5\ntc_type: K\n\
         tc_averaging_count: 4\n"
    );
    let path = dir.join("printer.cfg");
    std::fs::write(&path, text).unwrap();
    path
}

/// `cadence print` of `gcode` with `sim_args` for the simulated MCU.
fn print(dir: &Path, gcode: &str, sim_args: Option<&str>) -> Run {
    let cfg = config(dir);
    print_scaled(dir, &cfg, gcode, sim_args, TIMEOUT)
}

#[test]
fn heaters_and_sensors_read_through_spi_chips() {
    let dir = scratch("spi-sensors");
    let run = print(
        &dir,
        "M140 S40\nM104 S150\nM109 S150\nM190 S40\nM105\nG4 P2000\nM105\n",
        None,
    );
    assert_eq!(run.code, Some(0), "{}\n{}", run.stdout, run.stderr);
    let out = &run.stdout;
    eprintln!("{out}");
    // After the waits both heaters are at their targets, as their chips read them.
    let m105 = out
        .lines()
        .rfind(|l| l.contains("M105: B:"))
        .unwrap_or_else(|| panic!("no M105 in\n{out}"));
    let bed = value_after(m105, "B:", "B:");
    let hotend = value_after(m105, "T0:", "T0:");
    // The bed heats while M109 waits for the hotend: at or a little past its target.
    assert!((37.0..48.0).contains(&bed), "bed {bed}: {m105}");
    assert!((hotend - 150.0).abs() < 3.0, "hotend {hotend}: {m105}");
    // The sensors at room temperature (25 °C), each within its chip's resolution.
    let k = value_after(out, "temperature_sensor k_therm:", "k_therm:");
    assert!((k - 25.0).abs() <= 0.5, "MAX31855: {k}\n{out}");
    let tc = value_after(out, "temperature_sensor tc:", "tc:");
    assert!((tc - 25.0).abs() <= 0.5, "MAX31856: {tc}\n{out}");
}

#[test]
fn an_open_thermocouple_shuts_down_with_the_chips_fault() {
    let dir = scratch("spi-sensor-open");
    // The hotend's RTD opens 20 s of MCU time into the heat-up.
    let run = print(
        &dir,
        "M104 S200\nM109 S200\nG4 P100000\n",
        Some("--heater-fault PE0=open@20"),
    );
    assert_ne!(run.code, Some(0), "{}", run.stdout);
    let err = &run.stderr;
    assert!(err.contains("Thermocouple reader fault"), "{err}");
    assert!(err.contains("MAX31865: RTD input is disconnected"), "{err}");
}
