//! End to end: a `[bltouch]` on simulated two-MCU printers (`cadence print`). The probe sits on
//! `probe_mcu` with its servo (`control_pin`) and sensor (`sensor_pin`); the simulated MCU's
//! BLTouch (firmware `sim::bltouch`) decodes the servo pulses the host schedules, deploys and
//! stows its pin in 0.3 s, and its sensor triggers when the deployed pin reaches the simulated
//! bed surface. So a probe that the host did not deploy never triggers, and one it did not
//! stow fails the host's raise check.
//!
//! Printers (examples/simulated-probe.cfg with 20 mm axes, `[probe]` replaced by `[bltouch]`):
//! - "virtual": Z homes on the BLTouch (`probe:z_virtual_endstop`), so it triggers at Z =
//!   z_offset ([`Z_OFFSET`]);

use std::path::{Path, PathBuf};
use std::time::Duration;

use cadence_tests::{assert_success, retry_homing_timeouts, run, scratch, Run};

const TIMEOUT: Duration = Duration::from_secs(240);
const Z_OFFSET: f64 = 1.5;
/// One Z step and the sensor's sampling at the probing speed of 2 mm/s (a read every ≤ 1 ms,
/// 4 × 15 µs), twice (homing and probing), plus 5 ms of step lateness at 2 mm/s (a simulated
/// MCU on a starved VM runs its steps late, and the host computes the trigger's position from
/// the planned profile).
const TOLERANCE: f64 = 2.0 * (1.0 / 400.0 + 2.0 * (1e-3 + 4.0 * 15e-6)) + 2.0 * 5e-3 + 1e-9;
/// The multi-MCU stop budget.
const BUDGET_US: f64 = 25_000.0;

/// The example with 20 mm axes, `[probe]` replaced by `[bltouch]` with `options`, and `edit`
/// applied to each trimmed line (`None`: keep).
fn config(dir: &Path, options: &str, edit: impl Fn(&str) -> Option<String>) -> PathBuf {
    let section = format!(
        "[bltouch]\nsensor_pin: ^probe_mcu:PA4\ncontrol_pin: probe_mcu:PA5\nz_offset: {Z_OFFSET}\n\
         speed: 2\nlift_speed: 10\n{options}\n"
    );
    cadence_tests::probe_example_with(dir, &section, edit)
}

/// One printer of this file at a time: each runs two simulated MCUs whose trsync budget a
/// starved 2-core VM already strains.
static ONE_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// `cadence print` of `gcode` on `cfg`, with `CADENCE_SIM_ARGS_PROBE_MCU` set to `probe_args`;
/// a run that ended in `Communication timeout during homing` (a starved VM) is tried again.
fn print(dir: &Path, cfg: &Path, gcode: &str, probe_args: Option<&str>) -> Run {
    let _one = ONE_AT_A_TIME
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let g = dir.join("bltouch.gcode");
    std::fs::write(&g, gcode).expect("write gcode");
    retry_homing_timeouts(
        || {
            let mut cmd = std::process::Command::new(cadence_tests::bin("cadence"));
            cmd.arg("print")
                .arg(&g)
                .arg("--config")
                .arg(cfg)
                .arg("--no-progress");
            if let Some(a) = probe_args {
                cmd.env("CADENCE_SIM_ARGS_PROBE_MCU", a);
            }
            run(&mut cmd, TIMEOUT)
        },
        |r| r,
    )
}

/// Every value after `key` in the output.
fn values(stdout: &str, key: &str) -> Vec<f64> {
    stdout
        .lines()
        .filter_map(|l| l.split_once(key))
        .filter_map(|(_, v)| v.split_whitespace().next()?.parse().ok())
        .collect()
}

/// The z of every `probe at X,Y is z=Z` line.
fn probed(stdout: &str) -> Vec<f64> {
    stdout
        .lines()
        .filter(|l| l.contains("probe at "))
        .filter_map(|l| l.rsplit_once("z=")?.1.trim().parse().ok())
        .collect()
}

/// The stop bounds (µs after the trigger) of every pass of the `homing z:` line.
fn z_stop_bounds(stdout: &str) -> Vec<(f64, f64)> {
    let line = stdout
        .lines()
        .find(|l| l.contains("homing z:"))
        .unwrap_or_default();
    cadence_tests::stop_bounds(line)
}

#[test]
fn bltouch_homes_z_probes_and_answers_debug_commands() {
    let dir = scratch("bltouch-virtual");
    let cfg = config(&dir, "samples: 2\nsamples_result: median", |_| None);
    let run = print(
        &dir,
        &cfg,
        "G28\nG1 Z5 F600\nPROBE\nG1 Z5 F600\nBLTOUCH_DEBUG\nBLTOUCH_DEBUG COMMAND=pin_down\nQUERY_PROBE\n\
         BLTOUCH_DEBUG COMMAND=touch_mode\nQUERY_PROBE\nBLTOUCH_DEBUG COMMAND=pin_up\nQUERY_PROBE\n\
         BLTOUCH_DEBUG COMMAND=touch_mode\nQUERY_PROBE\nBLTOUCH_DEBUG COMMAND=reset\nBLTOUCH_STORE MODE=OD\n\
         BLTOUCH_STORE\n",
        None,
    );
    assert_success(&run);
    let out = &run.stdout;
    // Z homed on the BLTouch: both passes stopped within the multi-MCU budget.
    assert!(out.contains("homing z: mcus probe_mcu+mcu;"), "{out}");
    let bounds = z_stop_bounds(out);
    assert_eq!(bounds.len(), 2, "{out}");
    for (_, upper) in bounds {
        assert!(upper < BUDGET_US, "stop {upper} µs after the trigger\n{out}");
    }
    let probed = probed(out);
    assert_eq!(probed.len(), 2, "{out}");
    for z in probed.iter().chain(&values(out, "Result is z=")) {
        assert!((z - Z_OFFSET).abs() <= TOLERANCE, "probed z={z}\n{out}");
    }
    assert!(
        out.contains(
            "BLTouch commands: output_mode_store, pin_down, pin_up, reset, self_test, set_5V_output_mode, \
             set_OD_output_mode, touch_mode"
        ),
        "{out}"
    );
    // In the air: pin down reads open, so does touch mode with the pin down; pin up reads open,
    // and pin up + touch mode reads triggered (the self-test's condition).
    let answers: Vec<&str> = out
        .lines()
        .map(str::trim)
        .filter(|l| l.starts_with("probe: ") || l.starts_with("Sending BLTOUCH_DEBUG"))
        .collect();
    assert_eq!(
        answers,
        [
            "Sending BLTOUCH_DEBUG COMMAND=pin_down",
            "probe: open",
            "Sending BLTOUCH_DEBUG COMMAND=touch_mode",
            "probe: open",
            "Sending BLTOUCH_DEBUG COMMAND=pin_up",
            "probe: open",
            "Sending BLTOUCH_DEBUG COMMAND=touch_mode",
            "probe: TRIGGERED",
            "Sending BLTOUCH_DEBUG COMMAND=reset",
        ],
        "{out}"
    );
    assert!(out.contains("Storing BLTouch output mode: OD"), "{out}");
    assert!(out.contains("BLTouch output modes: 5V, OD"), "{out}");
}

/// A probe whose pin never gets up fails the raise check (after two retries); one whose sensor
/// never reports fails the self-test.
#[test]
fn bltouch_faults_are_reported() {
    let dir = scratch("bltouch-faults");
    let cfg = config(&dir, "", |_| None);
    let run = print(&dir, &cfg, "G28 Z\n", Some("--bltouch PA4=PA5,z,0,stuck"));
    assert_eq!(run.code, Some(1), "{}\n{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains("G28: BLTouch failed to raise probe"),
        "{}",
        run.stderr
    );
    let run = print(&dir, &cfg, "G28 Z\n", Some("--bltouch PA4=PA5,z,0,mute"));
    assert_eq!(run.code, Some(1), "{}\n{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains("G28: BLTouch failed to verify sensor state"),
        "{}",
        run.stderr
    );
}
