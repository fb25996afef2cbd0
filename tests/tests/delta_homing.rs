//! End to end: G28 on a delta printer homes its three towers live on the simulated printer
//! (each carriage up to its own endstop in the simulated world, the overshoot accounted
//! for) and puts the toolhead where forward kinematics of the three carriage heights says;
//! with one tower's `position_endstop` lower, the toolhead is off the centre as it would be on
//! Klipper. `position_endstop` is given in `[stepper_a]` only for towers B and C, as Klipper
//! defaults it. The toolhead then moves and the print ends cleanly.

use std::time::Duration;

use cadence_tests::{print_live, scratch};
use planner::kinematics::{DeltaGeometry, Kinematics};

const RADIUS: f64 = 100.0;
const ARM: f64 = 220.0;

/// A small delta (its towers 120 mm tall, 40 steps/mm: short homing moves); tower B's endstop
/// `b_endstop` (None: as tower A's, 120).
fn config(b_endstop: Option<f64>) -> String {
    let tower = |name: &str, pins: [&str; 4], endstop: Option<f64>| {
        let mut t = format!(
            "[stepper_{name}]\nstep_pin: {}\ndir_pin: {}\nenable_pin: !{}\nmicrosteps: 8\n\
             rotation_distance: 40\nendstop_pin: ^{}\nhoming_speed: 50\n",
            pins[0], pins[1], pins[2], pins[3]
        );
        if let Some(e) = endstop {
            t.push_str(&format!("position_endstop: {e}\n"));
        }
        if name == "a" {
            t.push_str(&format!("arm_length: {ARM}\n"));
        }
        t + "\n"
    };
    format!(
        "[mcu]\nserial: simulator\n\n[printer]\nkinematics: delta\nmax_velocity: 300\n\
         max_accel: 3000\nmax_z_velocity: 150\ndelta_radius: {RADIUS}\n\n{}{}{}",
        tower("a", ["PA0", "PA1", "PA2", "PA3"], Some(120.0)),
        tower("b", ["PA4", "PA5", "PA6", "PA7"], b_endstop),
        tower("c", ["PB0", "PB1", "PB2", "PB3"], None),
    )
}

/// `cadence print` of G28, M114, a short move, M114 on `cfg`: (X, Y, Z) of each M114.
fn home(name: &str, cfg: &str) -> Vec<[f64; 3]> {
    let dir = scratch(name);
    let cfg_path = dir.join("printer.cfg");
    std::fs::write(&cfg_path, cfg).unwrap();
    let gcode = dir.join("home.gcode");
    std::fs::write(&gcode, "G28\nM114\nG90\nG1 X5 Y5 Z110 F3000\nM400\nM114\n").unwrap();
    let run = print_live(&gcode, &cfg_path, "1", Duration::from_secs(300));
    assert_eq!(run.code, Some(0), "{}\n{}", run.stdout, run.stderr);
    for tower in ["homing x:", "homing y:", "homing z:"] {
        assert!(run.stdout.contains(tower), "no '{tower}' in\n{}", run.stdout);
    }
    run.stdout
        .lines()
        .filter_map(|l| l.split_once("M114 (line ").map(|(_, r)| r))
        .map(|r| {
            let v = |k: &str| -> f64 {
                r.split_whitespace()
                    .find_map(|w| w.strip_prefix(k))
                    .and_then(|v| v.parse().ok())
                    .unwrap_or_else(|| panic!("no {k} in {r}"))
            };
            [v("X:"), v("Y:"), v("Z:")]
        })
        .collect()
}

fn close(a: [f64; 3], b: [f64; 3], tol: f64) -> bool {
    a.iter().zip(&b).all(|(x, y)| (x - y).abs() <= tol)
}

/// Both printers, one after the other (side by side, a loaded machine's pauses could make a
/// trigger report miss the end of its homing move).
#[test]
fn g28_homes_the_three_towers_and_the_toolhead_follows() {
    let at = home("delta-home", &config(None));
    assert_eq!(at.len(), 2, "{at:?}");
    // The endstops agree: the centre at position_endstop (within the overshoot, a step or so).
    assert!(close(at[0], [0.0, 0.0, 120.0], 0.05), "{at:?}");
    assert!(close(at[1], [5.0, 5.0, 110.0], 1e-3), "{at:?}");

    // Tower B's endstop 5 mm lower: the toolhead homes off the centre, where the three
    // carriage heights put it.
    let at = home("delta-home-b", &config(Some(115.0)));
    let g = DeltaGeometry {
        radius: RADIUS,
        arm_length: [ARM; 3],
        angles: [210.0, 330.0, 90.0],
    };
    let offset = (ARM * ARM - RADIUS * RADIUS).sqrt();
    let expect = Kinematics::Delta(g).forward([120.0 + offset, 115.0 + offset, 120.0 + offset]);
    assert!(expect[0].hypot(expect[1]) > 1.0, "{expect:?}");
    assert!(close(at[0], expect, 0.05), "{at:?} vs {expect:?}");
}
