//! End to end on the simulated printer: the board-level sensors and outputs of Klipper's
//! example configs — the MCU's own temperature sensor (`temperature_mcu` on `ADC_TEMPERATURE`),
//! `[adc_scaled]` (a Duet's ADC references, which the simulated ADC's offset and gain error
//! make necessary), a hardware-PWM fan (`config_pwm_out`), fan tachometers (`config_counter`)
//! and a `[multi_pin]` heater output — each read back from the simulated MCU through the print's
//! summary.
//! Times are MCU time (a time-scaled simulator); bounds are generous.

use std::path::{Path, PathBuf};
use std::time::Duration;

use cadence_tests::{print_scaled, scratch, value_after, Run};

const TIMEOUT: Duration = Duration::from_secs(240);

/// The built-in simulated printer without endstops (no homing needed), with the board's
/// sensors and fans of this test.
fn config(dir: &Path) -> PathBuf {
    let mut text: String = sysconfig::printer::SIMULATED_PRINTER_CFG
        .lines()
        .filter(|l| !l.starts_with("endstop_pin:") && !l.starts_with("homing_speed:"))
        .map(|l| format!("{l}\n"))
        .collect();
    // The part fan (software PWM) gets a tachometer.
    text = text.replacen("[fan]\npin: PE2\n", "[fan]\npin: PE2\ntachometer_pin: ^PE10\n", 1);
    text.push_str(
        "\n[temperature_sensor board]\nsensor_type: temperature_mcu\nmin_temp: 0\nmax_temp: 100\n\
         \n[adc_scaled vref_scaled]\nvref_pin: PF5\nvssa_pin: PF6\n\
         \n[temperature_sensor chamber]\nsensor_type: Generic 3950\nsensor_pin: vref_scaled:PF2\n\
         \n[temperature_sensor unscaled]\nsensor_type: Generic 3950\nsensor_pin: PF3\n\
         \n[fan_generic exhaust]\npin: PE6\nhardware_pwm: True\ncycle_time: 0.00004\n\
         tachometer_pin: PE7\ntachometer_ppr: 1\n",
    );
    let path = dir.join("printer.cfg");
    std::fs::write(&path, text).unwrap();
    path
}

fn print(dir: &Path, gcode: &str) -> Run {
    let cfg = config(dir);
    print_scaled(dir, &cfg, gcode, None, TIMEOUT)
}

#[test]
fn mcu_sensor_scaled_adc_hardware_pwm_and_tachometers() {
    let dir = scratch("board-sensors");
    // The die warms from 25 °C towards 40 °C (τ = 2 min): 30 °C after ~49 s of MCU time.
    let run = print(
        &dir,
        "M106 S128\nSET_FAN_SPEED FAN=exhaust SPEED=1\n\
         TEMPERATURE_WAIT SENSOR=\"temperature_sensor board\" MINIMUM=30\nG4 P4000\n",
    );
    assert_eq!(run.code, Some(0), "{}\n{}", run.stdout, run.stderr);
    let out = &run.stdout;
    let board = value_after(out, "temperature_sensor board:", "board:");
    assert!((30.0..=40.5).contains(&board), "the MCU's die: {board}\n{out}");
    let low = value_after(out, "temperature_sensor board:", "lowest");
    assert!(
        (23.0..30.0).contains(&low),
        "it warmed from ambient: {low}\n{out}"
    );
    // Through the references the room reads 25 °C; without them the ADC's error shows.
    let chamber = value_after(out, "temperature_sensor chamber:", "chamber:");
    assert!((chamber - 25.0).abs() < 0.3, "scaled: {chamber}\n{out}");
    let unscaled = value_after(out, "temperature_sensor unscaled:", "unscaled:");
    assert!((unscaled - 25.0).abs() > 1.0, "unscaled: {unscaled}\n{out}");
    // The fans spin at their power (the simulated fan: 5000 rpm at full power).
    let part = value_after(out, "fan fan: 50 %", "%,");
    assert!((part - 2500.0).abs() < 250.0, "part fan: {part} rpm\n{out}");
    let exhaust = value_after(out, "fan_generic exhaust: 100 %", "%,");
    assert!(
        (exhaust - 5000.0).abs() < 250.0,
        "exhaust fan: {exhaust} rpm\n{out}"
    );
}

/// `[multi_pin]`: the hotend's heater output on two pins; the simulated MCU gets a second
/// hotend model on the group's second pin (read by a `[temperature_sensor]`), which heats as the
/// first does only if the host drives both pins with the same PWM.
#[test]
fn a_multi_pin_heater_drives_every_pin_of_its_group() {
    let dir = scratch("multi-pin");
    let cfg = config(&dir);
    let text = std::fs::read_to_string(&cfg).unwrap();
    assert!(text.contains("heater_pin: PE0\n"), "the example's hotend moved");
    let text = text.replacen("heater_pin: PE0\n", "heater_pin: multi_pin:hotend\n", 1)
        + "\n[multi_pin hotend]\npins: PE4, PE5\n\
           \n[temperature_sensor twin]\nsensor_type: Generic 3950\nsensor_pin: PF4\n";
    std::fs::write(&cfg, text).unwrap();
    let run = print_scaled(
        &dir,
        &cfg,
        "M109 S60\nM104 S0\n",
        Some("--heater PE5=PF4,hotend"),
        TIMEOUT,
    );
    assert_eq!(run.code, Some(0), "{}\n{}", run.stdout, run.stderr);
    let out = &run.stdout;
    let hotend = value_after(out, "heater extruder:", "highest");
    let twin = value_after(out, "temperature_sensor twin:", "highest");
    assert!(hotend >= 59.0, "{out}");
    assert!(
        (twin - hotend).abs() < 5.0,
        "the second pin heated as the first: {twin} vs {hotend}\n{out}"
    );
}

/// `temperature_mcu` on an MCU type without a calibration line and without the config's two
/// points is refused when the MCU is configured, naming the sensor.
#[test]
fn an_uncalibrated_mcu_sensor_names_itself() {
    let m = cadence::heaters::mcu_sensor::McuSensor {
        point1: None,
        point2: None,
    };
    let e = m.sensor("stm32h743xx").unwrap_err().to_string();
    assert!(e.contains("MCU temperature not supported on stm32h743xx"), "{e}");
}
