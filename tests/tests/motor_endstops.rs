//! End to end: G28 with two Z motors on their own endstops (`[stepper_z1] endstop_pin`), on the
//! simulated printer (the built-in cartesian one with 20 mm axes, the carriages starting 2 mm
//! from the endstops). Each motor drives its own end of the gantry in the simulated world and
//! its switch reads that end; `[simulator] gantry_tilt` starts `[stepper_z1]`'s end higher and
//! `z_endstop_offsets` puts its switch higher. The main MCU's step trace says where each end
//! really stopped: each on its own switch, so a tilted gantry comes out level, and switches
//! that differ leave the ends apart by exactly that. The passes' stop latencies are printed as
//! a histogram against the 25 ms budget.

use std::path::Path;
use std::time::Duration;

use cadence_tests::{
    net_steps, print_traced, retry_homing_timeouts, run, scratch, short_homing_config_text, stop_bounds, Run,
};
use firmware::trace::read_trace;

const TIMEOUT: Duration = Duration::from_secs(180);
/// Z steps per mm (both motors: 200 full steps, 16 microsteps, 8 mm per turn).
const Z_STEPS_PER_MM: f64 = 400.0;
/// Where the simulated Z carriage starts (10 % of 20 mm from the endstop at 0).
const START_MM: f64 = 2.0;
/// Oids on the main MCU: stepper_x, stepper_y, stepper_z, then stepper_z1.
const Z_OID: u8 = 2;
const Z1_OID: u8 = 3;
/// A motor stops at most this far below its switch: a step plus the endstop's sampling
/// (≤ 1.06 ms) at the 5 mm/s second pass, plus the stop latency at that speed (generously,
/// the 25 ms budget).
const BELOW: f64 = 1.0 / Z_STEPS_PER_MM + 5.0 * 1.06e-3 + 5.0 * 0.025;
/// The multi-MCU stop budget (µs).
const BUDGET_US: f64 = 25_000.0;

/// The short printer with a second Z motor (`stepper_z1`, inverted dir pin) on its own
/// endstop `PG3` (or, with `simulator` naming `[mcu zboard]`, `zboard:PA3`), and `simulator`
/// lines added to `[simulator]`.
fn config(dir: &Path, simulator: &str) -> std::path::PathBuf {
    let (simulator, pin) = match simulator.split_once("[mcu zboard]") {
        Some((sim, board)) => (sim.to_string(), format!("zboard:PA3\n[mcu zboard]{board}")),
        None => (simulator.to_string(), "PG3\n".to_string()),
    };
    let text = short_homing_config_text("simulated-cartesian.cfg")
        .replace("time_scale: 1.0\n", &format!("time_scale: 1.0\n{simulator}"));
    let text = format!(
        "{text}\n[stepper_z1]\nstep_pin: PG0\ndir_pin: !PG1\nenable_pin: !PG2\nmicrosteps: 16\n\
         rotation_distance: 8\nendstop_pin: ^{pin}"
    );
    let path = dir.join("printer.cfg");
    std::fs::write(&path, text).expect("write config");
    path
}

/// What one print did: its run, where each Z end stopped (world mm, from the step trace) and
/// the M114 Z after G28.
struct Homed {
    run: Run,
    z: f64,
    z1: f64,
    m114_z: f64,
}

/// Prints `gcode` (ending where the ends are to be checked) on the printer with `simulator`;
/// `z1_start` is where `[stepper_z1]`'s end starts.
fn print(test: &str, simulator: &str, gcode: &str, z1_start: f64) -> Homed {
    let dir = scratch(test);
    let cfg = config(&dir, simulator);
    let file = dir.join("home.gcode");
    std::fs::write(&file, gcode).expect("write G-code");
    let trace = dir.join("print.trace");
    let run = retry_homing_timeouts(|| run(&mut print_traced(&file, &cfg, &trace), TIMEOUT), |r| r);
    let (z, z1, m114_z) = match run.code {
        Some(0) => {
            let net = net_steps(&read_trace(&trace).expect("trace"));
            let steps = |oid| net.get(&oid).copied().unwrap_or(0) as f64;
            let m114_z = cadence_tests::value_after(&run.stdout, "M114 (line", "Z:");
            // stepper_z1's dir pin is inverted: its end goes down when its MCU steps forward.
            (
                START_MM + steps(Z_OID) / Z_STEPS_PER_MM,
                z1_start - steps(Z1_OID) / Z_STEPS_PER_MM,
                m114_z,
            )
        }
        _ => (f64::NAN, f64::NAN, f64::NAN),
    };
    Homed { run, z, z1, m114_z }
}

impl Homed {
    /// The print's stdout, once it succeeded with stepper_z's end on its switch at 0 and
    /// stepper_z1's on its own at `z1_switch` (so the ends are that far apart).
    #[track_caller]
    fn on_switches(&self, z1_switch: f64) -> &str {
        assert_eq!(self.run.code, Some(0), "{}\n{}", self.run.stdout, self.run.stderr);
        let out = &self.run.stdout;
        assert_on_switch("stepper_z", self.z, 0.0, out);
        assert_on_switch("stepper_z1", self.z1, z1_switch, out);
        assert!(
            ((self.z1 - self.z) - z1_switch).abs() <= BELOW,
            "ends {} and {} mm\n{out}",
            self.z,
            self.z1
        );
        out
    }
}

/// The first Z homing report line of `out`.
#[track_caller]
fn z_line(out: &str) -> &str {
    out.lines()
        .find(|l| l.trim_start().starts_with("homing z:"))
        .unwrap_or_else(|| panic!("no Z homing report\n{out}"))
}

/// The stop bounds (µs after the trigger) of every Z pass the runs report.
fn z_passes(runs: &[&Run]) -> Vec<(f64, f64)> {
    runs.iter()
        .flat_map(|r| r.stdout.lines())
        .filter(|l| l.trim_start().starts_with("homing z:"))
        .flat_map(stop_bounds)
        .collect()
}

/// Nearest-rank quantile `q` of sorted `v`.
fn quantile(v: &[f64], q: f64) -> f64 {
    let i = ((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1;
    v[i]
}

#[track_caller]
fn assert_on_switch(what: &str, at: f64, switch: f64, out: &str) {
    assert!(
        at <= switch + 1.0 / Z_STEPS_PER_MM + 1e-9 && at >= switch - BELOW,
        "{what} stopped at {at} mm, its switch is at {switch}\n{out}"
    );
}

#[test]
fn each_z_motor_stops_on_its_own_endstop() {
    // A gantry 3 mm higher at stepper_z1's end (more than the 2 mm retract), both switches at
    // 0: stepper_z's switch stops both motors first, and each then ends on its own: it comes
    // out level.
    let level = print(
        "motor-endstops-level",
        "gantry_tilt: 0, 3\n",
        "G28\nM400\nM114\n",
        START_MM + 3.0,
    );
    let out = level.on_switches(0.0);
    // The host's Z is where stepper_z's end really is (its overshoot accounted for).
    assert!(
        // A step, the endstop's sampling at 5 mm/s and M114's three decimals.
        (level.m114_z - level.z).abs() <= 1.0 / Z_STEPS_PER_MM + 5.0 * 1.06e-3 + 1e-3,
        "M114 Z {} vs stepper_z's end at {}\n{out}",
        level.m114_z,
        level.z
    );
    // Three passes: both motors onto [stepper_z]'s endstop, then each on its own.
    let line = z_line(out);
    assert_eq!(stop_bounds(line).len(), 3, "{line}");

    // stepper_z1's switch 0.3 mm higher (it stops both motors first), homed three more
    // times: its end stays 0.3 mm up.
    let apart = print(
        "motor-endstops-apart",
        "z_endstop_offsets: 0, 0.3\n",
        "G28\nG1 Z4 F600\nG28 Z\nG1 Z3 F600\nG28 Z\nG1 Z6 F600\nG28 Z\nM400\nM114\n",
        START_MM,
    );
    apart.on_switches(0.3);

    assert_within_budget("one MCU", &[&level.run, &apart.run], 3 + 4 * 3);
}

/// Prints the histogram of the Z passes' stop latencies (the first cancelled step after the
/// trigger, the host's upper bound) of `runs` and checks it against the budget.
#[track_caller]
fn assert_within_budget(what: &str, runs: &[&Run], passes: usize) {
    let mut upper: Vec<f64> = z_passes(runs).iter().map(|b| b.1).collect();
    assert_eq!(upper.len(), passes, "{upper:?}");
    upper.sort_by(f64::total_cmp);
    let (p50, p99, p999, max) = (
        quantile(&upper, 0.5),
        quantile(&upper, 0.99),
        quantile(&upper, 0.999),
        quantile(&upper, 1.0),
    );
    eprintln!(
        "Z passes on their own endstops ({what}): trigger → stop (first cancelled step) over {} \
         passes: p50 {p50:.0} µs, p99 {p99:.0} µs, p99.9 {p999:.0} µs, max {max:.0} µs (budget \
         {BUDGET_US:.0} µs)",
        upper.len()
    );
    assert!(max < BUDGET_US, "{upper:?}");
}

#[test]
fn a_motors_own_endstop_on_another_mcu_stops_it_through_the_relay() {
    // stepper_z1's switch on a second simulated MCU, 0.2 mm up: the host relays its trigger
    // to the main MCU within the budget.
    let r = print(
        "motor-endstops-zboard",
        "z_endstop_offsets: 0, 0.2\n[mcu zboard]\nserial: simulator\n",
        "G28\nG1 Z4 F600\nG28 Z\nG1 Z3 F600\nG28 Z\nM400\nM114\n",
        START_MM,
    );
    let line = z_line(r.on_switches(0.2));
    assert!(
        line.contains("mcus mcu+zboard") && line.contains("trigger on 'zboard'"),
        "{line}"
    );
    assert_within_budget("relayed from zboard", &[&r.run], 3 * 3);
}

#[test]
fn a_switch_still_pressed_after_the_retract_is_reported_by_name() {
    // stepper_z1's switch 5 mm up, pressed from the start (its end at 2 mm): the first pass
    // stops at once, and the 2 mm retract does not clear it.
    let r = print(
        "motor-endstops-pressed",
        "z_endstop_offsets: 0, 5\n",
        "G28\n",
        START_MM,
    );
    assert_ne!(r.run.code, Some(0), "{}", r.run.stdout);
    assert!(
        r.run
            .stderr
            .contains("G28: Endstop z1 still triggered after retract"),
        "{}",
        r.run.stderr
    );
}
