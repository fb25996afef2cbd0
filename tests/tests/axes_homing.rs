//! End to end: G28 as printer.cfg writes it, on the simulated printer (the built-in cartesian
//! one with 20 mm of travel per axis, endstops at 0, the carriages starting 2 mm from them):
//! `[safe_z_home]` (lift, X and Y, the safe spot, Z, lift again) and `[homing_override]` (its
//! script instead of G28, with `set_position_z`). The main MCU's step trace says where each axis
//! really went.

use std::path::{Path, PathBuf};
use std::time::Duration;

use cadence_tests::{
    assert_success, print_traced, retry_homing_timeouts, run, scratch, short_homing_config_text, Run,
};
use firmware::trace::{read_trace, TraceRecord};

const TIMEOUT: Duration = Duration::from_secs(180);
/// Steps per mm of X, Y, Z (oids 0, 1, 2).
const STEPS_PER_MM: [f64; 3] = [80.0, 80.0, 400.0];
const START_MM: f64 = 2.0;
/// Homed within a step plus the endstop's sampling (≤ 1.06 ms) at the 5 mm/s second pass.
const TOL: f64 = 1.0 / 80.0 + 5.0 * 1.06e-3 + 1e-9;

/// The short built-in printer plus `extra` sections.
fn config(dir: &Path, extra: &str) -> PathBuf {
    let mut out = short_homing_config_text("simulated-cartesian.cfg");
    out.push_str(extra);
    let path = dir.join("printer.cfg");
    std::fs::write(&path, out).expect("write config");
    path
}

/// Prints `gcode` on the printer with `extra`; returns the run and each axis's path: the
/// positions (mm) after every step of X, Y, Z.
fn print(test: &str, extra: &str, gcode: &str) -> (Run, [Vec<f64>; 3]) {
    let dir = scratch(test);
    let cfg = config(&dir, extra);
    let file = dir.join("home.gcode");
    std::fs::write(&file, gcode).expect("write G-code");
    let trace = dir.join("print.trace");
    let run = retry_homing_timeouts(|| run(&mut print_traced(&file, &cfg, &trace), TIMEOUT), |r| r);
    assert_success(&run);
    let t = read_trace(&trace).expect("trace");
    let mut paths: [Vec<f64>; 3] = Default::default();
    let mut at = [START_MM; 3];
    for r in &t.records {
        if let TraceRecord::Step { oid, dir, .. } = *r {
            let a = oid as usize;
            if a < 3 {
                at[a] += if dir { 1.0 } else { -1.0 } / STEPS_PER_MM[a];
                paths[a].push(at[a]);
            }
        }
    }
    (run, paths)
}

/// The highest point of `path` before its lowest (where the axis homed).
fn peak_before_home(path: &[f64]) -> f64 {
    let low = (0..path.len())
        .min_by(|&a, &b| path[a].total_cmp(&path[b]))
        .unwrap_or(0);
    path[..low].iter().copied().fold(f64::MIN, f64::max)
}

fn last(path: &[f64]) -> f64 {
    path.last().copied().unwrap_or(START_MM)
}

/// The order in which the report says the axes homed.
fn homing_order(stdout: &str) -> Vec<&str> {
    stdout
        .lines()
        .filter_map(|l| l.trim().strip_prefix("homing ")?.split(':').next())
        .collect()
}

#[test]
fn safe_z_home_homes_z_at_the_safe_spot_and_lifts() {
    let extra = "\n[safe_z_home]\nhome_xy_position: 10, 12\nspeed: 20\nz_hop: 3\nz_hop_speed: 5\n";
    let (run, paths) = print("axes-safe-z-home", extra, "G28\nM400\n");
    assert_eq!(homing_order(&run.stdout), ["x", "y", "z"], "{}", run.stdout);
    // Z was lifted 3 mm first (from 2 mm, unhomed), homed, then lifted to z_hop.
    let z_max_before_home = peak_before_home(&paths[2]);
    assert!(
        (z_max_before_home - (START_MM + 3.0)).abs() <= 1.0 / 400.0 + 1e-9,
        "Z rose to {z_max_before_home} mm\n{}",
        run.stdout
    );
    for (a, want) in [(0, 10.0), (1, 12.0), (2, 3.0)] {
        let got = last(&paths[a]);
        assert!(
            (got - want).abs() <= TOL,
            "axis {a} ended at {got} mm, want {want}\n{}",
            run.stdout
        );
    }
}

#[test]
fn homing_override_runs_its_script_instead_of_g28() {
    // Z is assumed at 0 and lifted 4 mm before X and Y home; a G28 Z inside the script is the
    // printer's own; `axes: z` leaves a G28 X alone.
    let extra = "\n[homing_override]\naxes: z\nset_position_z: 0\ngcode:\n  G90\n  G1 Z4 F600\n  G28 Y\n  G28 X\n  G28 Z\n";
    let (run, paths) = print(
        "axes-homing-override",
        extra,
        "G28\nG28 X\nG1 X5 Y6 Z7 F1200\nM400\n",
    );
    assert_eq!(homing_order(&run.stdout), ["y", "x", "z", "x"], "{}", run.stdout);
    let z_max = peak_before_home(&paths[2]);
    assert!(
        (z_max - (START_MM + 4.0)).abs() <= 1.0 / 400.0 + 1e-9,
        "Z rose to {z_max} mm\n{}",
        run.stdout
    );
    for (a, want) in [(0, 5.0), (1, 6.0), (2, 7.0)] {
        let got = last(&paths[a]);
        assert!(
            (got - want).abs() <= TOL,
            "axis {a} ended at {got} mm, want {want}\n{}",
            run.stdout
        );
    }
}
