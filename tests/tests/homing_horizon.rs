//! A homing move whose steps take long to compute starts far enough ahead for them, but never
//! beyond what a 32-bit MCU clock can name: the printer's Z has 600,000 steps of homing travel
//! (1.5 × 1000 mm at 400 steps/mm), which at time scale 10 asked for a minute of MCU time
//! ahead, more than the 43 s a 50 MHz clock's 2³¹ ticks reach; the move's start and the
//! endstop's first read then read as in the past (Klipper's `printer-ratrig-v-minion-2021.cfg`,
//! 3200 steps/mm on its probe, ended G28 with "'mcu' reported a trigger but the endstop did
//! not trigger" every time at that scale).

use std::time::Duration;

use cadence_tests::{print_live, scratch};

#[test]
fn a_long_homing_move_on_a_fast_clock_homes_at_time_scale_10() {
    let dir = scratch("homing-horizon");
    let base = sysconfig::printer::SIMULATED_PRINTER_CFG;
    let z = "endstop_pin: ^PC3\nposition_endstop: 0\nposition_max: 200\nhoming_speed: 10\n";
    assert!(
        base.contains(z),
        "the built-in printer's Z changed: adapt this test"
    );
    assert!(
        base.contains("clock_freq: 50000000"),
        "the built-in MCU's clock changed"
    );
    let text = base.replacen(
        z,
        "endstop_pin: ^PC3\nposition_endstop: 0\nposition_max: 1000\nhoming_speed: 25\n",
        1,
    );
    let cfg = dir.join("printer.cfg");
    std::fs::write(&cfg, text).unwrap();
    let gcode = dir.join("home.gcode");
    std::fs::write(&gcode, "G28 Z\nG1 Z5 F600\nM400\n").unwrap();
    let run = print_live(&gcode, &cfg, "10", Duration::from_secs(300));
    assert_eq!(run.code, Some(0), "{}\n{}", run.stdout, run.stderr);
    assert!(run.stdout.contains("homing z:"), "{}", run.stdout);
}
