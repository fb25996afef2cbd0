//! End to end: PROBE / PROBE_ACCURACY / QUERY_PROBE on simulated two-MCU printers
//! (`cadence print`): the Z stepper on `mcu`, the probe on `probe_mcu`, so every probing move
//! needs the trigger relayed by the host. The simulated probe triggers where the Z axis reaches
//! `[simulator] bed_surface_z`, which the test chose: PROBE must measure it.
//!
//! Printers:
//! - "separate": examples/simulated-multi-mcu.cfg with 20 mm axes, the Z endstop moved to the
//!   main MCU (at Z = 0) and a `[probe]` on probe_mcu; the bed surface is at [`SURFACE`];
//! - "virtual": examples/simulated-probe.cfg with 20 mm axes: Z homes on the probe
//!   (`probe:z_virtual_endstop`), so the probe triggers at Z = z_offset ([`Z_OFFSET`]).

use std::path::{Path, PathBuf};
use std::time::Duration;

use cadence_tests::{
    assert_exit, assert_no_step_after_stop, assert_success, print_traced, retry_homing_timeouts, run,
    scratch, workspace, Run,
};

const TIMEOUT: Duration = Duration::from_secs(180);
/// Where the simulated probe triggers in the "separate" printer (not a whole step).
const SURFACE: f64 = 1.3791;
/// The "virtual" printer's z_offset (examples/simulated-probe.cfg).
const Z_OFFSET: f64 = 1.5;
/// Z mm per step.
const Z_STEP: f64 = 1.0 / 400.0;
/// The probe's sampling: a read every ≤ 1 ms, 4 × 15 µs to confirm.
const SAMPLING_S: f64 = 1e-3 + 4.0 * 15e-6;

/// Rewrites the example `name` with 20 mm axes (homing at 10 then 5 mm/s after a 2 mm
/// retract), applying `edit` to each trimmed line (`None`: keep) and appending `extra`.
fn config(dir: &Path, name: &str, edit: impl Fn(&str) -> Option<String>, extra: &str) -> PathBuf {
    let text = std::fs::read_to_string(workspace().join("examples").join(name)).expect("example");
    let mut out = String::new();
    for line in text.lines() {
        let l = line.split('#').next().unwrap_or_default().trim();
        let line = match l {
            "position_max: 220" | "position_max: 200" => "position_max: 20".to_string(),
            "homing_speed: 50" => "homing_speed: 10".to_string(),
            l if l.starts_with("[stepper_") => {
                format!("{line}\nhoming_retract_dist: 2\nsecond_homing_speed: 5")
            }
            l => edit(l).unwrap_or_else(|| line.to_string()),
        };
        out.push_str(&line);
        out.push('\n');
    }
    out.push_str(extra);
    let path = dir.join("printer.cfg");
    std::fs::write(&path, out).expect("write config");
    path
}

/// The "separate" printer, probing at `speed` mm/s.
fn separate(dir: &Path, speed: f64) -> PathBuf {
    config(
        dir,
        "simulated-multi-mcu.cfg",
        |l| match l {
            "endstop_pin: ^probe_mcu:PA3" => Some("endstop_pin: ^PC3".into()),
            "time_scale: 1.0" => Some(format!("time_scale: 1.0\nbed_surface_z: {SURFACE}")),
            _ => None,
        },
        &format!("\n[probe]\npin: ^probe_mcu:PA4\nz_offset: 1\nspeed: {speed}\nlift_speed: 10\n"),
    )
}

fn virtual_endstop(dir: &Path) -> PathBuf {
    config(dir, "simulated-probe.cfg", |_| None, "")
}

/// Like [`print`], but a run that ended in `Communication timeout during homing` is tried again
/// (up to 3 runs): on a CPU-starved machine the simulated MCUs can miss the 25 ms budget, a
/// legitimate outcome that is not what these tests are about (a wrong position never is).
fn print_ok(dir: &Path, cfg: &Path, gcode: &str) -> Run {
    retry_homing_timeouts(|| print(dir, cfg, gcode, None).0, |r| r)
}

/// `cadence print` of `gcode` on `cfg` (trace of the main MCU in `dir`), with `CADENCE_SIM_ARGS_PROBE_MCU`
/// set to `probe_args`.
fn print(dir: &Path, cfg: &Path, gcode: &str, probe_args: Option<&str>) -> (Run, PathBuf, PathBuf) {
    let g = dir.join("probe.gcode");
    std::fs::write(&g, gcode).expect("write gcode");
    let trace = dir.join("main.trace");
    let mut cmd = print_traced(&g, cfg, &trace);
    if let Some(a) = probe_args {
        cmd.env("CADENCE_SIM_ARGS_PROBE_MCU", a);
    }
    (run(&mut cmd, TIMEOUT), g, trace)
}

/// Every value after `key` in the output (`probe at X,Y is z=` → the z values).
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

fn assert_ok(run: &Run) {
    assert_success(run);
}

/// One step plus the sampling resolution at `speed`, plus the same again for the clock
/// conversion between the two MCUs (the trigger clock is on probe_mcu, the steps on mcu).
fn tolerance(speed: f64) -> f64 {
    2.0 * (Z_STEP + speed * SAMPLING_S) + 1e-9
}

#[test]
fn probe_measures_the_simulated_bed_surface() {
    let dir = scratch("probe-surface");
    let speed = 2.0;
    let cfg = separate(&dir, speed);
    let run = print_ok(
        &dir,
        &cfg,
        "G28 Z\nG1 Z4 F600\nQUERY_PROBE\nPROBE\nG1 Z4 F600\nPROBE SAMPLES=2 SAMPLES_RESULT=median\n",
    );
    assert_ok(&run);
    assert!(run.stdout.contains("probe: open"), "{}", run.stdout);
    let z = probed(&run.stdout);
    assert_eq!(z.len(), 3, "{}", run.stdout);
    let results = values(&run.stdout, "Result is z=");
    assert_eq!(results.len(), 2, "{}", run.stdout);
    let tol = tolerance(speed);
    for v in z.iter().chain(&results) {
        assert!(
            (v - SURFACE).abs() <= tol,
            "probed z={v}, the simulated surface is at {SURFACE} (tolerance {tol})\n{}",
            run.stdout
        );
    }
}

/// Corexz: Z is moved by motors A (x + z) and B (x − z), both on `mcu`; G28 homes X and Z with
/// both, and PROBE stops both on the probe's trigger relayed from probe_mcu. The "separate"
/// printer with corexz kinematics, A and B alike (Z's rotation_distance 40: 80 steps per mm).
#[test]
fn corexz_probe_stops_both_motors_and_measures_the_surface() {
    let dir = scratch("probe-corexz");
    let speed = 2.0;
    let cfg = config(
        &dir,
        "simulated-multi-mcu.cfg",
        |l| match l {
            "endstop_pin: ^probe_mcu:PA3" => Some("endstop_pin: ^PC3".into()),
            "time_scale: 1.0" => Some(format!("time_scale: 1.0\nbed_surface_z: {SURFACE}")),
            "kinematics: cartesian" => Some("kinematics: corexz".into()),
            "rotation_distance: 8" => Some("rotation_distance: 40".into()),
            _ => None,
        },
        &format!("\n[probe]\npin: ^probe_mcu:PA4\nz_offset: 1\nspeed: {speed}\nlift_speed: 10\n"),
    );
    let run = print_ok(
        &dir,
        &cfg,
        "G28\nG1 X10 Z4 F600\nPROBE\nG1 Z4 F600\nPROBE SAMPLES=2\n",
    );
    assert_ok(&run);
    for axis in ["x", "z"] {
        assert!(
            run.stdout.contains(&format!("homing {axis}: mcus mcu;")),
            "{}",
            run.stdout
        );
    }
    let z = probed(&run.stdout);
    assert_eq!(z.len(), 3, "{}", run.stdout);
    // A motor step moves Z by half a step of 1/80 mm; one step per motor, twice (homing and
    // probing each carry a trigger's sampling).
    let tol = 2.0 * (1.0 / 80.0 + 10.0 * SAMPLING_S) + 1e-9;
    for v in z.iter().chain(&values(&run.stdout, "Result is z=")) {
        assert!(
            (v - SURFACE).abs() <= tol,
            "probed z={v}, the simulated surface is at {SURFACE} (tolerance {tol})\n{}",
            run.stdout
        );
    }
    // The host's X, recomputed from the halted motors after each probe, stays where G1 put it
    // up to half a motor step (A and B may halt a step apart).
    let xs: Vec<f64> = run
        .stdout
        .lines()
        .filter_map(|l| l.split_once("probe at ")?.1.split(',').next()?.parse().ok())
        .collect();
    assert_eq!(xs.len(), 3, "{}", run.stdout);
    for x in xs {
        assert!(
            (x - 10.0).abs() <= 0.5 / 80.0 + 5e-4,
            "probe at X={x}\n{}",
            run.stdout
        );
    }
}

#[test]
fn z_homes_on_the_probe_virtual_endstop_and_probe_agrees() {
    let dir = scratch("probe-virtual");
    let cfg = virtual_endstop(&dir);
    let run = print_ok(
        &dir,
        &cfg,
        "G28\nG1 Z4 F600\nPROBE\nG1 Z4 F600\nPROBE_ACCURACY SAMPLES=2\n",
    );
    assert_ok(&run);
    assert!(
        run.stdout.contains("homing z: mcus probe_mcu+mcu"),
        "{}",
        run.stdout
    );
    let z = probed(&run.stdout);
    assert_eq!(z.len(), 3, "{}", run.stdout);
    // Homing and probing both carry the conversion error of a probe_mcu clock: twice.
    let tol = tolerance(10.0).max(2.0 * tolerance(5.0));
    for v in &z {
        assert!(
            (v - Z_OFFSET).abs() <= tol,
            "probed z={v}, the probe triggers at z_offset {Z_OFFSET} (tolerance {tol})\n{}",
            run.stdout
        );
    }
    assert!(
        run.stdout.contains("probe accuracy results: maximum "),
        "{}",
        run.stdout
    );
}

#[test]
fn probe_before_homing_is_refused() {
    let dir = scratch("probe-unhomed");
    let cfg = separate(&dir, 5.0);
    let (run, g, _) = print(&dir, &cfg, "G4 P10\nPROBE\n", None);
    assert_exit(&run, 1);
    let want = format!("cadence: error: {}:2: PROBE: Must home before probe", g.display());
    assert!(
        run.stderr.lines().any(|l| l == want),
        "want {want}\nstderr:\n{}",
        run.stderr
    );
}

#[test]
fn probe_already_triggered_is_refused() {
    // Z homes to 0 on its own endstop, below the bed surface: the probe reads triggered.
    let dir = scratch("probe-triggered");
    let cfg = separate(&dir, 5.0);
    let (run, g, _) = print(&dir, &cfg, "G28 Z\nPROBE\n", None);
    assert_exit(&run, 1);
    let want = format!(
        "cadence: error: {}:2: PROBE: Probe triggered prior to movement",
        g.display()
    );
    let timeout = format!(
        "cadence: error: {}:1: G28: Communication timeout during homing",
        g.display()
    );
    assert!(
        run.stderr.lines().any(|l| l == want || l == timeout),
        "want {want}\nstderr:\n{}",
        run.stderr
    );
}

#[test]
fn delayed_probe_mcu_fails_with_a_communication_timeout() {
    let dir = scratch("probe-delay");
    let cfg = separate(&dir, 5.0);
    let (run, g, trace) = print(&dir, &cfg, "G28 Z\nG1 Z4 F600\nPROBE\n", Some("--tx-delay-ms 30"));
    assert_exit(&run, 1);
    let want = format!(
        "cadence: error: {}:3: PROBE: Communication timeout during homing",
        g.display()
    );
    assert!(
        run.stderr.lines().any(|l| l == want),
        "want {want}\nstderr:\n{}",
        run.stderr
    );
    // The main MCU's trsync stopped Z, and Z took no step after that.
    assert_no_step_after_stop(&trace, None, 2);
}

#[test]
fn bad_probe_options_are_config_errors() {
    let dir = scratch("probe-config");
    let cases = [
        ("speed: 0", "[probe] speed: must be above 0, got 0"),
        ("samples: 0", "[probe] samples: must have minimum of 1, got 0"),
        (
            "samples_result: mode",
            "[probe] samples_result: expected one of median, average, got 'mode'",
        ),
        (
            "pin: ^nope:PA4",
            "[probe] pin: pin '^nope:PA4' refers to mcu 'nope', but there is no [mcu nope] section",
        ),
    ];
    for (bad, want) in cases {
        let key = bad.split(':').next().unwrap_or_default();
        let cfg = config(
            &dir,
            "simulated-probe.cfg",
            |l| l.starts_with(&format!("{key}:")).then(|| bad.to_string()),
            "",
        );
        let (run, _, _) = print(&dir, &cfg, "G28\n", None);
        assert_eq!(run.code, Some(1), "{bad}: stderr:\n{}", run.stderr);
        let line = run
            .stderr
            .lines()
            .find(|l| l.starts_with("cadence: error: "))
            .unwrap_or_default();
        assert!(
            line.starts_with(&format!("cadence: error: {}:", cfg.display())) && line.ends_with(want),
            "{bad}: want …{want}\nstderr:\n{}",
            run.stderr
        );
    }
}
