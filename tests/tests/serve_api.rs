//! `cadence serve` on the simulated printer, driven over Klipper's API socket as a front end
//! (Moonraker) drives Klipper: the socket's permissions, `info` until ready, objects, G-code
//! scripts (a refused command fails alone and the printer stays ready), subscriptions, bad
//! messages, an emergency stop and a firmware restart, then SIGTERM → exit 0.

use std::io::{Read, Write};
use std::os::unix::fs::PermissionsExt;
use std::os::unix::net::UnixStream;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use cadence_tests::api::{start_service, Api, Service};
use cadence_tests::{printer_without_endstops, scratch, workspace};
use serde_json::{json, Value};

/// Starts `cadence serve` with `printer` arguments (`--config PATH` or `--simulated`), its
/// log in `dir/serve.log`.
fn start(dir: &Path, socket: &Path, printer: &[&std::ffi::OsStr]) -> Service {
    let log = dir.join("serve.log");
    let mut args = printer.to_vec();
    args.extend(["--log-file".as_ref(), log.as_os_str()]);
    start_service(dir, socket, &args)
}

#[test]
fn a_front_end_drives_the_service_over_the_api_socket() {
    let dir = scratch("serve-api");
    let socket = dir.join("klippy.sock");
    let cfg = printer_without_endstops(&dir);
    let mut service = start(&dir, &socket, &["--config".as_ref(), cfg.as_os_str()]);
    let mode = std::fs::metadata(&socket).expect("socket").permissions().mode();
    assert_eq!(mode & 0o777, 0o600, "the socket is owner-only: {mode:o}");

    let mut api = Api::connect(&socket, Duration::from_secs(120));
    let info = api.wait_state("ready");
    assert_eq!(info["state_message"], "Printer is ready");
    assert_eq!(info["process_id"], json!(service.0.id()));
    assert_eq!(info["config_file"], json!(cfg.display().to_string()));
    for key in [
        "hostname",
        "software_version",
        "user_id",
        "group_id",
        "app",
        "log_file",
    ] {
        assert!(info.get(key).is_some(), "info has {key}: {info}");
    }
    let endpoints = api.ok("list_endpoints", json!({}));
    assert!(endpoints["endpoints"]
        .as_array()
        .expect("list")
        .contains(&json!("gcode/script")));
    let objects = api.ok("objects/list", json!({}));
    for name in [
        "webhooks",
        "toolhead",
        "print_stats",
        "mcu",
        "latency",
        "configfile",
    ] {
        assert!(
            objects["objects"]
                .as_array()
                .expect("list")
                .contains(&json!(name)),
            "{objects}"
        );
    }
    api.ok("gcode/subscribe_output", json!({"response_template": {}}));

    // G28 homes; the query then shows the homed axes.
    api.ok("gcode/script", json!({"script": "G28"}));
    let q = api.ok(
        "objects/query",
        json!({"objects": {"toolhead": ["homed_axes", "position"], "webhooks": null}}),
    );
    assert_eq!(q["status"]["toolhead"]["homed_axes"], "xyz", "{q}");
    assert_eq!(q["status"]["webhooks"]["state"], "ready", "{q}");
    assert!(q["eventtime"].is_number(), "{q}");

    // A refused command fails alone: the printer stays ready and takes the next one.
    let e = api.error("gcode/script", json!({"script": "G1 X100000"}));
    assert!(!e.is_empty());
    assert_eq!(api.ok("info", json!({}))["state"], "ready");
    let output_seen = api.notes.iter().any(|n| {
        n["method"] == "notify_gcode_response"
            && n["params"]["response"]
                .as_str()
                .is_some_and(|r| r.starts_with("!! "))
    });
    assert!(
        output_seen,
        "the error went to the G-code output: {:?}",
        api.notes
    );

    // Subscriptions: the changed fields come every 250 ms.
    let sub = api.ok(
        "objects/subscribe",
        json!({"objects": {"toolhead": ["position"]}}),
    );
    assert!(sub["status"]["toolhead"]["position"].is_array(), "{sub}");
    api.notes.clear();
    api.ok("gcode/script", json!({"script": "G1 X20 Y10 F6000"}));
    let deadline = Instant::now() + Duration::from_secs(30);
    let moved = loop {
        if let Some(n) = api.notes.iter().find(|n| n["method"] == "notify_status_update") {
            break n.clone();
        }
        assert!(Instant::now() < deadline, "no status update: {:?}", api.notes);
        let m = api.read();
        api.notes.push(m);
    };
    assert!(moved["params"]["eventtime"].is_number(), "{moved}");
    assert_eq!(
        moved["params"]["status"]["toolhead"]["position"][0],
        json!(20.0),
        "{moved}"
    );

    // Bad requests: each gets Klipper's error shape and the connection goes on.
    let e = api.error("no/such/endpoint", json!({}));
    assert!(
        e.contains("No registered callback for path 'no/such/endpoint'"),
        "{e}"
    );
    let e = api.error("gcode/script", json!({}));
    assert_eq!(e, "Missing Argument [script]");
    let e = api.error("gcode/script", json!({"script": 5}));
    assert_eq!(e, "Invalid Argument Type [script]");
    api.send_raw(b"{not json\x03");
    let r = api.reply(&Value::Null);
    assert!(
        r["error"]["message"]
            .as_str()
            .expect("message")
            .contains("not JSON"),
        "{r}"
    );
    api.send_raw(b"{\"id\":1,\"method\":\"info\xff\"}\x03");
    let r = api.reply(&Value::Null);
    assert!(
        r["error"]["message"].as_str().expect("message").contains("UTF-8"),
        "{r}"
    );

    // A second client sending over 1 MiB without 0x03 is disconnected; the first goes on.
    let mut flood = UnixStream::connect(&socket).expect("second client");
    flood
        .set_read_timeout(Some(Duration::from_secs(60)))
        .expect("timeout");
    let junk = vec![b' '; 64 * 1024];
    for _ in 0..20 {
        if flood.write_all(&junk).is_err() {
            break;
        }
    }
    let mut buf = [0u8; 16];
    assert!(
        matches!(flood.read(&mut buf), Ok(0) | Err(_)),
        "the flooding client was dropped"
    );
    assert_eq!(api.ok("info", json!({}))["state"], "ready");

    // Emergency stop → shutdown with the reason; commands are refused; a firmware restart
    // brings the printer back.
    api.ok("emergency_stop", json!({}));
    let info = api.wait_state("shutdown");
    assert!(
        info["state_message"]
            .as_str()
            .expect("message")
            .contains("emergency stop"),
        "{info}"
    );
    let e = api.error("gcode/script", json!({"script": "G1 X1"}));
    assert!(e.contains("FIRMWARE_RESTART"), "{e}");
    api.ok("gcode/firmware_restart", json!({}));
    api.wait_state("ready");
    api.ok("gcode/script", json!({"script": "G28 X\nG1 X5 F3000"}));

    // SIGTERM: motion stops, the log is flushed, exit 0, the socket is gone.
    let (status, stderr) = stop(&mut service, &dir, nix::sys::signal::Signal::SIGTERM);
    assert!(status.success(), "exit {status:?}\n{stderr}");
    assert!(!socket.exists(), "the socket was removed");
    assert!(
        stderr.contains("too slow") || stderr.contains("without its 0x03"),
        "{stderr}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Stops `service` with `signal` and returns its exit status and stderr.
fn stop(
    service: &mut Service,
    dir: &Path,
    signal: nix::sys::signal::Signal,
) -> (std::process::ExitStatus, String) {
    nix::sys::signal::kill(nix::unistd::Pid::from_raw(service.0.id() as i32), signal).expect("signal");
    let deadline = Instant::now() + Duration::from_secs(60);
    let status = loop {
        if let Some(s) = service.0.try_wait().expect("wait") {
            break s;
        }
        assert!(
            Instant::now() < deadline,
            "cadence serve did not stop on {signal}"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    (
        status,
        std::fs::read_to_string(dir.join("stderr.txt")).unwrap_or_default(),
    )
}

#[test]
fn the_built_in_simulated_printer_serves_and_stops_on_sigint() {
    let dir = scratch("serve-sim");
    let socket = dir.join("api.sock");
    let mut service = start(&dir, &socket, &["--simulated".as_ref()]);
    let mut api = Api::connect(&socket, Duration::from_secs(120));
    let info = api.wait_state("ready");
    assert_eq!(info["config_file"], Value::Null, "{info}");
    let q = api.ok(
        "objects/query",
        json!({"objects": {"configfile": ["config"], "mcu": null}}),
    );
    assert!(
        q["status"]["configfile"]["config"]["stepper_x"].is_object(),
        "{q}"
    );
    assert!(q["status"]["mcu"]["last_stats"].is_object(), "{q}");
    let (status, stderr) = stop(&mut service, &dir, nix::sys::signal::Signal::SIGINT);
    assert!(status.success(), "exit {status:?}\n{stderr}");
    assert!(!socket.exists(), "the socket was removed");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A status object's field.
fn field(api: &mut Api, object: &str, name: &str) -> Value {
    let q = api.ok("objects/query", json!({"objects": {object: [name]}}));
    q["status"][object][name].clone()
}

fn wait_field(api: &mut Api, object: &str, name: &str, want: &Value) {
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let v = field(api, object, name);
        if &v == want {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "{object}.{name} stayed {v}, not {want}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn sdcard_prints_pause_resume_at_the_same_byte_and_cancel() {
    let dir = scratch("serve-sd");
    let socket = dir.join("api.sock");
    let cfg = printer_without_endstops(&dir);
    let gcodes = dir.join("gcodes");
    std::fs::create_dir_all(&gcodes).expect("gcodes dir");
    // 60 moves of 5 mm at 20 mm/s: 15 s, far more than the planner buffers ahead.
    let mut text = String::from("G28\nM117 Printing zigzag\nM73 P10\n");
    for k in 0..60 {
        text.push_str(&format!("G1 X{} Y10 F1200\n", if k % 2 == 0 { 5 } else { 0 }));
    }
    text.push_str("G1 X42 Y7\n");
    std::fs::write(gcodes.join("zig zag.gcode"), &text).expect("gcode");
    let mut service = start(
        &dir,
        &socket,
        &[
            "--config".as_ref(),
            cfg.as_os_str(),
            "--virtual-sdcard".as_ref(),
            gcodes.as_os_str(),
        ],
    );
    let mut api = Api::connect(&socket, Duration::from_secs(120));
    api.wait_state("ready");

    let e = api.error(
        "gcode/script",
        json!({"script": "SDCARD_PRINT_FILE FILENAME=../no-endstops.cfg"}),
    );
    assert!(e.contains("Unable to open file"), "{e}");
    api.ok(
        "gcode/script",
        json!({"script": "SDCARD_PRINT_FILE FILENAME=\"zig zag.gcode\""}),
    );
    wait_field(&mut api, "print_stats", "state", &json!("printing"));
    wait_field(&mut api, "display_status", "message", &json!("Printing zigzag"));
    assert_eq!(field(&mut api, "print_stats", "filename"), json!("zig zag.gcode"));

    api.ok("pause_resume/pause", json!({}));
    assert_eq!(field(&mut api, "pause_resume", "is_paused"), json!(true));
    assert_eq!(field(&mut api, "print_stats", "state"), json!("paused"));
    let at = field(&mut api, "virtual_sdcard", "file_position");
    let size = field(&mut api, "virtual_sdcard", "file_size");
    assert!(at.as_u64() < size.as_u64(), "paused at {at} of {size}");
    std::thread::sleep(Duration::from_millis(1500));
    assert_eq!(
        field(&mut api, "virtual_sdcard", "file_position"),
        at,
        "nothing read while paused"
    );
    let e = api.error("gcode/script", json!({"script": "PAUSE"}));
    assert_eq!(e, "Print already paused");

    api.ok("pause_resume/resume", json!({}));
    wait_field(&mut api, "print_stats", "state", &json!("complete"));
    assert_eq!(field(&mut api, "virtual_sdcard", "progress"), json!(1.0));
    let pos = field(&mut api, "toolhead", "position");
    assert_eq!(
        (pos[0].as_f64(), pos[1].as_f64()),
        (Some(42.0), Some(7.0)),
        "{pos}"
    );
    let r = api.ok("gcode/script", json!({"script": "M27"}));
    assert!(r.is_object());

    // Cancel: the print ends, nothing more moves once what was queued ran.
    api.ok("gcode/script", json!({"script": "M23 zig zag.gcode\nM24"}));
    wait_field(&mut api, "print_stats", "state", &json!("printing"));
    api.ok("pause_resume/cancel", json!({}));
    assert_eq!(field(&mut api, "print_stats", "state"), json!("cancelled"));
    assert_eq!(field(&mut api, "virtual_sdcard", "is_active"), json!(false));
    let e = api.error("gcode/script", json!({"script": "RESUME"}));
    assert!(e.contains("not paused"), "{e}");
    let after = field(&mut api, "toolhead", "position");
    std::thread::sleep(Duration::from_millis(1000));
    assert_eq!(
        field(&mut api, "toolhead", "position"),
        after,
        "nothing planned after the cancel"
    );
    assert_eq!(api.ok("info", json!({}))["state"], "ready");

    let (status, stderr) = stop(&mut service, &dir, nix::sys::signal::Signal::SIGTERM);
    assert!(status.success(), "exit {status:?}\n{stderr}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_gcode_pseudo_terminal_answers_ok_and_errors() {
    let dir = scratch("serve-pty");
    let socket = dir.join("api.sock");
    let link = dir.join("printer");
    let cfg = printer_without_endstops(&dir);
    let mut service = start(
        &dir,
        &socket,
        &[
            "--config".as_ref(),
            cfg.as_os_str(),
            "-I".as_ref(),
            link.as_os_str(),
        ],
    );
    let mut api = Api::connect(&socket, Duration::from_secs(120));
    api.wait_state("ready");
    let mut tty = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&link)
        .expect("open the G-code terminal");
    let mut answers = std::io::BufReader::new(tty.try_clone().expect("clone"));
    let mut read_line = || {
        let mut line = String::new();
        std::io::BufRead::read_line(&mut answers, &mut line).expect("read an answer");
        line
    };
    tty.write_all(b"G28\n").expect("write");
    assert_eq!(read_line(), "ok\n");
    tty.write_all(b"G1 X100000\n").expect("write");
    let error = read_line();
    assert!(error.starts_with("!! "), "{error}");
    assert_eq!(read_line(), "ok\n");
    tty.write_all(b"G1 X12 F3000\n").expect("write");
    assert_eq!(read_line(), "ok\n");
    assert_eq!(api.ok("info", json!({}))["state"], "ready");
    let (status, stderr) = stop(&mut service, &dir, nix::sys::signal::Signal::SIGTERM);
    assert!(status.success(), "exit {status:?}\n{stderr}");
    assert!(std::fs::symlink_metadata(&link).is_err(), "the link was removed");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_service_unit_passes_systemd_analyze_verify() {
    let dir = scratch("serve-unit");
    let run = cadence_tests::cadence(
        &[
            "service",
            "print",
            "--config",
            "examples/simulated-cartesian.cfg",
            "--user",
            "root",
        ],
        Duration::from_secs(60),
    );
    cadence_tests::assert_success(&run);
    for want in [
        "ExecStart=",
        " serve --config ",
        "LimitRTPRIO=",
        "LimitMEMLOCK=infinity",
        "Restart=on-failure",
    ] {
        assert!(run.stdout.contains(want), "{want} missing:\n{}", run.stdout);
    }
    let unit = dir.join("cadence.service");
    std::fs::write(&unit, &run.stdout).expect("write the unit");
    match Command::new("systemd-analyze").arg("verify").arg(&unit).output() {
        Err(e) => println!("SKIPPED systemd-analyze verify: systemd-analyze not available ({e})"),
        Ok(out) => {
            let err = String::from_utf8_lossy(&out.stderr);
            // Only complaints about this unit count (the host's own units may have some).
            let ours: Vec<&str> = err.lines().filter(|l| l.contains("cadence.service")).collect();
            assert!(
                out.status.success() && ours.is_empty(),
                "systemd-analyze verify:\n{err}"
            );
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_printer_that_cannot_start_is_in_error_with_the_reason_and_the_service_stays_up() {
    let dir = scratch("serve-error");
    let socket = dir.join("api.sock");
    let text = std::fs::read_to_string(workspace().join("examples/simulated-cartesian.cfg")).expect("config");
    let cfg = dir.join("absent.cfg");
    let mut body: Vec<String> = Vec::new();
    let mut in_mcu = false;
    for line in text.lines() {
        if line.starts_with('[') {
            in_mcu = line.trim() == "[mcu]";
        }
        if in_mcu && line.trim_start().starts_with("serial") {
            body.push("serial: /dev/ttyCADENCE_ABSENT".to_string());
        } else {
            body.push(line.to_string());
        }
    }
    std::fs::write(&cfg, body.join("\n")).expect("write config");
    let mut service = start(
        &dir,
        &socket,
        &[
            "--config".as_ref(),
            cfg.as_os_str(),
            "--retry".as_ref(),
            "0.5".as_ref(),
        ],
    );
    let mut api = Api::connect(&socket, Duration::from_secs(120));
    let info = api.wait_state("error");
    let message = info["state_message"].as_str().expect("message");
    assert!(message.contains("ttyCADENCE_ABSENT"), "{message}");
    assert!(message.contains("RESTART"), "{message}");
    let e = api.error("gcode/script", json!({"script": "G28"}));
    assert!(e.contains("ttyCADENCE_ABSENT"), "{e}");
    // Still retrying, still answering: each retry is "startup" for as long as it takes to fail
    // again (a moment, longer on a loaded machine), then "error" with the reason again.
    std::thread::sleep(Duration::from_millis(1500));
    let state = api.ok("info", json!({}))["state"].clone();
    assert!(state == "error" || state == "startup", "{state}");
    let again = api.wait_state("error");
    assert!(
        again["state_message"]
            .as_str()
            .is_some_and(|m| m.contains("ttyCADENCE_ABSENT")),
        "{again}"
    );
    let (status, stderr) = stop(&mut service, &dir, nix::sys::signal::Signal::SIGTERM);
    assert!(status.success(), "exit {status:?}\n{stderr}");
    let _ = std::fs::remove_dir_all(&dir);
}
