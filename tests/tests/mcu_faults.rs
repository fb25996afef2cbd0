//! Bad MCUs end a print with a clear one-line error and a non-zero exit, never a hang.

use std::io::Write;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use cadence_tests::{assert_exit, bin, cadence, scratch, workspace};

/// The built-in printer's config with its MCU moved to `serial`.
fn config_with_serial(dir: &std::path::Path, serial: &str) -> std::path::PathBuf {
    let text =
        sysconfig::printer::SIMULATED_PRINTER_CFG.replace("serial: simulator", &format!("serial: {serial}"));
    assert!(text.contains(serial));
    // The [simulator] section is only for simulated MCUs; drop it.
    let text = text.replace("[simulator]", "[simulator]\n# unused here");
    let path = dir.join("printer.cfg");
    std::fs::write(&path, text).unwrap();
    path
}

#[test]
fn mcu_that_never_answers_identify() {
    let dir = scratch("silent");
    // A pty whose other end nobody serves: the host's identify goes unanswered.
    let pty = nix::pty::openpty(None, None).expect("openpty");
    let slave = std::fs::read_link(format!(
        "/proc/self/fd/{}",
        std::os::fd::AsRawFd::as_raw_fd(&pty.slave)
    ))
    .expect("slave path");
    let cfg = config_with_serial(&dir, slave.to_str().unwrap());
    let gcode = workspace().join("examples/square.gcode");
    let started = Instant::now();
    let run = cadence(
        &[
            "print",
            gcode.to_str().unwrap(),
            "--config",
            cfg.to_str().unwrap(),
        ],
        Duration::from_secs(60),
    );
    assert_exit(&run, 1);
    assert!(run.stderr.contains("identify"), "{}", run.stderr);
    assert!(!run.stderr.contains("panicked"), "{}", run.stderr);
    assert!(started.elapsed() < Duration::from_secs(60));
    drop(pty);
}

#[test]
fn mcu_process_dying_mid_print() {
    let dir = scratch("dies");
    let trace = dir.join("t.trace");
    let gcode = workspace().join("examples/square.gcode");
    let mut child = Command::new(bin("cadence"))
        .args([
            "print",
            gcode.to_str().unwrap(),
            "--trace",
            trace.to_str().unwrap(),
        ])
        .current_dir(workspace())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Wait until the simulated MCU runs (its trace file appears), then kill it.
    let deadline = Instant::now() + Duration::from_secs(30);
    let mcu_pid = loop {
        assert!(Instant::now() < deadline, "the simulated MCU never started");
        let children =
            std::fs::read_to_string(format!("/proc/{0}/task/{0}/children", child.id())).unwrap_or_default();
        if let Some(pid) = children.split_whitespace().next() {
            if trace.exists() {
                break pid.to_string();
            }
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    std::thread::sleep(Duration::from_millis(1500));
    let killed = Command::new("kill").args(["-9", &mcu_pid]).status().unwrap();
    assert!(killed.success());
    let deadline = Instant::now() + Duration::from_secs(60);
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!("cadence hung after its MCU died");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let mut stderr = String::new();
    std::io::Read::read_to_string(child.stderr.as_mut().unwrap(), &mut stderr).unwrap();
    assert_eq!(status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("mcu 'mcu'"), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    let _ = std::io::stderr().flush();
}
