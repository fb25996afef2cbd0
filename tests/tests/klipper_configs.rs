//! Opt-in acceptance run over Klipper's example configs: every `config/printer-*.cfg` and
//! `config/generic-*.cfg` of the Klipper checkout named by `CADENCE_KLIPPER_CONFIGS`, with only
//! the MCUs' `serial:` replaced by the simulator, prints a small G-code (G28, heat the nozzle,
//! an extruded 10 mm square) in batch mode and/or as a live print on the simulated printer
//! (`CADENCE_KLIPPER_CONFIGS_MODE`: `batch`, `live` or `both`, the default); a live print that
//! fails on timing runs again at time scale 4, then 1 (the MCUs' real speed). The table of
//! results by cause is printed (run with `--nocapture`); each config's copy and output are
//! kept in the scratch directory. Skipped, saying so, without the variable: Klipper's files
//! are not part of this repository.
//!
//! `CADENCE_KLIPPER_CONFIGS_JOBS=N` runs N configs at a time, `CADENCE_KLIPPER_CONFIGS_ONLY=a.cfg,…`
//! only those, `CADENCE_KLIPPER_CONFIGS_TIME_SCALE` sets the live prints' time scale.
//!
//! What it asserts: no run hangs or crashes (a signal, or a panic's message), and each config
//! that fails says why on stderr. `CADENCE_KLIPPER_CONFIGS_MIN=N` also requires at least N
//! configs to print in each mode run.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Duration;

use cadence_tests::scratch;

/// The small print: start heating the nozzle to a temperature every example extruder allows,
/// home meanwhile, wait for the temperature, an extruded square at Z 1 (inside a delta's
/// print radius too), wait for the moves.
const GCODE: &str = "M104 S200\nG28\nM109 S200\nG90\nM83\nG1 Z1 F600\nG1 X10 Y10 F3000\n\
G1 X20 Y10 E0.5 F1200\nG1 X20 Y20 E0.5\nG1 X10 Y20 E0.5\nG1 X10 Y10 E0.5\nM400\n";

/// Live prints run the simulated MCUs this much faster than the wall clock (heating 25 → 200 °C
/// takes ~75 s of printer time); `CADENCE_KLIPPER_CONFIGS_TIME_SCALE` changes it.
const LIVE_TIME_SCALE: &str = "10";

/// A live print that failed on time (a step not ready 100 ms ahead, or a homing
/// communication timeout: this loaded VM's pauses at a fast time scale, or a debug build's
/// slow step computation) runs again at these scales in turn, the last the MCUs' real speed;
/// the table shows the last run's result.
const RETRY_TIME_SCALES: [&str; 2] = ["4", "1"];

/// `text` with every `[mcu]`/`[mcu NAME]` section's `serial:` (or `canbus_uuid:`) line set to
/// the simulator; nothing else changes.
fn on_simulator(text: &str) -> String {
    let mut in_mcu = false;
    let mut out = String::with_capacity(text.len() + 64);
    for line in text.lines() {
        let t = line.trim_start();
        if t.starts_with('[') {
            let name = t.trim_start_matches('[').split(']').next().unwrap_or("");
            in_mcu = name == "mcu" || name.starts_with("mcu ");
        }
        let key = t.split([':', '=']).next().unwrap_or("").trim();
        if in_mcu && line == t && (key == "serial" || key == "canbus_uuid") {
            out.push_str("serial: simulator\n");
        } else {
            out.push_str(line);
            out.push('\n');
        }
    }
    out
}

/// The configs to run: Klipper's printer-*.cfg and generic-*.cfg, sorted.
fn example_configs(src: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(src.join("config"))
        .unwrap_or_else(|e| panic!("{}/config: {e}", src.display()))
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let n = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
            (n.starts_with("printer-") || n.starts_with("generic-")) && n.ends_with(".cfg")
        })
        .collect();
    v.sort();
    v
}

/// The cause of a failed run: the first error line of stderr with file names, line numbers,
/// section names in brackets, pins and figures taken out, so that configs failing for one
/// reason share one row.
fn cause(stderr: &str) -> String {
    let line = stderr
        .lines()
        .find(|l| l.starts_with("cadence: error") || l.contains("error:"))
        .or_else(|| stderr.lines().rev().find(|l| !l.trim().is_empty()))
        .unwrap_or("(no message)");
    let mut s = String::new();
    let mut skip_bracket = false;
    for word in line.split_whitespace() {
        if word.contains(".cfg:") || word.contains("/tmp/") {
            continue;
        }
        let w: String = word
            .chars()
            .map(|c| if c.is_ascii_digit() { '#' } else { c })
            .collect();
        // `[stepper_x]`, `[temperature_sensor NAME]`: the kind stays, the name goes.
        if skip_bracket {
            skip_bracket = !w.ends_with(']');
            if !skip_bracket {
                s.push_str("…] ");
            }
            continue;
        }
        if w.starts_with('[') && !w.ends_with(']') {
            skip_bracket = true;
            s.push_str(&w);
            s.push(' ');
            continue;
        }
        if w.starts_with("[stepper_") || w.starts_with("[extruder") {
            s.push_str("[stepper/extruder] ");
            continue;
        }
        let w = if w.starts_with('\'') && w.trim_end_matches([':', ',']).ends_with('\'') {
            "'…'".to_string()
        } else {
            w
        };
        s.push_str(&w);
        s.push(' ');
    }
    s.trim().chars().take(160).collect()
}

/// One config's result in one mode.
struct Outcome {
    name: String,
    ok: bool,
    cause: String,
}

/// Whether a live run's failure is one of timing, worth a run at a slower time scale: a step
/// or a heater's PWM update late, a homing communication timeout, or a homing trigger not seen
/// by the end of its move (the report came after the host stopped waiting). A real fault of the
/// config fails at every scale, and the table shows the last run.
fn timing_failure(o: &Outcome) -> bool {
    const TIMING: [&str; 5] = [
        "before it is due",
        "Communication timeout",
        "Missed scheduling",
        "Timer too close",
        "after full movement",
    ];
    !o.ok && TIMING.iter().any(|t| o.cause.contains(t))
}

fn run_one(dir: &Path, cfg: &Path, live: bool) -> Outcome {
    let scale =
        std::env::var("CADENCE_KLIPPER_CONFIGS_TIME_SCALE").unwrap_or_else(|_| LIVE_TIME_SCALE.into());
    let mut o = run_at(dir, cfg, live.then_some(scale.as_str()));
    for retry in RETRY_TIME_SCALES {
        if !(live && timing_failure(&o)) {
            break;
        }
        o = run_at(dir, cfg, Some(retry));
    }
    o
}

/// One config in batch mode (`scale` None) or live at time scale `scale`.
fn run_at(dir: &Path, cfg: &Path, scale: Option<&str>) -> Outcome {
    let live = scale.is_some();
    let name = cfg
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or("?")
        .to_string();
    let text = std::fs::read_to_string(cfg).unwrap_or_else(|e| panic!("{}: {e}", cfg.display()));
    let copy = dir.join(&name);
    std::fs::write(&copy, on_simulator(&text)).unwrap_or_else(|e| panic!("{e}"));
    let gcode = dir.join("square.gcode");
    let copy_s = copy.to_string_lossy().into_owned();
    let gcode_s = gcode.to_string_lossy().into_owned();
    let bin_out = dir.join(format!("{name}.bin")).to_string_lossy().into_owned();
    let mut args = vec!["print", &gcode_s, "--config", &copy_s, "--no-progress"];
    if let Some(scale) = scale {
        args.extend(["--time-scale", scale, "--no-realtime"]);
    } else {
        args.extend(["--batch", &bin_out]);
    }
    let run = cadence_tests::cadence(&args, Duration::from_secs(if live { 600 } else { 300 }));
    let mode = if live { "live" } else { "batch" };
    let _ = std::fs::write(
        dir.join(format!("{name}.{mode}.out")),
        format!("{}\n--- stderr\n{}", run.stdout, run.stderr),
    );
    assert!(
        run.code.is_some() && !run.stderr.contains("panicked"),
        "{name} ({mode}) crashed: {:?}\n{}",
        run.code,
        run.stderr
    );
    let ok = run.code == Some(0);
    if !ok {
        assert!(!run.stderr.trim().is_empty(), "{name} ({mode}) failed silently");
    }
    Outcome {
        name,
        ok,
        cause: if ok { String::new() } else { cause(&run.stderr) },
    }
}

/// Prints the mode's table (causes by count, with the configs) and returns the pass count.
fn report(mode: &str, outcomes: &[Outcome]) -> usize {
    let passed = outcomes.iter().filter(|o| o.ok).count();
    let mut by_cause: BTreeMap<&str, Vec<&str>> = BTreeMap::new();
    for o in outcomes.iter().filter(|o| !o.ok) {
        by_cause.entry(&o.cause).or_default().push(&o.name);
    }
    let mut rows: Vec<_> = by_cause.into_iter().collect();
    rows.sort_by(|a, b| b.1.len().cmp(&a.1.len()).then(a.0.cmp(b.0)));
    println!(
        "\n{mode}: {passed} of {} print ({:.0} %)\n| configs | cause | examples |\n|---|---|---|",
        outcomes.len(),
        100.0 * passed as f64 / outcomes.len().max(1) as f64
    );
    for (c, names) in rows {
        let shown: Vec<&str> = names.iter().take(3).copied().collect();
        println!("| {} | {c} | {} |", names.len(), shown.join(", "));
    }
    passed
}

/// Every config, `CADENCE_KLIPPER_CONFIGS_JOBS` at a time (default 1; a live print mostly
/// waits for its simulated MCU), in config order.
fn run_all(dir: &Path, configs: &[PathBuf], live: bool) -> Vec<Outcome> {
    let jobs: usize = std::env::var("CADENCE_KLIPPER_CONFIGS_JOBS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1)
        .max(1);
    let next = AtomicUsize::new(0);
    let results = Mutex::new(Vec::new());
    std::thread::scope(|s| {
        for _ in 0..jobs {
            s.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(cfg) = configs.get(i) else {
                    return;
                };
                let o = run_one(dir, cfg, live);
                results.lock().unwrap_or_else(|e| e.into_inner()).push((i, o));
            });
        }
    });
    let mut v = results.into_inner().unwrap_or_else(|e| e.into_inner());
    v.sort_by_key(|(i, _)| *i);
    v.into_iter().map(|(_, o)| o).collect()
}

#[test]
fn klipper_example_configs_print_on_the_simulator() {
    let Ok(src) = std::env::var("CADENCE_KLIPPER_CONFIGS") else {
        eprintln!("skipped: set CADENCE_KLIPPER_CONFIGS to a Klipper checkout to run its example configs");
        return;
    };
    let mode = std::env::var("CADENCE_KLIPPER_CONFIGS_MODE").unwrap_or_else(|_| "both".into());
    let min: Option<usize> = std::env::var("CADENCE_KLIPPER_CONFIGS_MIN")
        .ok()
        .and_then(|v| v.parse().ok());
    let mut configs = example_configs(Path::new(&src));
    // `CADENCE_KLIPPER_CONFIGS_ONLY=a.cfg,b.cfg`: those configs alone.
    if let Ok(only) = std::env::var("CADENCE_KLIPPER_CONFIGS_ONLY") {
        let names: Vec<&str> = only.split(',').map(str::trim).collect();
        configs.retain(|c| {
            c.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| names.contains(&n))
        });
    }
    assert!(
        !configs.is_empty(),
        "no printer-*.cfg/generic-*.cfg under {src}/config"
    );
    let dir = scratch("klipper-configs").keep();
    std::fs::write(dir.join("square.gcode"), GCODE).unwrap_or_else(|e| panic!("{e}"));
    println!("configs and outputs in {}", dir.display());
    for (label, live) in [("batch", false), ("live", true)] {
        if mode != "both" && mode != label {
            continue;
        }
        let outcomes = run_all(&dir, &configs, live);
        let passed = report(label, &outcomes);
        if let Some(min) = min {
            assert!(passed >= min, "{label}: {passed} configs print, fewer than {min}");
        }
    }
}

#[test]
fn only_the_mcu_serial_changes() {
    let text = "[mcu]\nserial: /dev/ttyUSB0\nbaud: 250000\n[mcu z]\ncanbus_uuid: 1234\n\
                [stepper_x]\nserial: kept\n#serial: comment\n";
    assert_eq!(
        on_simulator(text),
        "[mcu]\nserial: simulator\nbaud: 250000\n[mcu z]\nserial: simulator\n\
         [stepper_x]\nserial: kept\n#serial: comment\n"
    );
}

#[test]
fn causes_group_configs() {
    let a = cause("cadence: error: /tmp/x/printer-a.cfg:12: [stepper_x] endstop_pin: 'tmc2209_stepper_x:virtual_endstop' is not supported");
    let b = cause("cadence: error: /tmp/x/printer-b.cfg:40: [stepper_y] endstop_pin: 'tmc2130_stepper_y:virtual_endstop' is not supported");
    assert_eq!(a, b);
    assert!(a.contains("endstop_pin"), "{a}");
}
