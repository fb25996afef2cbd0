//! End to end with the IO stage in its own process: `cadence print --io-process` starts
//! `cadence serve --role io`, which owns the simulated MCU; step batches, the MCU info, clock
//! snapshots and the status cross between the two processes over iceoryx2. The MCU's positions
//! (read back by the IO process) must equal the planner's, and the MCU's step trace must show
//! exactly those net steps.
//!
//! Homing needs the in-process IO stage, and the planner refuses moves before G28; the prints
//! here use the example printer without endstops, where G28 only declares the axes homed.

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use cadence_tests::{
    assert_exit, assert_success, bin, cadence, check_trace, printer_without_endstops, scratch, workspace, Run,
};

const TIMEOUT: Duration = Duration::from_secs(180);

fn square() -> std::path::PathBuf {
    workspace().join("examples/square.gcode")
}

/// The summary's rows: (stepper, mcu pos, host pos, position mm).
fn rows(stdout: &str) -> Vec<(String, i64, i64, f64)> {
    let mut out = Vec::new();
    for line in stdout.lines() {
        let f: Vec<&str> = line.split_whitespace().collect();
        if f.len() >= 5 && (f[0].starts_with("stepper_") || f[0] == "extruder") {
            if let (Ok(m), Ok(h), Ok(mm)) = (f[2].parse(), f[3].parse(), f[4].parse()) {
                out.push((f[0].to_string(), m, h, mm));
            }
        }
    }
    out
}

fn check_square(run: &Run, trace: &std::path::Path) {
    assert_success(run);
    assert!(!run.stdout.contains("MISMATCH"), "{}", run.stdout);
    let rows = rows(&run.stdout);
    assert_eq!(rows.len(), 4, "summary rows missing:\n{}", run.stdout);
    for (name, want) in [("stepper_x", 10.0), ("stepper_y", 10.0), ("stepper_z", 5.0)] {
        let r = rows.iter().find(|r| r.0 == name).unwrap();
        assert!((r.3 - want).abs() < 1e-6, "{name} at {} mm, want {want}", r.3);
    }
    // The MCU's pins: every stepper's net steps equal the position both processes agree on
    // (the toolhead starts at 0; G28 without endstops moves nothing).
    let check = check_trace(trace);
    assert!(check.queue_steps > 0, "no queue_step was received");
    assert!(
        check.min_lead_ms >= 100.0,
        "a queue_step arrived with only {:.2} ms lead",
        check.min_lead_ms
    );
    for (oid, (name, mcu, host, _)) in rows.iter().enumerate() {
        assert_eq!(mcu, host, "{name}");
        let net = check.net.get(&(oid as u8)).copied().unwrap_or(0);
        assert_eq!(net, *host, "{name}: the trace shows {net} net steps");
    }
    assert!(
        run.stdout.contains("in IO process"),
        "no IO process lead line:\n{}",
        run.stdout
    );
    assert!(
        run.stdout.contains("dropped (queue full)"),
        "no logger report:\n{}",
        run.stdout
    );
}

#[test]
fn io_process_prints_the_square_exactly() {
    let dir = scratch("serve-io");
    let cfg = printer_without_endstops(&dir);
    let trace = dir.join("square.trace");
    let log = dir.join("print.log");
    let run = cadence(
        &[
            "print",
            square().to_str().unwrap(),
            "--config",
            cfg.to_str().unwrap(),
            "--io-process",
            "--trace",
            trace.to_str().unwrap(),
            "--time-scale",
            "2",
            "--log-file",
            log.to_str().unwrap(),
        ],
        TIMEOUT,
    );
    check_square(&run, &trace);
    // Both processes logged into the same file through their logger threads.
    let text = std::fs::read_to_string(&log).unwrap_or_default();
    assert!(text.contains("planner done"), "log:\n{text}");
    assert!(text.contains("serve: print done"), "log:\n{text}");
}

#[test]
fn io_process_refuses_homing_clearly() {
    // The built-in printer has endstops: its G28 would home with motion.
    let run = cadence(&["print", square().to_str().unwrap(), "--io-process"], TIMEOUT);
    assert_exit(&run, 1);
    assert!(
        run.stderr.contains("homing needs the in-process IO stage"),
        "{}",
        run.stderr
    );
    assert!(!run.stderr.contains("panicked"), "{}", run.stderr);
}

#[test]
fn io_process_refuses_heating_clearly() {
    let dir = scratch("serve-io-heat");
    let gcode = dir.join("heat.gcode");
    // Turning off and reporting pass; a target would never be driven, so it is refused.
    std::fs::write(&gcode, "M104 S0\nM105\nM109 S200\n").expect("write G-code");
    let run = cadence(&["print", gcode.to_str().unwrap(), "--io-process"], TIMEOUT);
    assert_exit(&run, 1);
    assert!(
        run.stderr
            .contains("heat.gcode:3: heaters and fans are driven only with the IO stage in this process"),
        "{}",
        run.stderr
    );
    assert!(!run.stderr.contains("panicked"), "{}", run.stderr);
}

#[test]
fn print_attaches_to_a_running_io_process() {
    let dir = scratch("serve-attach");
    let cfg = printer_without_endstops(&dir);
    let trace = dir.join("attach.trace");
    let instance = format!("test-attach-{}", std::process::id());
    let mut serve = Command::new(bin("cadence"))
        .args([
            "serve",
            "--role",
            "io",
            "--instance",
            &instance,
            "--idle-timeout",
            "150",
        ])
        .arg("--config")
        .arg(&cfg)
        .arg("--trace")
        .arg(&trace)
        .current_dir(workspace())
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start cadence serve");
    let run = cadence(
        &[
            "print",
            square().to_str().unwrap(),
            "--config",
            cfg.to_str().unwrap(),
            "--io-attach",
            &instance,
        ],
        TIMEOUT,
    );
    // The IO process serves one print and exits.
    let deadline = Instant::now() + Duration::from_secs(60);
    let status = loop {
        if let Some(s) = serve.try_wait().expect("wait") {
            break Some(s);
        }
        if Instant::now() > deadline {
            let _ = serve.kill();
            let _ = serve.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let out = serve.wait_with_output().ok();
    let serve_out = out
        .map(|o| {
            format!(
                "{}\n{}",
                String::from_utf8_lossy(&o.stdout),
                String::from_utf8_lossy(&o.stderr)
            )
        })
        .unwrap_or_default();
    check_square(&run, &trace);
    assert!(
        status.map(|s| s.success()).unwrap_or(false),
        "serve: {status:?}\n{serve_out}"
    );
    assert!(serve_out.contains("io: mcu 'mcu'"), "{serve_out}");
}
