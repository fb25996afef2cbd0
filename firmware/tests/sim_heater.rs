//! End to end: a `cadence-mcu` process with a simulated hotend whose thermistor opens (the
//! `--heater-fault` option). The test plays Klipper's host: it configures the heater's PWM
//! output with `max_duration` and the thermistor's `analog_in` with Klipper's oversampling and
//! range check, turns the heater on, and waits for the MCU to shut itself down with "ADC out of
//! range". The checks are on MCU clocks with generous bounds, never on wall time; the run
//! takes about 2.5 s.

mod common;

use common::{spawn_with, FREQ};
use firmware::core::constants::static_string_id;
use firmware::sim::heater::adc_of;
use std::ffi::OsStr;

#[test]
fn an_open_thermistor_shuts_the_simulated_mcu_down() {
    let args: &[&OsStr] = &[
        "--heater".as_ref(),
        "PA1=PA2".as_ref(),
        "--heater-fault".as_ref(),
        "PA1=open@1".as_ref(),
    ];
    let mut host = spawn_with(args);
    host.identify();
    host.send(&[("allocate_oids", &[2])]);
    // PA1 is pin 1, PA2 pin 2; max_duration 3 s, PWM cycle 0.1 s.
    host.send(&[
        ("config_digital_out", &[0, 1, 0, 0, 3 * FREQ as i64]),
        ("config_analog_in", &[1, 2]),
    ]);
    host.send(&[("finalize_config", &[1]), ("get_config", &[])]);
    assert_eq!(host.wait_for("config").0[0], 1);
    let start = host.clock() + FREQ / 2;
    let rest = 3 * FREQ / 10;
    let (min, max) = (8 * adc_of(250.0) as i64, 8 * adc_of(0.0) as i64);
    host.send(&[
        ("set_digital_out_pwm_cycle", &[0, (FREQ / 10) as i64]),
        ("queue_digital_out", &[0, start as i64, (FREQ / 10) as i64]),
        (
            "query_analog_in",
            &[1, start as i64, (FREQ / 1000) as i64, 8, rest as i64, min, max, 4],
        ),
    ]);
    let fault = FREQ; // open@1: MCU time 1 s
    let first = host.wait_for("analog_in_state").0;
    if start + FREQ / 100 < fault {
        assert!(
            (8 * 3800..=8 * 3911).contains(&first[2]),
            "ambient reading {first:?}"
        );
    }
    let shutdown = host.wait_for_shutdown();
    assert_eq!(
        shutdown[1],
        static_string_id("ADC out of range") as i64,
        "{shutdown:?}"
    );
    // Rounds start every `rest` from `start`; the 4th round that reads the open sensor ends
    // the run at its 8th reading (7 ms in), well before the heater's max_duration.
    let first_bad = if fault <= start {
        start
    } else {
        start + (fault - start).div_ceil(rest) * rest
    };
    let expect = first_bad + 3 * rest + 7 * FREQ / 1000;
    let clock = shutdown[0] as u64;
    assert!(
        clock + FREQ / 1000 >= expect && clock <= expect + rest,
        "shutdown at {clock}, expected {expect}"
    );
    assert!(clock < start + 3 * FREQ, "before max_duration");
    host.close();
}

#[test]
fn a_fault_on_an_unknown_heater_is_refused() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_cadence-mcu"))
        .args(["--heater", "PA1=PA2", "--heater-fault", "PA3=frozen@1"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("--heater-fault: pin 3 is not the heater pin of any --heater"),
        "{stderr}"
    );
}
