//! End to end: axes driven by several motors (`[stepper_x1]`, `[stepper_z1]`…`[stepper_z3]`)
//! on the simulated printer. Every motor of an axis is stepped from the same motion and stopped
//! by the axis's endstop through the trsync path; in the simulated world each motor drives its
//! own end of the carriage (`z`, `z1`, `z2`, `z3`), so a motor that missed the stop or a step
//! would leave its end elsewhere.
//!
//! The printer: the built-in cartesian one with 20 mm of travel per axis, X doubled by
//! `stepper_x1` and Z by three more motors, all on the main MCU (Klipper's rule: the motors
//! stopped by one endstop share an MCU). Stepper oids there: x 0, y 1, z 2, x1 3, z1..z3 4..6,
//! extruder 7.

use std::path::{Path, PathBuf};
use std::time::Duration;

use cadence_tests::{
    assert_exit, assert_no_step_after_stop, assert_success, home_traced, homing_timed_out, net_steps,
    print_traced, retry_homing_timeouts, run, scratch, short_homing_config_text, Run,
};
use firmware::trace::read_trace;

const TIMEOUT: Duration = Duration::from_secs(180);
/// Steps per mm of X (and X1) and of the Z motors.
const X_STEPS_PER_MM: f64 = 80.0;
const Z_STEPS_PER_MM: f64 = 400.0;
/// The simulated carriages start 10% of the 20 mm travel from the endstops at 0.
const START_MM: f64 = 2.0;
/// Oids of the X motors and of the Z motors on the main MCU.
const X_OIDS: [u8; 2] = [0, 3];
const Z_OIDS: [u8; 4] = [2, 4, 5, 6];
/// The endstop's sampling: a read every ≤ 1 ms, 4 × 15 µs to confirm; second passes at 5 mm/s.
const SAMPLING_S: f64 = 1e-3 + 4.0 * 15e-6;
const SECOND_SPEED: f64 = 5.0;
/// With the endstop on another simulated MCU: how far the stepper MCU's process may run
/// behind its steps on a loaded machine (the endstop reads the world as it was at its sample's
/// due time, but a step not taken yet is not in it).
const SIM_LATE_S: f64 = 0.010;

/// The built-in printer with short axes and the further motors; with `z_endstop_mcu`, Z's
/// endstop sits on a second simulated MCU of that name (the trigger is relayed by the host).
fn config(dir: &Path, z_endstop_mcu: Option<&str>) -> PathBuf {
    let mut out = short_homing_config_text("simulated-cartesian.cfg");
    // X1 turns the other way round (inverted dir pin), as a motor facing its twin does.
    out.push_str(
        "\n[stepper_x1]\nstep_pin: PJ0\ndir_pin: !PJ1\nenable_pin: !PJ2\nmicrosteps: 16\nrotation_distance: 40\n",
    );
    for (n, port) in [(1, 'G'), (2, 'H'), (3, 'K')] {
        out.push_str(&format!(
            "\n[stepper_z{n}]\nstep_pin: P{port}0\ndir_pin: P{port}1\nenable_pin: !P{port}2\nmicrosteps: 16\n\
             rotation_distance: 8\n"
        ));
    }
    if let Some(m) = z_endstop_mcu {
        out = out
            .replace("[printer]", &format!("[mcu {m}]\nserial: simulator\n\n[printer]"))
            .replace("endstop_pin: ^PC3", &format!("endstop_pin: ^{m}:PA3"));
    }
    let path = dir.join("printer.cfg");
    std::fs::write(&path, out).expect("write config");
    path
}

/// Where each motor's end of the carriage is, from its net steps in the main MCU's trace
/// (an inverted dir pin counts the other way).
fn world_ends(trace: &Path, oids: &[u8], steps_per_mm: f64, inverted: &[u8]) -> Vec<f64> {
    let net = net_steps(&read_trace(trace).expect("trace"));
    oids.iter()
        .map(|oid| {
            let n = *net.get(oid).unwrap_or(&0) as f64;
            let n = if inverted.contains(oid) { -n } else { n };
            START_MM + n / steps_per_mm
        })
        .collect()
}

/// Every end agrees with the first within one step (the motors step at the same clocks; one
/// step may fall on either side of the stop's clock) and with `want` within `tol`.
fn assert_ends(ends: &[f64], want: f64, steps_per_mm: f64, tol: f64, what: &str, run: &Run) {
    for (i, e) in ends.iter().enumerate() {
        assert!(
            (e - ends[0]).abs() <= 1.0 / steps_per_mm + 1e-9,
            "{what}: motor {i} is at {e} mm, the first at {} mm\n{}",
            ends[0],
            run.stdout
        );
        assert!(
            (e - want).abs() <= tol,
            "{what}: motor {i} is at {e} mm, want {want} ± {tol} mm\n{}",
            run.stdout
        );
    }
}

/// The host's `homed position: x=… y=… z=…` line.
fn homed_position(stdout: &str) -> [f64; 3] {
    let line = stdout
        .lines()
        .find_map(|l| l.strip_prefix("homed position: "))
        .unwrap_or_else(|| panic!("no homed position in:\n{stdout}"));
    let mut p = [f64::NAN; 3];
    for (i, field) in line.split_whitespace().enumerate().take(3) {
        p[i] = field[2..].parse().expect("number");
    }
    p
}

/// G28 then moves: both X motors and the four Z motors land on the commanded position (the
/// print also checks every motor's MCU position against the host's at its end).
#[test]
fn several_motors_per_axis_home_and_move_together() {
    let dir = scratch("axes-print");
    let cfg = config(&dir, None);
    let gcode = dir.join("home-move.gcode");
    std::fs::write(&gcode, "G28\nG90\nG1 X10 Y5 Z3 F1200\nG1 X7.5 Z7.25 F300\nM400\n").expect("write G-code");
    let trace = dir.join("print.trace");
    let run = retry_homing_timeouts(|| run(&mut print_traced(&gcode, &cfg, &trace), TIMEOUT), |r| r);
    assert_success(&run);
    for axis in ["x", "z"] {
        let want = format!("homing {axis}: mcus mcu;");
        assert!(run.stdout.contains(&want), "no '{want}' in:\n{}", run.stdout);
    }
    // Homed within a motor step plus the trigger's sampling; the moves add no error.
    let x_tol = 1.0 / X_STEPS_PER_MM + SECOND_SPEED * SAMPLING_S + 1e-9;
    let x = world_ends(&trace, &X_OIDS, X_STEPS_PER_MM, &[3]);
    assert_ends(&x, 7.5, X_STEPS_PER_MM, x_tol, "X", &run);
    let z_tol = 1.0 / Z_STEPS_PER_MM + SECOND_SPEED * SAMPLING_S + 1e-9;
    let z = world_ends(&trace, &Z_OIDS, Z_STEPS_PER_MM, &[]);
    assert_ends(&z, 7.25, Z_STEPS_PER_MM, z_tol, "Z", &run);
}

/// Z's endstop on another MCU: the host relays the trigger to the four Z motors' MCU, which
/// stops them all; none steps after the stop, and the host's homed Z is where they halted.
#[test]
fn z_motors_stop_together_on_an_endstop_of_another_mcu() {
    let dir = scratch("axes-relay");
    let cfg = config(&dir, Some("probe_mcu"));
    let trace = dir.join("home.trace");
    let run = retry_homing_timeouts(|| run(&mut home_traced("z", &cfg, &trace), TIMEOUT), |r| r);
    assert_success(&run);
    assert!(
        run.stdout.contains("homing z: mcus probe_mcu+mcu;"),
        "{}",
        run.stdout
    );
    for oid in Z_OIDS {
        assert_no_step_after_stop(&trace, None, oid);
    }
    let host = homed_position(&run.stdout);
    let tol = 1.0 / Z_STEPS_PER_MM + SECOND_SPEED * (SAMPLING_S + 5.0 * SIM_LATE_S) + 1e-9;
    let z = world_ends(&trace, &Z_OIDS, Z_STEPS_PER_MM, &[]);
    assert_ends(&z, host[2], Z_STEPS_PER_MM, tol, "Z", &run);
    // The trigger coordinate is position_endstop = 0: the carriage halted just past it.
    assert!((-tol..=0.250 + tol).contains(&z[0]), "Z halted at {} mm", z[0]);
}

/// An endstop MCU that answers too late: `Communication timeout during homing`, and every Z
/// motor was stopped.
#[test]
fn z_motors_all_stop_on_a_communication_timeout() {
    let dir = scratch("axes-timeout");
    let cfg = config(&dir, Some("probe_mcu"));
    let trace = dir.join("home.trace");
    let mut cmd = home_traced("z", &cfg, &trace);
    cmd.env("CADENCE_SIM_ARGS_PROBE_MCU", "--tx-delay-ms 30");
    let run = run(&mut cmd, TIMEOUT);
    assert_exit(&run, 1);
    assert!(homing_timed_out(&run), "stderr:\n{}", run.stderr);
    let t = assert_no_step_after_stop(&trace, None, Z_OIDS[0]);
    let net = net_steps(&t);
    for oid in Z_OIDS {
        assert_no_step_after_stop(&trace, None, oid);
        let n = net.get(&oid).copied().unwrap_or(0);
        // Far less than the 1.5 × travel homing move.
        assert!(
            n.abs() < (20.0 * Z_STEPS_PER_MM) as i64,
            "Z motor {oid} moved {n} steps"
        );
    }
}
