//! End to end: BED_MESH_CALIBRATE and SCREWS_TILT_CALCULATE on a tilted and warped simulated bed,
//! BED_SCREWS_ADJUST going round the screws,
//! Z_TILT_ADJUST and QUAD_GANTRY_LEVEL on a tilted gantry (`cadence print` on
//! examples/simulated-probe.cfg with 20 mm axes; Z homes on the probe, which sits on
//! probe_mcu, so every probe's trigger is relayed by the host within the 25 ms budget).
//!
//! The truth is the simulator's surface `h(x, y) = TILT_X·x + TILT_Y·y + WARP·sin(2πx/P)·sin(2πy/P)`
//! (`[simulator] bed_tilt_x/bed_tilt_y/bed_warp/bed_warp_period`): the probe triggers where
//! the world's Z reaches `bed_surface_z + h` at the probe's X, Y. Z homes at a known X, Y, so the
//! mesh at a probed point must be `h(point) − h(probe at homing)`; and a first-layer move's
//! nozzle height, rebuilt from the main MCU's step trace (not from the host's numbers), must
//! follow `h` under the nozzle.

use std::path::{Path, PathBuf};
use std::time::Duration;

use cadence_tests::{assert_success, print_traced, retry_homing_timeouts, run, scratch, workspace, Run};
use firmware::trace::{read_trace, TraceRecord};

const TIMEOUT: Duration = Duration::from_secs(300);
const TILT: [f64; 2] = [0.012, -0.007];
const WARP: f64 = 0.06;
const PERIOD: f64 = 30.0;
/// The probe's offsets from the nozzle.
const OFFSET: [f64; 2] = [2.0, 1.0];
const Z_OFFSET: f64 = 1.5;
/// Where the nozzle is when Z homes on the probe.
const HOME_XY: [f64; 2] = [10.0, 10.0];
/// The brief's bound.
const TOLERANCE: f64 = 0.02;
/// X/Y and Z steps per mm (rotation_distance 40 and 8, 16 microsteps).
const XY_STEPS: f64 = 80.0;
const Z_STEPS: f64 = 400.0;
/// Stepper oids on the main MCU (config order).
const OID: [u8; 3] = [0, 1, 2];

/// The simulated bed height at bed point (x, y).
fn h(x: f64, y: f64) -> f64 {
    let k = std::f64::consts::TAU / PERIOD;
    TILT[0] * x + TILT[1] * y + WARP * (k * x).sin() * (k * y).sin()
}

/// examples/simulated-probe.cfg with 20 mm axes, the shaped bed, probe offsets and `mesh`;
/// with `main_mcu` the probe is on the main MCU (the steppers' own, as on most printers), else
/// on probe_mcu (every trigger relayed by the host).
fn config(dir: &Path, mesh: &str, main_mcu: bool) -> PathBuf {
    config_with(dir, mesh, main_mcu, true)
}

/// [`config`], the bed flat unless `shaped`.
fn config_with(dir: &Path, mesh: &str, main_mcu: bool, shaped: bool) -> PathBuf {
    let text = std::fs::read_to_string(workspace().join("examples/simulated-probe.cfg")).expect("example");
    let mut out = String::new();
    for line in text.lines() {
        let l = line.split('#').next().unwrap_or_default().trim();
        let line = match l {
            "position_max: 220" | "position_max: 200" => "position_max: 20".to_string(),
            "homing_speed: 50" => "homing_speed: 10".to_string(),
            "speed: 5" => format!("speed: 2\nlift_speed: 10\nx_offset: {}\ny_offset: {}", OFFSET[0], OFFSET[1]),
            "bed_surface_z: 0" if !shaped => format!("bed_surface_z: 0\ngantry_tilt: {}", gantry_tilt(mesh)),
            "bed_surface_z: 0" => format!(
                "bed_surface_z: 0\nbed_tilt_x: {}\nbed_tilt_y: {}\nbed_warp: {WARP}\nbed_warp_period: {PERIOD}",
                TILT[0], TILT[1]
            ),
            l if l.starts_with("[stepper_") => format!("{line}\nhoming_retract_dist: 2\nsecond_homing_speed: 2"),
            "pin: ^probe_mcu:PA4" if main_mcu => "pin: ^PA4".to_string(),
            _ => line.to_string(),
        };
        out.push_str(&line);
        out.push('\n');
    }
    out.push_str(mesh);
    if main_mcu {
        out = out.replace("[mcu probe_mcu]\nserial: simulator\n", "");
    }
    let path = dir.join("printer.cfg");
    std::fs::write(&path, out).expect("write config");
    path
}

fn print(dir: &Path, cfg: &Path, gcode: &str) -> (Run, PathBuf) {
    let g = dir.join("mesh.gcode");
    std::fs::write(&g, gcode).expect("write gcode");
    let trace = dir.join("main.trace");
    let run = retry_homing_timeouts(|| run(&mut print_traced(&g, cfg, &trace), TIMEOUT), |r| r);
    (run, trace)
}

/// The `WHO: N probe passes, stop at most A..B us after trigger` line of `out`, checked: the
/// latest stop bound of every pass is within the 25 ms budget.
fn within_budget<'o>(out: &'o str, who: &str) -> &'o str {
    let line = out
        .lines()
        .find(|l| l.contains(&format!("{who}: ")) && l.contains("probe passes"))
        .unwrap_or_default();
    eprintln!("{line}");
    let worst_us: f64 = line
        .split_once("stop at most ")
        .and_then(|(_, r)| r.split_once("..")?.1.split_whitespace().next()?.parse().ok())
        .unwrap_or_else(|| panic!("no latency line\n{out}"));
    assert!(worst_us < 25_000.0, "{line}");
    line
}

/// (nozzle x, y, z) of every `probe at X,Y is z=Z` line.
fn probed(stdout: &str) -> Vec<[f64; 3]> {
    stdout
        .lines()
        .filter_map(|l| {
            let rest = l.split_once("probe at ")?.1;
            let (xy, z) = rest.split_once(" is z=")?;
            let (x, y) = xy.split_once(',')?;
            Some([x.parse().ok()?, y.parse().ok()?, z.trim().parse().ok()?])
        })
        .collect()
}

/// The rows under `Measured points:` (top row first, as printed).
fn measured(stdout: &str) -> Vec<Vec<f64>> {
    stdout
        .lines()
        .skip_while(|l| !l.contains("Measured points:"))
        .skip(1)
        .map_while(|l| {
            let v: Option<Vec<f64>> = l.split_whitespace().map(|w| w.parse().ok()).collect();
            v.filter(|v| !v.is_empty())
        })
        .collect()
}

const MESH: &str =
    "\n[bed_mesh]\nmesh_min: 3, 2\nmesh_max: 19, 18\nprobe_count: 5, 5\nhorizontal_move_z: 3\nspeed: 100\n\
                    split_delta_z: 0.01\nmove_check_distance: 3\n";

#[test]
fn bed_mesh_calibrate_measures_the_warped_bed_and_the_first_layer_follows_it() {
    let dir = scratch("bed-mesh-warped");
    let cfg = config(&dir, MESH, true);
    let gcode = format!(
        "G28 X Y\nG1 X{} Y{} F3000\nG28 Z\nBED_MESH_CALIBRATE\nBED_MESH_OUTPUT\n\
         G1 Z0.3 F600\nG1 X4 Y16 F3000\nG4 P300\nG1 X17 Y16 F600\nG4 P300\n",
        HOME_XY[0], HOME_XY[1]
    );
    let (run, trace) = print(&dir, &cfg, &gcode);
    assert_success(&run);
    let out = &run.stdout;
    // The homing/probing latency figures: every pass stopped within the 25 ms budget.
    let line = within_budget(out, "bed_mesh");
    assert!(line.contains("25 probe passes"), "{line}\n{out}");
    assert!(out.contains("homing z: mcus mcu;"), "{out}");

    // Each probe point: the probe's Z is z_offset + h(probe) − h(probe at homing).
    let href = h(HOME_XY[0] + OFFSET[0], HOME_XY[1] + OFFSET[1]);
    let points = probed(out);
    assert_eq!(points.len(), 25, "{out}");
    let mut worst: f64 = 0.0;
    for [x, y, z] in &points {
        let want = Z_OFFSET + h(x + OFFSET[0], y + OFFSET[1]) - href;
        worst = worst.max((z - want).abs());
        assert!(
            (z - want).abs() <= TOLERANCE,
            "probe at {x},{y}: z={z}, surface says {want}\n{out}"
        );
    }
    eprintln!("bed_mesh: probed points within {worst:.4} mm of the true surface");
    // The mesh (BED_MESH_OUTPUT, top row first) is the probed heights minus z_offset.
    let rows = measured(out);
    assert_eq!(rows.len(), 5, "{out}");
    for (r, row) in rows.iter().rev().enumerate() {
        assert_eq!(row.len(), 5, "{out}");
        for (c, v) in row.iter().enumerate() {
            let (x, y) = (3.0 + 4.0 * c as f64, 2.0 + 4.0 * r as f64);
            let want = h(x, y) - href;
            assert!(
                (v - want).abs() <= TOLERANCE,
                "mesh ({c},{r}) at {x},{y}: {v}, surface says {want}\n{out}"
            );
        }
    }

    // The first-layer move X4 Y16 → X17 Y16 at Z0.3 (inside the mesh: outside it the edge holds), from the MCU's executed steps: the
    // nozzle's height above the bed stays what it was at the move's start.
    let t = read_trace(&trace).expect("trace");
    let mut steps: Vec<(u64, u8, bool)> = t
        .records
        .iter()
        .filter_map(|r| match *r {
            TraceRecord::Step { oid, dir, clock, .. } => Some((clock, oid, dir)),
            _ => None,
        })
        .collect();
    steps.sort_by_key(|s| s.0);
    // The move starts after the last pause of more than 200 ms between steps.
    let gap = (0.2 * t.clock_freq as f64) as u64;
    let start = steps
        .windows(2)
        .rposition(|w| w[1].0 - w[0].0 > gap)
        .map(|i| i + 1)
        .expect("a pause before the layer move");
    let layer = &steps[start..];
    let mut pos = [0i64; 3];
    let mut worst: f64 = 0.0;
    let mut rise: f64 = 0.0;
    let (x0, y0) = (4.0, 16.0);
    for &(_, oid, dir) in layer {
        if let Some(axis) = OID.iter().position(|&o| o == oid) {
            pos[axis] += if dir { 1 } else { -1 };
        }
        let (x, y) = (x0 + pos[0] as f64 / XY_STEPS, y0 + pos[1] as f64 / XY_STEPS);
        let dz = pos[2] as f64 / Z_STEPS;
        let err = dz - (h(x, y) - h(x0, y0));
        worst = worst.max(err.abs());
        rise = rise.max((h(x, y) - h(x0, y0)).abs());
    }
    let end = [x0 + pos[0] as f64 / XY_STEPS, y0 + pos[1] as f64 / XY_STEPS];
    assert!(
        (end[0] - 17.0).abs() < 0.02 && (end[1] - 16.0).abs() < 0.02,
        "the layer move ends at {end:?}"
    );
    eprintln!(
        "bed_mesh: first layer over {rise:.3} mm of bed height change followed the surface within {worst:.4} mm"
    );
    assert!(worst <= TOLERANCE, "nozzle height off the surface by {worst} mm");
    // Without the mesh the nozzle would be off by the surface's own change.
    assert!(
        rise > 5.0 * TOLERANCE,
        "the test surface must change along the move: {rise}"
    );
}

#[test]
fn profiles_save_load_remove_and_save_config() {
    let dir = scratch("bed-mesh-profiles");
    let cfg = config(&dir, MESH, false);
    let (run, _) = print(
        &dir,
        &cfg,
        "BED_MESH_OUTPUT\nG28 X Y\nG1 X10 Y10 F3000\nG28 Z\nBED_MESH_CALIBRATE PROFILE=pla PROBE_COUNT=3 ALGORITHM=lagrange\n\
         BED_MESH_PROFILE SAVE=copy\nBED_MESH_CLEAR\nBED_MESH_OUTPUT\nBED_MESH_PROFILE LOAD=copy\nBED_MESH_OUTPUT\n\
         BED_MESH_PROFILE REMOVE=pla\nSAVE_CONFIG\n",
    );
    assert_success(&run);
    let all = format!("{}{}", run.stdout, run.stderr);
    assert!(all.contains("Bed has not been probed"), "{all}");
    assert!(all.contains("Profile [pla] removed from storage"), "{all}");
    assert_eq!(measured(&run.stdout).len(), 3, "{all}");
    // Every probe's trigger came from probe_mcu, relayed within the 25 ms budget.
    assert!(all.contains("homing z: mcus probe_mcu+mcu"), "{all}");
    assert!(all.contains("bed_mesh: 9 probe passes, stop at most"), "{all}");
    let saved = std::fs::read_to_string(&cfg).expect("config");
    assert!(saved.contains("#*# [bed_mesh copy]"), "{saved}");
    assert!(!saved.contains("[bed_mesh pla]"), "{saved}");
    // The saved profile loads on the next run; an unknown one is an error naming it.
    let (run, _) = print(&dir, &cfg, "BED_MESH_PROFILE LOAD=copy\nBED_MESH_OUTPUT\n");
    assert_success(&run);
    assert_eq!(measured(&run.stdout).len(), 3, "{}", run.stdout);
    let (run, _) = print(&dir, &cfg, "BED_MESH_PROFILE LOAD=nope\n");
    assert!(
        run.stderr
            .contains("mesh.gcode:1: BED_MESH_PROFILE: bed_mesh: Unknown profile [nope]"),
        "{}",
        run.stderr
    );
}

/// The simulated gantry's tilt for a config with `extra`: four corner motors bent out of a
/// plane for `[quad_gantry_level]`, else `[stepper_z1]`'s end 0.4 mm high.
fn gantry_tilt(extra: &str) -> &'static str {
    match extra.contains("[quad_gantry_level]") {
        true => QGL_TILT,
        false => "0, 0.4",
    }
}

/// Where each corner of the QGL gantry starts (not one plane: 0 + 0.5 ≠ 0.3 + 0.1).
const QGL_TILT: &str = "0, 0.3, 0.5, 0.1";

/// Two Z motors, `[stepper_z1]`'s end of the gantry 0.4 mm high.
const Z_TILT: &str =
    "\n[stepper_z1]\nstep_pin: PG0\ndir_pin: PG1\nenable_pin: !PG2\nmicrosteps: 16\nrotation_distance: 8\n\
                      \n[z_tilt]\nz_positions:\n  -5, 10\n  25, 10\npoints:\n  2, 10\n  16, 10\nspeed: 50\n\
                      horizontal_move_z: 3\nretries: 5\nretry_tolerance: 0.01\n";

/// Z_TILT_ADJUST on a gantry tilted 0.4 mm across its two motors: it converges (the probed
/// range within retry_tolerance), and the MCU's own step counts show the two motors' ends level.
#[test]
fn z_tilt_adjust_levels_a_tilted_gantry() {
    let dir = scratch("z-tilt");
    let cfg = config_with(&dir, Z_TILT, true, false);
    let (run, trace) = print(
        &dir,
        &cfg,
        &format!(
            "G28 X Y\nG1 X{} Y{} F3000\nG28 Z\nZ_TILT_ADJUST\nBED_MESH_CALIBRATE\n",
            HOME_XY[0], HOME_XY[1]
        ),
    );
    assert_success(&run);
    let out = &run.stdout;
    let ranges: Vec<f64> = out
        .lines()
        .filter_map(|l| {
            l.split_once("Probed points range: ")?
                .1
                .split_whitespace()
                .next()?
                .parse()
                .ok()
        })
        .collect();
    eprintln!("z_tilt: probed ranges {ranges:?}");
    assert!(ranges.len() >= 2, "{out}");
    assert!(ranges[0] > 0.15, "the tilt is seen first: {ranges:?}");
    assert!(
        ranges.last().is_some_and(|&r| r <= 0.01),
        "converged: {ranges:?}\n{out}"
    );
    assert!(out.contains("Making the following Z adjustments:"), "{out}");
    within_budget(out, "z_tilt");
    // Without [bed_mesh] its commands are unknown commands: skipped, the print goes on (the
    // run succeeded above).
    // From the trace: z (oid 2) and z1 (oid 3) net steps; z1 started 0.4 mm higher.
    let t = read_trace(&trace).expect("trace");
    let net = cadence_tests::net_steps(&t);
    let z0 = *net.get(&2).unwrap_or(&0) as f64 / Z_STEPS;
    let z1 = 0.4 + *net.get(&3).unwrap_or(&0) as f64 / Z_STEPS;
    eprintln!("z_tilt: motor ends after adjusting: stepper_z {z0:.4}, stepper_z1 {z1:.4} (relative to stepper_z's start)");
    assert!(
        (z1 - z0).abs() <= TOLERANCE,
        "gantry ends differ by {} mm\n{out}",
        z1 - z0
    );
}

/// SCREWS_TILT_CALCULATE on the tilted, warped bed: each screw's height is the surface's, and
/// the turns (CW-M3, 0.5 mm per turn) bring it to the base screw's.
#[test]
fn screws_tilt_calculate_reports_the_turns_of_the_true_surface() {
    let dir = scratch("screws-tilt");
    let screws = "\n[screws_tilt_adjust]\nscrew1: 2, 2\nscrew1_name: front left screw\nscrew2: 17, 2\n\
                  screw2_name: front right screw\nscrew3: 10, 17\nscrew3_name: rear screw\nhorizontal_move_z: 3\n\
                  \n[bed_screws]\nscrew1: 2, 2\nscrew2: 17, 2\nscrew3: 10, 17\n";
    let cfg = config(&dir, screws, true);
    let (run, _) = print(
        &dir,
        &cfg,
        &format!(
            "G28 X Y\nG1 X{} Y{} F3000\nG28 Z\nSCREWS_TILT_CALCULATE\n",
            HOME_XY[0], HOME_XY[1]
        ),
    );
    assert_success(&run);
    let out = &run.stdout;
    assert!(
        out.contains("01:20 means 1 full turn and 20 minutes, CW=clockwise, CCW=counter-clockwise"),
        "{out}"
    );
    let href = h(HOME_XY[0] + OFFSET[0], HOME_XY[1] + OFFSET[1]);
    let bed = |x: f64, y: f64| Z_OFFSET + h(x + OFFSET[0], y + OFFSET[1]) - href;
    let base = bed(2.0, 2.0);
    let mut seen = 0;
    for line in out.lines().filter(|l| l.contains(" : x=")) {
        let field = |k: &str| -> f64 {
            line.split_once(k)
                .and_then(|(_, r)| r.split([',', ' ']).next()?.parse().ok())
                .unwrap_or(f64::NAN)
        };
        let (x, y, z) = (field("x="), field("y="), field("z="));
        assert!(
            (z - bed(x, y)).abs() <= TOLERANCE,
            "{line}: the surface is at {}",
            bed(x, y)
        );
        if let Some((_, adj)) = line.split_once(" : adjust ") {
            let (dir, hm) = adj.split_once(' ').unwrap_or_default();
            let (hh, mm) = hm.split_once(':').unwrap_or_default();
            let minutes =
                hh.parse::<f64>().unwrap_or(f64::NAN) * 60.0 + mm.parse::<f64>().unwrap_or(f64::NAN);
            let want = (base - bed(x, y)) / 0.5 * 60.0;
            assert_eq!(dir, if want >= 0.0 { "CW" } else { "CCW" }, "{line}");
            // 0.02 mm is 2.4 minutes of a 0.5 mm turn.
            assert!(
                (minutes - want.abs()).abs() <= 3.0,
                "{line}: want {want:.1} minutes"
            );
        }
        seen += 1;
    }
    assert_eq!(seen, 3, "{out}");
}

/// BED_SCREWS_ADJUST takes the nozzle to each screw at `probe_height` and waits for ACCEPT or
/// ADJUSTED; after an ADJUSTED it goes round until every screw is accepted in a row, then the
/// fine-adjust points, then up to `horizontal_move_z`. The MCU's step counts show where the
/// nozzle ended.
#[test]
fn bed_screws_adjust_goes_round_the_screws_until_all_are_accepted() {
    let dir = scratch("bed-screws");
    let screws = "\n[bed_screws]\nscrew1: 2, 2\nscrew1_name: front left\nscrew2: 17, 2\nscrew3: 10, 17\n\
                  screw3_fine_adjust: 12, 15\nprobe_height: 0.2\nhorizontal_move_z: 4\n";
    let cfg = config(&dir, screws, true);
    let (run, _) = print(&dir, &cfg, "BED_SCREWS_ADJUST\n");
    assert!(
        run.code != Some(0) && run.stderr.contains("BED_SCREWS_ADJUST: Must home axis first: X"),
        "{}",
        run.stderr
    );
    let answers = "ACCEPT\nADJUSTED\nACCEPT\nACCEPT\nACCEPT\nACCEPT\n";
    let (run, _) = print(&dir, &cfg, &format!("G28\nBED_SCREWS_ADJUST\n{answers}ACCEPT\n"));
    assert_success(&run);
    let prompts: Vec<&str> = run
        .stderr
        .lines()
        .filter_map(|l| {
            l.split_once("warning: Adjust ")?
                .1
                .split_once(". Then run ACCEPT")
        })
        .map(|(screw, _)| screw)
        .collect();
    // front left, 17,2 turned, back, then round: front left and 17,2 make three in a row;
    // then the back screw's fine point.
    let (fl, fr, back) = ("front left", "screw at 17.000,2.000", "screw at 10.000,17.000");
    assert_eq!(prompts, [fl, fr, back, fl, fr, back], "{}", run.stderr);
    assert!(
        run.stderr.contains("Bed screws tool completed successfully"),
        "{}",
        run.stderr
    );
    // The last ACCEPT came after the tool ended: an unknown command, as in Klipper.
    assert!(
        run.stderr.contains("Unknown command:\"ACCEPT\""),
        "{}",
        run.stderr
    );
    // Ended over the fine point, up at horizontal_move_z.
    let mm = |stepper: &str| -> f64 {
        let row = run.stdout.lines().find(|l| l.trim_start().starts_with(stepper));
        let row = row.unwrap_or_else(|| panic!("no {stepper} row:\n{}", run.stdout));
        row.split_whitespace()
            .last()
            .and_then(|v| v.parse().ok())
            .unwrap_or(f64::NAN)
    };
    assert_eq!(
        (mm("stepper_x "), mm("stepper_y "), mm("stepper_z ")),
        (12.0, 15.0, 4.0),
        "{}",
        run.stdout
    );
}

/// Four corner motors for `[quad_gantry_level]` (front left, back left, back right, front right).
const QGL: &str = "\n[stepper_z1]\nstep_pin: PG0\ndir_pin: PG1\nenable_pin: !PG2\nmicrosteps: 16\nrotation_distance: 8\n\
                   \n[stepper_z2]\nstep_pin: PG3\ndir_pin: PG4\nenable_pin: !PG5\nmicrosteps: 16\nrotation_distance: 8\n\
                   \n[stepper_z3]\nstep_pin: PG6\ndir_pin: PG7\nenable_pin: !PG8\nmicrosteps: 16\nrotation_distance: 8\n\
                   \n[quad_gantry_level]\ngantry_corners:\n  -5, -5\n  25, 25\npoints:\n  2, 2\n  2, 16\n  16, 16\n  16, 2\n\
                   speed: 50\nhorizontal_move_z: 3\nmax_adjust: 2\nretries: 5\nretry_tolerance: 0.01\n";

/// QUAD_GANTRY_LEVEL on a gantry whose four corners start bent out of a plane: it converges,
/// and the MCU's step counts show the four corners level.
#[test]
fn quad_gantry_level_levels_a_bent_gantry() {
    let dir = scratch("qgl");
    let cfg = config_with(&dir, QGL, true, false);
    let (run, trace) = print(
        &dir,
        &cfg,
        &format!(
            "G28 X Y\nG1 X{} Y{} F3000\nG28 Z\nQUAD_GANTRY_LEVEL\n",
            HOME_XY[0], HOME_XY[1]
        ),
    );
    assert_success(&run);
    let out = &run.stdout;
    assert!(out.contains("Making the following Z adjustments:"), "{out}");
    assert!(out.contains("Retries: 1/5"), "{out}");
    within_budget(out, "quad_gantry_level");
    let t = read_trace(&trace).expect("trace");
    let net = cadence_tests::net_steps(&t);
    let start: Vec<f64> = QGL_TILT
        .split(',')
        .map(|v| v.trim().parse().unwrap_or(f64::NAN))
        .collect();
    // Oids: x 0, y 1, z 2, z1 3, z2 4, z3 5.
    let ends: Vec<f64> = (0..4)
        .map(|i| start[i] + *net.get(&(2 + i as u8)).unwrap_or(&0) as f64 / Z_STEPS)
        .collect();
    eprintln!("quad_gantry_level: corner heights after levelling {ends:?}");
    let spread = ends.iter().copied().fold(f64::NEG_INFINITY, f64::max)
        - ends.iter().copied().fold(f64::INFINITY, f64::min);
    assert!(spread <= TOLERANCE, "corners differ by {spread} mm\n{out}");
}
