//! Several extruders and forced moves on the simulated printer: a live print whose MCU trace
//! shows each extruder stepper's steps (the inactive extruder's stepper does not move, the
//! active one's count is its E distance, a synced `[extruder_stepper]` follows), FORCE_MOVE's
//! and STEPPER_BUZZ's steps; the same G-code in batch mode passes `decode --check`.

use std::collections::HashMap;
use std::time::Duration;

use cadence_tests::{assert_success, bin, print_traced, run, scratch, workspace};
use firmware::trace::{read_trace, TraceRecord};

/// The example printer with `[extruder1]`, an unsynced `[extruder_stepper e2]`, FORCE_MOVE
/// enabled and Klipper's usual T0/T1 macros. Stepper oids: X 0, Y 1, Z 2, extruder 3,
/// extruder1 4, e2 5.
fn config() -> String {
    let base = std::fs::read_to_string(workspace().join("examples/simulated-cartesian.cfg"))
        .unwrap_or_else(|e| panic!("{e}"));
    format!(
        "{base}\n[extruder1]\nstep_pin: PD4\ndir_pin: PD5\nenable_pin: !PD6\nmicrosteps: 16\n\
         rotation_distance: 33.5\nnozzle_diameter: 0.4\nfilament_diameter: 1.75\nheater_pin: PE4\n\
         sensor_type: Generic 3950\nsensor_pin: PF2\ncontrol: watermark\nmin_temp: 0\nmax_temp: 250\n\
         min_extrude_temp: 0\n\n[extruder_stepper e2]\nextruder:\nstep_pin: PD8\ndir_pin: PD9\n\
         microsteps: 16\nrotation_distance: 33.5\n\n[force_move]\nenable_force_move: True\n\n\
         [gcode_macro T0]\ngcode:\n  ACTIVATE_EXTRUDER EXTRUDER=extruder\n\n\
         [gcode_macro T1]\ngcode:\n  ACTIVATE_EXTRUDER EXTRUDER=extruder1\n"
    )
}

/// Extruder moves (relative E): extruder 2 + 1 mm, extruder1 3 + 1 mm, e2 the last 1 mm of
/// extruder1's.
const MOVES: &str = "M83\nG1 X10 Y10 F6000\nG1 X20 E2 F1200\nT1\nG1 X30 E3\n\
SYNC_EXTRUDER_MOTION EXTRUDER=e2 MOTION_QUEUE=extruder1\nG1 X40 E1\nT0\nG1 X50 E1\n";

const E_STEP: f64 = 33.5 / 3200.0;

/// Steps from E `from` to `to` (the step grid anchored at 0 of the coordinate followed).
fn span(from: f64, to: f64) -> i64 {
    let index = |x: f64| (x / E_STEP + 0.5).floor() as i64;
    index(to) - index(from)
}

/// (net, total) steps per oid of a trace.
fn steps(path: &std::path::Path) -> (HashMap<u8, i64>, HashMap<u8, u64>) {
    let t = read_trace(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let (mut net, mut total) = (HashMap::new(), HashMap::new());
    for r in &t.records {
        match *r {
            TraceRecord::Step { oid, dir, .. } => {
                *net.entry(oid).or_default() += if dir { 1 } else { -1 };
                *total.entry(oid).or_default() += 1;
            }
            TraceRecord::Shutdown { .. } => panic!("the MCU shut down: {r:?}"),
            _ => {}
        }
    }
    (net, total)
}

#[test]
fn live_print_steps_only_the_active_extruder_and_forced_steppers() {
    let dir = scratch("extruders-live");
    let cfg = dir.join("printer.cfg");
    std::fs::write(&cfg, config()).unwrap_or_else(|e| panic!("{e}"));
    let gcode = dir.join("print.gcode");
    let text = format!(
        "SET_KINEMATIC_POSITION X=0 Y=0 Z=0\n{MOVES}FORCE_MOVE STEPPER=stepper_y DISTANCE=5 VELOCITY=10\n\
         STEPPER_BUZZ STEPPER=e2\nG1 X60 F6000\nM400\n"
    );
    std::fs::write(&gcode, text).unwrap_or_else(|e| panic!("{e}"));
    let trace = dir.join("trace.bin");
    let r = run(
        print_traced(&gcode, &cfg, &trace).args(["--no-progress", "--time-scale", "2"]),
        Duration::from_secs(300),
    );
    assert_success(&r);
    assert!(r.stdout.contains("Activating extruder extruder1"), "{}", r.stdout);
    let (net, total) = steps(&trace);
    // X 60 mm, Y 10 mm of moves + 5 mm forced (80 steps/mm), Z nothing.
    assert_eq!(net.get(&0), Some(&4800), "{net:?}");
    assert_eq!(net.get(&1), Some(&1200), "{net:?}");
    assert_eq!(net.get(&2).copied().unwrap_or(0), 0, "{net:?}");
    // extruder: E 0 → 2 while active, then 2 → 3 after T0 (it did not move meanwhile).
    assert_eq!(net.get(&3), Some(&span(0.0, 3.0)), "{net:?}");
    assert_eq!(
        total.get(&3).map(|&t| t as i64),
        Some(span(0.0, 3.0)),
        "{total:?}"
    );
    // extruder1: 0 → 4 while active.
    assert_eq!(net.get(&4), Some(&span(0.0, 4.0)), "{net:?}");
    // e2: extruder1's 3 → 4, then ten buzz cycles of 1 mm out and back.
    assert_eq!(net.get(&5), Some(&span(3.0, 4.0)), "{net:?}");
    let buzz = 2 * 10 * span(4.0, 5.0);
    assert_eq!(
        total.get(&5).map(|&t| t as i64),
        Some(span(3.0, 4.0) + buzz),
        "{total:?}"
    );
}

#[test]
fn batch_stream_of_several_extruders_checks() {
    let dir = scratch("extruders-batch");
    let cfg = dir.join("printer.cfg");
    std::fs::write(&cfg, config()).unwrap_or_else(|e| panic!("{e}"));
    let gcode = dir.join("print.gcode");
    std::fs::write(&gcode, format!("G28\n{MOVES}")).unwrap_or_else(|e| panic!("{e}"));
    let out = dir.join("out.bin");
    let s = |p: &std::path::Path| p.to_string_lossy().into_owned();
    let r = cadence_tests::cadence(
        &["print", &s(&gcode), "--config", &s(&cfg), "--batch", &s(&out)],
        Duration::from_secs(120),
    );
    assert_success(&r);
    let r = run(
        std::process::Command::new(bin("cadence")).args([
            "decode",
            &s(&out),
            "--check",
            &s(&gcode),
            "--config",
            &s(&cfg),
        ]),
        Duration::from_secs(120),
    );
    assert_success(&r);
    let line = |name: &str| {
        r.stdout
            .lines()
            .find(|l| l.trim_start().starts_with(name))
            .unwrap_or_else(|| panic!("no {name} line:\n{}", r.stdout))
            .to_string()
    };
    assert!(
        line("extruder1").contains(&format!("{} steps", span(0.0, 4.0))),
        "{}",
        r.stdout
    );
    assert!(
        line("e2").contains(&format!("{} steps", span(3.0, 4.0))),
        "{}",
        r.stdout
    );
}
