//! End to end: steppers on a second MCU (examples/simulated-toolboard.cfg: X, Y on `mcu`, Z
//! and the extruder on `toolboard`, the Z endstop on `mcu`). A print streams each MCU its own
//! steps in its own clock (here the toolboard runs a 16 MHz clock next to the main 50 MHz
//! one); homing Z relays the main MCU's endstop trigger to the toolboard. The simulated MCUs'
//! step traces say what really happened; the host must agree with them.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use cadence_tests::{
    assert_exit, assert_no_step_after_stop, assert_success, bin, check_trace, home_traced, homing_timed_out,
    net_steps, print_traced, retry_homing_timeouts, run, scratch, short_homing_config, workspace, Run,
};
use firmware::trace::{read_trace, TraceRecord};

const TIMEOUT: Duration = Duration::from_secs(180);
/// The toolboard as a 16 MHz board (its own CLOCK_FREQ, its own clock offset).
const TOOLBOARD_16MHZ: &str = "--clock-freq 16000000";
/// Object ids on the toolboard: Z stepper 0, extruder 1, two enable pins (2, 3), trsync 4.
const Z_OID: u8 = 0;
const E_OID: u8 = 1;
const TOOLBOARD_TRSYNC_OID: u8 = 4;
/// Z: 400 steps per mm, starts 10% of its travel above the endstop at 0 (src/hardware.rs).
const Z_STEPS_PER_MM: f64 = 400.0;
/// Second-pass speed of the short-travel config, and the endstop's sampling: a read every
/// ≤ 1 ms, 4 × 15 µs to confirm.
const SECOND_SPEED: f64 = 5.0;
const SAMPLING_S: f64 = 1e-3 + 4.0 * 15e-6;

fn example() -> String {
    std::fs::read_to_string(workspace().join("examples/simulated-toolboard.cfg")).expect("example")
}

/// The toolboard example with 20 mm axes and a second homing pass (homing takes seconds).
fn short_config(dir: &Path) -> PathBuf {
    short_homing_config(dir, "simulated-toolboard.cfg")
}

/// The toolboard example as it is, written to `dir/printer.cfg`.
fn example_config(dir: &Path) -> PathBuf {
    let cfg = dir.join("printer.cfg");
    std::fs::write(&cfg, example()).expect("write config");
    cfg
}

/// `…/name.trace` → `…/name-toolboard.trace` (the host's naming of other MCUs' traces).
fn toolboard_trace(trace: &Path) -> PathBuf {
    trace.with_file_name(format!(
        "{}-toolboard.trace",
        trace.file_stem().and_then(|s| s.to_str()).expect("stem")
    ))
}

#[test]
fn square_prints_on_two_mcus_with_their_own_clocks() {
    let dir = scratch("toolboard-square");
    let cfg = example_config(&dir);
    let trace = dir.join("square.trace");
    let gcode = workspace().join("examples/square.gcode");
    let print = |trace: &Path| {
        let mut cmd = print_traced(&gcode, &cfg, trace);
        cmd.env("CADENCE_SIM_ARGS_TOOLBOARD", TOOLBOARD_16MHZ);
        run(&mut cmd, TIMEOUT)
    };
    // G28 homes Z across the MCUs: a starved VM can miss the 25 ms budget, which ends the run
    // with exactly the timeout error; that run is tried again (at most 3 runs).
    let run = retry_homing_timeouts(|| print(&trace), |r| r);
    assert_success(&run);
    // The binary itself compares every stepper's MCU position with the host's at the end (a
    // mismatch fails the print); the summary shows both MCUs' lead.
    for mcu in ["mcu", "toolboard"] {
        assert!(
            run.stdout.contains(&format!("mcu '{mcu}': min lead margin")),
            "no lead figure for {mcu}:\n{}",
            run.stdout
        );
    }
    assert!(
        run.stdout.contains("homing z: mcus mcu+toolboard"),
        "{}",
        run.stdout
    );

    let main = check_trace(&trace);
    let tool = check_trace(&toolboard_trace(&trace));
    for (name, t) in [("mcu", &main), ("toolboard", &tool)] {
        assert!(t.queue_steps > 0, "{name}: no queue_step was received");
        assert!(
            t.min_lead_ms >= 100.0,
            "{name}: a queue_step arrived with only {:.2} ms lead",
            t.min_lead_ms
        );
    }
    // Where the axes ended (examples/square.gcode: X10 Y10 Z5, E 4 + 4 − 0.8 mm), from where the
    // simulated carriages started (10% of the travel from the endstops at 0).
    let e_dist = 33.5 / 3200.0;
    let expected = [
        (&main, 0u8, (10.0 - 22.0) * 80.0),
        (&main, 1, (10.0 - 22.0) * 80.0),
        (&tool, Z_OID, (5.0 - 20.0) * Z_STEPS_PER_MM),
        (&tool, E_OID, (4.0 + 4.0 - 0.8) / e_dist),
    ];
    for (t, oid, want) in expected {
        let got = t.net.get(&oid).copied().unwrap_or(0) as f64;
        // ±1 step of rounding, ±1 of endstop sampling.
        assert!(
            (got - want).abs() <= 2.0,
            "oid {oid}: {got} net steps, commanded {want:.2}\n{}",
            run.stdout
        );
    }
    // Both MCUs run the last move (X on mcu, Z on the toolboard) at the same time: the
    // toolboard's steps were planned in its own clock through the host's clock fits. Off by
    // the fits' error (tens of µs here); a wrong clock mapping is off by whole milliseconds
    // to seconds. The margin covers a badly disturbed clock sync on a loaded VM.
    let skew = last_move_skew(&trace, &toolboard_trace(&trace));
    assert!(skew.len() >= 50, "too few steps compared: {}", skew.len());
    let worst = skew.iter().fold(0.0f64, |m, s| m.max(s.abs()));
    println!(
        "last move, toolboard Z vs main X: skew median {:.1} us, worst {:.1} us over {} steps",
        median(&skew) * 1e6,
        worst * 1e6,
        skew.len()
    );
    assert!(
        worst < 3e-3,
        "the MCUs ran the last move {worst} s apart: {skew:?}"
    );
}

fn median(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s.get(s.len() / 2).copied().unwrap_or(f64::NAN)
}

fn home_z(dir: &Path, toolboard_args: &str) -> (Run, PathBuf) {
    let cfg = short_config(dir);
    let trace = dir.join("home.trace");
    let mut cmd = home_traced("z", &cfg, &trace);
    cmd.env("CADENCE_SIM_ARGS_TOOLBOARD", toolboard_args);
    (run(&mut cmd, TIMEOUT), toolboard_trace(&trace))
}

/// The `homed position: x=… y=… z=…` line's z.
fn homed_z(stdout: &str) -> f64 {
    let line = stdout
        .lines()
        .find_map(|l| l.strip_prefix("homed position: "))
        .unwrap_or_else(|| panic!("no homed position in:\n{stdout}"));
    line.split_whitespace()
        .find_map(|f| f.strip_prefix("z="))
        .and_then(|v| v.parse().ok())
        .expect("z")
}

fn overshoots(stdout: &str) -> Vec<f64> {
    stdout
        .split("overshoot ")
        .skip(1)
        .filter_map(|s| s.split_whitespace().next()?.parse().ok())
        .collect()
}

#[test]
fn z_on_the_toolboard_homes_on_the_main_mcus_endstop() {
    let dir = scratch("toolboard-home-z");
    let (run, trace) = retry_homing_timeouts(|| home_z(&dir, TOOLBOARD_16MHZ), |(r, _)| r);
    assert_success(&run);
    assert!(
        run.stdout.contains("homing z: mcus mcu+toolboard"),
        "{}",
        run.stdout
    );
    assert!(run.stdout.contains("trigger on 'mcu'"), "{}", run.stdout);
    // The host's homed Z agrees with the simulated axis (moved by the toolboard's stepper)
    // within one step plus the endstop's sampling at the second-pass speed.
    let host = homed_z(&run.stdout);
    let net = net_steps(&read_trace(&trace).expect("toolboard trace"));
    let phys = 2.0 + *net.get(&Z_OID).unwrap_or(&0) as f64 / Z_STEPS_PER_MM;
    let tol = 1.0 / Z_STEPS_PER_MM + SECOND_SPEED * SAMPLING_S + 1e-9;
    assert!(
        (host - phys).abs() <= tol,
        "host says z = {host} mm, the simulated axis is at {phys} mm (tolerance {tol})\n{}",
        run.stdout
    );
    assert!(phys.abs() <= 0.250 + tol, "Z halted at {phys} mm");
    let o = overshoots(&run.stdout);
    assert_eq!(o.len(), 2, "{}", run.stdout);
    assert!(
        // One step of timing noise (compression error, clock conversion) may show as -1 step.
        o.iter()
            .all(|&v| (-1.0 / Z_STEPS_PER_MM - 1e-9..=0.250).contains(&v)),
        "overshoots {o:?}\n{}",
        run.stdout
    );
}

#[test]
fn delayed_toolboard_fails_homing_with_a_communication_timeout() {
    let dir = scratch("toolboard-home-delay");
    let (run, trace) = home_z(&dir, "--tx-delay-ms 30");
    assert_exit(&run, 1);
    assert!(homing_timed_out(&run), "stderr:\n{}", run.stderr);
    // The toolboard stopped Z and never stepped it afterwards; Z moved far less than the
    // 1.5 × travel homing move.
    let t = assert_no_step_after_stop(&trace, Some(TOOLBOARD_TRSYNC_OID), Z_OID);
    let net = net_steps(&t).get(&Z_OID).copied().unwrap_or(0);
    assert!(net.abs() < (20.0 * Z_STEPS_PER_MM) as i64, "Z moved {net} steps");
}

#[test]
fn the_io_process_refuses_steppers_on_another_mcu() {
    let dir = scratch("toolboard-io-process");
    let cfg = example_config(&dir);
    let gcode = workspace().join("examples/square.gcode");
    let mut cmd = Command::new(bin("cadence"));
    cmd.arg("print")
        .arg(&gcode)
        .arg("--config")
        .arg(&cfg)
        .arg("--io-process");
    let run = run(&mut cmd, TIMEOUT);
    assert_exit(&run, 1);
    assert!(
        run.stderr.contains("[stepper_z] is driven by mcu 'toolboard'"),
        "stderr:\n{}",
        run.stderr
    );
    assert!(!run.stderr.contains("panicked"), "{}", run.stderr);
}

#[test]
fn batch_writes_one_wire_stream_per_mcu() {
    let dir = scratch("toolboard-batch");
    let cfg = example_config(&dir);
    let out = dir.join("square.bin");
    let gcode = workspace().join("examples/square.gcode");
    let mut cmd = Command::new(bin("cadence"));
    cmd.arg("print")
        .arg(&gcode)
        .arg("--config")
        .arg(&cfg)
        .arg("--batch")
        .arg(&out);
    let r = run(&mut cmd, TIMEOUT);
    assert_success(&r);
    for (file, steppers) in [(out.clone(), 2), (dir.join("square-toolboard.bin"), 2)] {
        let mut cmd = Command::new(bin("cadence"));
        cmd.arg("decode").arg(&file);
        let d = run(&mut cmd, TIMEOUT);
        assert_success(&d);
        let lines: Vec<&str> = d.stdout.lines().collect();
        let configured = lines.iter().filter(|l| l.starts_with("config_stepper")).count();
        assert_eq!(configured, steppers, "{}: {}", file.display(), d.stdout);
        assert!(
            lines.iter().filter(|l| l.starts_with("queue_step")).count() > 10,
            "{}: {}",
            file.display(),
            d.stdout
        );
    }
}

/// System time (CLOCK_MONOTONIC s, exact from the simulator's epoch) of every step of `oid`
/// in the trace at `path`, in order.
fn step_times(path: &Path, oid: u8) -> Vec<f64> {
    let t = read_trace(path).expect("trace");
    let epoch = firmware::sim::read_epoch(path).expect("epoch file beside the trace");
    let ticks_per_s = t.clock_freq as f64 * t.time_scale;
    t.records
        .iter()
        .filter_map(|r| match *r {
            TraceRecord::Step { oid: o, clock, .. } if o == oid => Some(epoch + clock as f64 / ticks_per_s),
            _ => None,
        })
        .collect()
}

/// How far apart in time two MCUs run one move: the last move of examples/square.gcode
/// (X50 Y50 Z0.6 → X10 Y10 Z5) moves X on `mcu` and Z on the toolboard together. For Z's
/// step `j` from the end (at `(j + ½)` steps before the target, which is a whole number of
/// steps on both axes), X is at the same fraction of the move at its step `i*` from the end;
/// returns `t_z(j) − t_x(i*)` (X's time interpolated) for the cruise part of the move.
fn last_move_skew(main_trace: &Path, tool_trace: &Path) -> Vec<f64> {
    let x = step_times(main_trace, 0);
    let z = step_times(tool_trace, Z_OID);
    let (sd_x, dx) = (1.0 / 80.0, 40.0);
    let (sd_z, dz) = (1.0 / Z_STEPS_PER_MM, 4.4);
    let mut out = Vec::new();
    for j in (200..1000).step_by(10) {
        let frac = (j as f64 + 0.5) * sd_z / dz;
        let i = frac * dx / sd_x - 0.5;
        let (i0, w) = (i.floor() as usize, i - i.floor());
        let (Some(&a), Some(&b), Some(&tz)) = (
            x.get(x.len().wrapping_sub(1 + i0)),
            x.get(x.len().wrapping_sub(2 + i0)),
            z.get(z.len().wrapping_sub(1 + j)),
        ) else {
            break;
        };
        // Steps from the end go back in time: a is later than b.
        let tx = a + (b - a) * w;
        out.push(tz - tx);
    }
    out
}
