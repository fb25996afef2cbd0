//! Shared helpers for the end-to-end tests in `tests/tests/`: locating the built binaries,
//! running them with a bounded wait, and workspace paths.

pub mod api;

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The workspace root.
pub fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_default()
}

/// The built-in simulated printer's printer.cfg plus `extra` sections, written to
/// `dir/printer.cfg`.
pub fn simulated_config(dir: &Path, extra: &str) -> PathBuf {
    let cfg = dir.join("printer.cfg");
    std::fs::write(
        &cfg,
        format!("{}\n{extra}\n", sysconfig::printer::SIMULATED_PRINTER_CFG),
    )
    .expect("write printer.cfg");
    cfg
}

/// examples/simulated-probe.cfg with 20 mm axes (homing at 10 then 5 mm/s after a 2 mm
/// retract), its `[probe]` section replaced by `probe_section` (another probe: `[bltouch]`,
/// `[smart_effector]`) and `edit` applied to every other trimmed line (`None`: keep), written
/// to `dir/printer.cfg`.
pub fn probe_example_with(dir: &Path, probe_section: &str, edit: impl Fn(&str) -> Option<String>) -> PathBuf {
    let mut out = String::new();
    let mut in_probe = false;
    for line in short_homing_config_text("simulated-probe.cfg").lines() {
        let l = line.split('#').next().unwrap_or_default().trim();
        if l.starts_with('[') {
            in_probe = l == "[probe]";
            if in_probe {
                out.push_str(probe_section);
                out.push('\n');
            }
        }
        if !in_probe {
            out.push_str(&edit(l).unwrap_or_else(|| line.to_string()));
            out.push('\n');
        }
    }
    let path = dir.join("printer.cfg");
    std::fs::write(&path, out).expect("write config");
    path
}

/// examples/simulated-cartesian.cfg without endstops, written to `dir/no-endstops.cfg`: G28
/// homes without motion (homing's timing under a loaded test machine is tested elsewhere).
pub fn printer_without_endstops(dir: &Path) -> PathBuf {
    let text = std::fs::read_to_string(workspace().join("examples/simulated-cartesian.cfg"))
        .expect("example config");
    let body: Vec<&str> = text
        .lines()
        .filter(|l| {
            let l = l.trim_start();
            !(l.starts_with("endstop_pin")
                || l.starts_with("position_endstop")
                || l.starts_with("homing_speed"))
        })
        .collect();
    let path = dir.join("no-endstops.cfg");
    std::fs::write(&path, body.join("\n")).expect("write config");
    path
}

/// A binary of the workspace, built by `cargo test --workspace` into the same target directory
/// as this test executable (`target/<profile>/deps/<test>` → `target/<profile>/<name>`).
pub fn bin(name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    let mut dir = exe.parent().expect("deps dir").to_path_buf();
    if dir.ends_with("deps") {
        dir.pop();
    }
    let path = dir.join(name);
    assert!(
        path.is_file(),
        "{} not built (run `cargo test --workspace`)",
        path.display()
    );
    path
}

/// Output of a finished process.
#[derive(Debug)]
pub struct Run {
    pub code: Option<i32>,
    pub stdout: String,
    pub stderr: String,
}

/// Runs the `cadence` binary with `args`, killing it after `timeout` (a hang is a test failure).
pub fn cadence(args: &[&str], timeout: Duration) -> Run {
    run(Command::new(bin("cadence")).args(args), timeout)
}

/// `cadence print GCODE --config CFG --batch OUT`: a batch print of `gcode` on the printer of
/// `cfg`, its wire stream to `out`, waited for at most `timeout`.
pub fn print_batch(gcode: &Path, cfg: &Path, out: &Path, timeout: Duration) -> Run {
    let mut cmd = Command::new(bin("cadence"));
    cmd.arg("print")
        .arg(gcode)
        .arg("--config")
        .arg(cfg)
        .arg("--batch")
        .arg(out);
    run(&mut cmd, timeout)
}

/// A live `cadence print` of `gcode` on `cfg` with the simulated MCUs at time scale `scale`,
/// without real-time settings or the progress line, killed after `timeout`.
pub fn print_live(gcode: &Path, cfg: &Path, scale: &str, timeout: Duration) -> Run {
    let (gcode, cfg) = (gcode.to_string_lossy(), cfg.to_string_lossy());
    cadence(
        &[
            "print",
            &gcode,
            "--config",
            &cfg,
            "--time-scale",
            scale,
            "--no-realtime",
            "--no-progress",
        ],
        timeout,
    )
}

/// Runs `cmd` to completion with a bounded wait.
pub fn run(cmd: &mut Command, timeout: Duration) -> Run {
    run_then(cmd, timeout, |_| {})
}

/// Starts `cmd`, calls `during` with the running child (e.g. to signal it), then waits for it
/// to end, bounded by `timeout` (a hang is a test failure).
pub fn run_then(cmd: &mut Command, timeout: Duration, during: impl FnOnce(&Child)) -> Run {
    let mut child = cmd
        .current_dir(workspace())
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn");
    let mut out = child.stdout.take().expect("stdout");
    let mut err = child.stderr.take().expect("stderr");
    let t_out = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = out.read_to_string(&mut s);
        s
    });
    let t_err = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = err.read_to_string(&mut s);
        s
    });
    during(&child);
    let deadline = Instant::now() + timeout;
    let status = loop {
        if let Some(status) = child.try_wait().expect("wait") {
            break Some(status);
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let stdout = t_out.join().unwrap_or_default();
    let stderr = t_err.join().unwrap_or_default();
    assert!(
        status.is_some(),
        "process hung for {timeout:?}\nstdout:\n{stdout}\nstderr:\n{stderr}"
    );
    Run {
        code: status.and_then(|s| s.code()),
        stdout,
        stderr,
    }
}

/// A fresh scratch directory for one test: removed when the test passes (the guard is dropped
/// without a panic), kept when it fails, for its traces and logs, or with `CADENCE_KEEP_SCRATCH`
/// set. Use it as a `&Path`.
pub fn scratch(test: &str) -> Scratch {
    let dir = std::env::temp_dir().join(format!("cadence-test-{}-{test}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("scratch dir");
    Scratch { dir, keep: false }
}

/// The directory of [`scratch`]; see there.
#[derive(Debug)]
pub struct Scratch {
    dir: PathBuf,
    /// Never removed (see [`Scratch::keep`]).
    keep: bool,
}

impl Scratch {
    /// The directory's path, owned.
    pub fn to_path_buf(&self) -> PathBuf {
        self.dir.clone()
    }

    /// The directory, kept whatever the test's outcome (its files are the test's report).
    pub fn keep(mut self) -> PathBuf {
        self.keep = true;
        self.dir.clone()
    }
}

impl std::ops::Deref for Scratch {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.dir
    }
}

impl AsRef<Path> for Scratch {
    fn as_ref(&self) -> &Path {
        &self.dir
    }
}

impl AsRef<std::ffi::OsStr> for Scratch {
    fn as_ref(&self) -> &std::ffi::OsStr {
        self.dir.as_os_str()
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        if !self.keep && !std::thread::panicking() && std::env::var_os("CADENCE_KEEP_SCRATCH").is_none() {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}

/// The first `lines` lines of the reference benchy (`../shared/data/gcode`) and the reference
/// cartesian printer (`../shared/data/printers`) on the built-in simulator, written into `dir`:
/// (G-code file, printer.cfg). `None` (the test then skips) when `../shared` is not there.
pub fn benchy_prefix(dir: &Path, lines: usize) -> Option<(PathBuf, PathBuf)> {
    use std::io::BufRead;
    let shared = workspace().join("../shared");
    let gcode_src = shared.join("data/gcode/benchy-prusaslicer.gcode");
    let cfg_src = shared.join("data/printers/benchy-cartesian.cfg");
    if !gcode_src.is_file() || !cfg_src.is_file() {
        println!("skipped: {} not found", gcode_src.display());
        return None;
    }
    let reader = std::io::BufReader::new(std::fs::File::open(&gcode_src).expect("benchy G-code"));
    let prefix: Vec<String> = reader
        .lines()
        .take(lines)
        .map(|l| l.expect("benchy line"))
        .collect();
    let gcode = dir.join("benchy-prefix.gcode");
    std::fs::write(&gcode, prefix.join("\n")).expect("write the G-code prefix");
    let cfg_text = std::fs::read_to_string(&cfg_src)
        .expect("benchy printer.cfg")
        .replace("serial: /dev/ttyACM0", "serial: simulator");
    let cfg = dir.join("printer.cfg");
    std::fs::write(&cfg, cfg_text).expect("write printer.cfg");
    Some((gcode, cfg))
}

/// `examples/<example>` made quick to home, written to `dir/printer.cfg`: 20 mm axes, homing at
/// 10 mm/s, and a second pass (retract 2 mm, 5 mm/s) on every stepper.
pub fn short_homing_config(dir: &Path, example: &str) -> PathBuf {
    let path = dir.join("printer.cfg");
    std::fs::write(&path, short_homing_config_text(example)).expect("write config");
    path
}

/// The text of [`short_homing_config`], for tests that add sections before writing it.
pub fn short_homing_config_text(example: &str) -> String {
    let text = std::fs::read_to_string(workspace().join("examples").join(example)).expect("example");
    let mut out = String::new();
    for line in text.lines() {
        let line = match line.trim() {
            "position_max: 220" | "position_max: 200" => "position_max: 20",
            "homing_speed: 50" => "homing_speed: 10",
            l if l.starts_with("[stepper_") => {
                out.push_str(line);
                out.push_str("\nhoming_retract_dist: 2\nsecond_homing_speed: 5\n");
                continue;
            }
            _ => line,
        };
        out.push_str(line);
        out.push('\n');
    }
    out
}

/// Fails the test unless `run` exited 0, showing both outputs.
#[track_caller]
pub fn assert_success(run: &Run) {
    assert_exit(run, 0);
}

/// Fails the test unless `run` exited with `code` (and did not panic), showing both outputs.
#[track_caller]
pub fn assert_exit(run: &Run, code: i32) {
    assert_eq!(
        run.code,
        Some(code),
        "stdout:\n{}\nstderr:\n{}",
        run.stdout,
        run.stderr
    );
    assert!(!run.stderr.contains("panicked"), "stderr:\n{}", run.stderr);
}

/// What a simulated MCU's step trace shows, after the checks every print must pass: step
/// times never go backwards per stepper and the MCU never shut down.
#[derive(Debug)]
pub struct TraceCheck {
    /// Net steps per stepper oid.
    pub net: std::collections::HashMap<u8, i64>,
    /// Steps in all.
    pub steps: u64,
    /// `queue_step` commands received.
    pub queue_steps: u64,
    /// Smallest lead (first step − receipt) of a received `queue_step`, ms of MCU time.
    pub min_lead_ms: f64,
    pub time_scale: f64,
}

/// Reads and checks the trace at `path` (see [`TraceCheck`]).
pub fn check_trace(path: &Path) -> TraceCheck {
    use firmware::trace::{read_trace, TraceRecord};
    let trace = read_trace(path).expect("trace");
    let freq = trace.clock_freq as f64;
    let mut check = TraceCheck {
        net: Default::default(),
        steps: 0,
        queue_steps: 0,
        min_lead_ms: f64::INFINITY,
        time_scale: trace.time_scale,
    };
    let mut last: std::collections::HashMap<u8, u64> = Default::default();
    for rec in &trace.records {
        match *rec {
            TraceRecord::Step { oid, dir, clock, .. } => {
                *check.net.entry(oid).or_default() += if dir { 1 } else { -1 };
                check.steps += 1;
                let prev = last.insert(oid, clock).unwrap_or(0);
                assert!(
                    clock >= prev,
                    "oid {oid}: step at {clock} before previous step at {prev}"
                );
            }
            TraceRecord::QueueStep {
                received_clock,
                first_step_clock,
                ..
            } => {
                check.queue_steps += 1;
                let lead_ms = (first_step_clock as f64 - received_clock as f64) / freq * 1e3;
                check.min_lead_ms = check.min_lead_ms.min(lead_ms);
            }
            TraceRecord::Shutdown { .. } => panic!("the MCU shut down: {rec:?}"),
        }
    }
    check
}

/// Asserts that stepper `stepper_oid` took no step after the stop of a trsync on its MCU (the
/// latest trsync trigger in `trace`, only trsync `trsync_oid` when given); returns the trace.
pub fn assert_no_step_after_stop(
    trace: &Path,
    trsync_oid: Option<u8>,
    stepper_oid: u8,
) -> firmware::trace::TraceFile {
    use firmware::trace::{read_trace, TraceRecord};
    let t = read_trace(trace).expect("trace");
    let stop = t
        .triggers
        .iter()
        .filter(|r| !r.endstop && trsync_oid.is_none_or(|o| r.oid == o))
        .map(|r| r.clock)
        .max()
        .expect("the main MCU's trsync never triggered");
    let last_step = t
        .records
        .iter()
        .filter_map(|r| match *r {
            TraceRecord::Step { oid, clock, .. } if oid == stepper_oid => Some(clock),
            _ => None,
        })
        .max()
        .unwrap_or(0);
    assert!(
        last_step <= stop,
        "stepper oid {stepper_oid} stepped at {last_step} after the stop at {stop}"
    );
    t
}

/// Net steps per stepper oid in a simulated MCU's trace; fails the test if the MCU shut down.
pub fn net_steps(trace: &firmware::trace::TraceFile) -> std::collections::HashMap<u8, i64> {
    use firmware::trace::TraceRecord;
    let mut net = std::collections::HashMap::new();
    for r in &trace.records {
        if let TraceRecord::Step { oid, dir, .. } = *r {
            *net.entry(oid).or_default() += if dir { 1 } else { -1 };
        }
        assert!(!matches!(r, TraceRecord::Shutdown { .. }), "MCU shut down: {r:?}");
    }
    net
}

/// `cadence print GCODE --config CFG --trace TRACE`.
pub fn print_traced(gcode: &Path, cfg: &Path, trace: &Path) -> Command {
    let mut cmd = Command::new(bin("cadence"));
    cmd.arg("print")
        .arg(gcode)
        .arg("--config")
        .arg(cfg)
        .arg("--trace")
        .arg(trace);
    cmd
}

/// `cadence home --axes AXES --config CFG --trace TRACE`.
pub fn home_traced(axes: &str, cfg: &Path, trace: &Path) -> Command {
    let mut cmd = Command::new(bin("cadence"));
    cmd.args(["home", "--axes", axes, "--config"])
        .arg(cfg)
        .arg("--trace")
        .arg(trace);
    cmd
}

/// The run ended in exactly the homing timeout error.
pub fn homing_timed_out(run: &Run) -> bool {
    run.stderr
        .lines()
        .any(|l| l == "cadence: error: Communication timeout during homing")
}

/// The run failed on the homing timeout: `cadence home`'s error line, or a print's, which
/// names the G-code line first (`cadence: error: FILE:LINE: G28: Communication timeout during
/// homing`).
fn failed_on_homing_timeout(run: &Run) -> bool {
    run.code == Some(1)
        && run.stderr.lines().any(|l| {
            l.starts_with("cadence: error: ") && l.ends_with(": Communication timeout during homing")
        })
}

/// One timing-sensitive run at a time in a test binary: the runs [`retry_homing_timeouts`]
/// guards each start a host and two or more simulated MCUs, and on 2 cores two of them side by
/// side are the likeliest cause of a missed 25 ms budget.
static TIMING_SENSITIVE: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Pauses before the 2nd, 3rd and 4th attempt: a starved VM's bad spell usually lasts seconds,
/// so trying again at once tends to land in the same spell.
const RETRY_PAUSES: [Duration; 3] = [
    Duration::from_secs(2),
    Duration::from_secs(5),
    Duration::from_secs(10),
];

/// Runs `attempt` (one at a time in this test binary) up to 4 times, pausing between attempts,
/// while its run (`run_of`) fails on the homing timeout (of `cadence home` or of a print's
/// G28/PROBE): a starved VM (CI runs tests in parallel on 2 cores) can legitimately miss the
/// 25 ms budget. A wrong position is never retried.
pub fn retry_homing_timeouts<T>(mut attempt: impl FnMut() -> T, run_of: impl Fn(&T) -> &Run) -> T {
    let _one_at_a_time = TIMING_SENSITIVE
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let mut out = attempt();
    for pause in RETRY_PAUSES {
        if !failed_on_homing_timeout(run_of(&out)) {
            break;
        }
        let why = run_of(&out)
            .stderr
            .lines()
            .filter(|l| l.contains("communication timeout") || l.contains("lateness"))
            .collect::<Vec<_>>()
            .join("\n  ");
        eprintln!("homing timed out (retrying in {} s):\n  {why}", pause.as_secs());
        std::thread::sleep(pause);
        out = attempt();
    }
    out
}

/// The stop bounds of every pass of a homing report line (`… last step 42 µs before the
/// trigger, first cancelled 208 µs after the trigger …`): (last executed step, first cancelled
/// step) in µs after the trigger, negative before it.
pub fn stop_bounds(line: &str) -> Vec<(f64, f64)> {
    let signed = |s: &str| -> Option<f64> {
        let s = s.trim_start();
        let (n, rest) = s.split_once(' ')?;
        let n: f64 = n.parse().ok()?;
        let rest = rest.trim_start_matches("µs ").trim_start_matches("us ");
        if rest.starts_with("before") {
            Some(-n)
        } else if rest.starts_with("after") {
            Some(n)
        } else {
            None
        }
    };
    line.split("last step ")
        .skip(1)
        .filter_map(|s| {
            let (last, rest) = s.split_once(", first cancelled ")?;
            Some((signed(last)?, signed(rest)?))
        })
        .collect()
}

/// `cadence print GCODE --config CFG --time-scale 5 --no-realtime` on the simulated printer
/// (`gcode` written to `dir/print.gcode`), its simulated main MCU given `sim_args` too
/// (`CADENCE_SIM_ARGS_MCU`): the heater and sensor tests' run.
pub fn print_scaled(dir: &Path, cfg: &Path, gcode: &str, sim_args: Option<&str>, timeout: Duration) -> Run {
    let g = dir.join("print.gcode");
    std::fs::write(&g, gcode).expect("write the G-code");
    let mut cmd = Command::new(bin("cadence"));
    cmd.args([
        "print",
        path_str(&g),
        "--config",
        path_str(cfg),
        "--time-scale",
        "5",
        "--no-realtime",
    ]);
    match sim_args {
        Some(a) => cmd.env("CADENCE_SIM_ARGS_MCU", a),
        None => cmd.env_remove("CADENCE_SIM_ARGS_MCU"),
    };
    run(&mut cmd, timeout)
}

/// A path as the `&str` a command line takes (the tests' paths are UTF-8).
fn path_str(p: &Path) -> &str {
    p.to_str().expect("UTF-8 path")
}

/// The number after `what` in the first line of `out` containing `line` (a print summary's
/// `temperature_sensor board: 31.2 °C (lowest 25.0 …)`, an M105 answer's `T0:`).
pub fn value_after(out: &str, line: &str, what: &str) -> f64 {
    let l = out
        .lines()
        .find(|l| l.contains(line))
        .unwrap_or_else(|| panic!("no '{line}' in\n{out}"));
    let rest = &l[l.find(what).unwrap_or_else(|| panic!("no '{what}' in {l}")) + what.len()..];
    let num: String = rest
        .trim_start()
        .chars()
        .take_while(|c| c.is_ascii_digit() || *c == '.' || *c == '-')
        .collect();
    num.parse()
        .unwrap_or_else(|_| panic!("no number after '{what}' in {l}"))
}

#[cfg(test)]
mod tests {
    #[test]
    fn stop_bounds_read_both_units_and_signs() {
        let line = "homing z: mcus mcu; pass 1 at 10 mm/s: trigger on 'mcu', overshoot 0.0000 mm, \
                    last step 42 µs before the trigger, first cancelled 208 µs after the trigger; \
                    pass 2 at 5 mm/s: trigger on 'mcu', overshoot 0.0000 mm, last step 3 us after the \
                    trigger, first cancelled 250 us after the trigger; position 0.000000";
        assert_eq!(super::stop_bounds(line), [(-42.0, 208.0), (3.0, 250.0)]);
    }
}
