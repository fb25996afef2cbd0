//! End to end: a heater whose sensor is on another MCU (Klipper's `sensor_pin: host:analog5`
//! for a heater on `mcu`): examples/simulated-toolboard.cfg with the hotend's output moved to
//! `mcu` and its thermistor left on `toolboard`. The host reads the ADC reports of one MCU and
//! schedules the PWM on the other's clock; the simulated hotend heats in `mcu`'s process and
//! its temperature reaches `toolboard`'s ADC through the simulated world. M109 waits until
//! the sensor on the other MCU reads the target. Times are MCU time; bounds are generous.

use std::path::{Path, PathBuf};
use std::time::Duration;

use cadence_tests::{print_scaled, scratch, workspace};

const TIMEOUT: Duration = Duration::from_secs(240);

fn config(dir: &Path) -> PathBuf {
    let text =
        std::fs::read_to_string(workspace().join("examples/simulated-toolboard.cfg")).expect("example");
    let text = text.replacen("heater_pin: toolboard:PE0", "heater_pin: PE0", 1);
    assert!(text.contains("heater_pin: PE0") && text.contains("sensor_pin: toolboard:PF0"));
    let path = dir.join("printer.cfg");
    std::fs::write(&path, text).unwrap();
    path
}

#[test]
fn a_heater_reads_its_sensor_on_another_mcu() {
    let dir = scratch("remote-sensor");
    let cfg = config(&dir);
    let gcode = "M104 S120\nM109 S120\nG4 P2000\nM105\nM104 S0\n";
    let run = print_scaled(&dir, &cfg, gcode, None, TIMEOUT);
    assert_eq!(run.code, Some(0), "{}\n{}", run.stdout, run.stderr);
    let out = &run.stdout;
    let m105 = out
        .lines()
        .rfind(|l| l.contains("M105: "))
        .unwrap_or_else(|| panic!("no M105 in\n{out}"));
    let t: f64 = m105
        .split("T0:")
        .nth(1)
        .and_then(|r| r.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("{m105}"));
    assert!((t - 120.0).abs() < 3.0, "hotend {t}: {m105}\n{out}");
    let waited = out
        .lines()
        .find(|l| l.contains("M109 waited"))
        .unwrap_or_else(|| panic!("no M109 wait in\n{out}"));
    eprintln!("{waited}");
}
