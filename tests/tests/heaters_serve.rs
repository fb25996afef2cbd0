//! End to end on `cadence serve`: the heater loop runs in a service session (a target set over
//! the API heats the simulated hotend, seen in the `extruder` status object), PID_CALIBRATE
//! answers in the G-code output, and SAVE_CONFIG rewrites the printer.cfg the service was
//! started with and restarts the printer, which comes back ready with the saved gains.

use std::io::{Read, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use cadence_tests::{bin, scratch, workspace};
use serde_json::{json, Value};

/// A minimal client of the API socket (JSON messages ended by 0x03).
struct Api {
    stream: UnixStream,
    pending: Vec<u8>,
    next_id: u64,
    /// Notifications read while waiting for replies.
    notes: Vec<Value>,
}

impl Api {
    fn connect(path: &Path) -> Api {
        let stream = UnixStream::connect(path).expect("connect to the API socket");
        stream
            .set_read_timeout(Some(Duration::from_secs(240)))
            .expect("timeout");
        Api {
            stream,
            pending: Vec::new(),
            next_id: 1,
            notes: Vec::new(),
        }
    }

    fn read(&mut self) -> Value {
        loop {
            if let Some(end) = self.pending.iter().position(|&b| b == 0x03) {
                let msg: Vec<u8> = self.pending.drain(..=end).collect();
                return serde_json::from_slice(&msg[..end]).expect("a JSON message");
            }
            let mut buf = [0u8; 65536];
            let n = self.stream.read(&mut buf).expect("read from the service");
            assert!(n > 0, "the service closed the connection");
            self.pending.extend_from_slice(&buf[..n]);
        }
    }

    fn ok(&mut self, method: &str, params: Value) -> Value {
        let id = json!(self.next_id);
        self.next_id += 1;
        let mut bytes =
            serde_json::to_vec(&json!({"id": id, "method": method, "params": params})).expect("json");
        bytes.push(0x03);
        self.stream.write_all(&bytes).expect("write");
        loop {
            let msg = self.read();
            if msg.get("id") == Some(&id) {
                assert!(msg.get("error").is_none(), "{method}: {msg}");
                return msg["result"].clone();
            }
            self.notes.push(msg);
        }
    }

    fn wait_ready(&mut self) {
        let deadline = Instant::now() + Duration::from_secs(120);
        loop {
            let info = self.ok("info", json!({}));
            if info["state"] == "ready" {
                return;
            }
            assert!(Instant::now() < deadline, "never ready: {info}");
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    fn status(&mut self, object: &str) -> Value {
        let q = self.ok("objects/query", json!({"objects": {object: null}}));
        q["status"][object].clone()
    }
}

/// The service process, killed when the test ends.
struct Service(Child);

impl Drop for Service {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The built-in simulated printer without endstops, as a file the service may rewrite.
fn config(dir: &Path) -> PathBuf {
    let text: String = sysconfig::printer::SIMULATED_PRINTER_CFG
        .lines()
        .filter(|l| !l.starts_with("endstop_pin:") && !l.starts_with("homing_speed:"))
        .map(|l| format!("{l}\n"))
        .collect();
    let path = dir.join("printer.cfg");
    std::fs::write(&path, text).expect("write config");
    path
}

#[test]
fn a_service_session_heats_calibrates_and_saves_its_config() {
    let dir = scratch("heat-serve");
    let cfg = config(&dir);
    let socket = dir.join("klippy.sock");
    let child = Command::new(bin("cadence"))
        .args(["serve", "--no-realtime", "--time-scale", "5", "-a"])
        .arg(&socket)
        .arg("--config")
        .arg(&cfg)
        .current_dir(workspace())
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(dir.join("stderr.txt")).expect("stderr file"))
        .spawn()
        .expect("start cadence serve");
    let _service = Service(child);
    let deadline = Instant::now() + Duration::from_secs(60);
    while !socket.exists() {
        assert!(Instant::now() < deadline, "no API socket after 60 s");
        std::thread::sleep(Duration::from_millis(20));
    }
    let mut api = Api::connect(&socket);
    api.wait_ready();
    let list = api.ok("objects/list", json!({}));
    for name in [
        "heaters",
        "extruder",
        "heater_bed",
        "fan",
        "heater_fan hotend_fan",
    ] {
        assert!(
            list["objects"].as_array().expect("list").contains(&json!(name)),
            "{list}"
        );
    }

    // A target over the API heats the hotend in the session's heater loop.
    api.ok("gcode/script", json!({"script": "M104 S60"}));
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let e = api.status("extruder");
        if e["target"] == json!(60.0) && e["temperature"].as_f64().unwrap_or(0.0) > 35.0 {
            assert!(
                e["power"].as_f64().is_some() && e["can_extrude"].is_boolean(),
                "{e}"
            );
            break;
        }
        assert!(Instant::now() < deadline, "the hotend did not heat: {e}");
        std::thread::sleep(Duration::from_millis(100));
    }
    assert_eq!(api.status("heater_fan hotend_fan")["speed"], json!(1.0));

    // PID_CALIBRATE answers in the G-code output; SAVE_CONFIG writes and restarts.
    api.ok("gcode/subscribe_output", json!({"response_template": {}}));
    api.ok(
        "gcode/script",
        json!({"script": "PID_CALIBRATE HEATER=extruder TARGET=200"}),
    );
    let said = |api: &Api, what: &str| api.notes.iter().any(|n| n.to_string().contains(what));
    let deadline = Instant::now() + Duration::from_secs(30);
    while !said(&api, "PID parameters: pid_Kp=") {
        assert!(Instant::now() < deadline, "no PID result in {:?}", api.notes);
        let _ = api.ok("info", json!({}));
        std::thread::sleep(Duration::from_millis(50));
    }
    api.ok("gcode/script", json!({"script": "SAVE_CONFIG"}));
    let text = std::fs::read_to_string(&cfg).expect("config");
    assert!(
        text.contains("#*# [extruder]\n#*# control = pid\n#*# pid_kp = "),
        "{text}"
    );
    assert!(text.contains("\n#pid_Kp: 22.2\n"), "{text}");
    let kp = text
        .split("#*# pid_kp = ")
        .nth(1)
        .and_then(|r| r.lines().next())
        .expect("pid_kp")
        .to_string();
    // The service restarts after answering: the reopened printer reads the saved gains and
    // is a new session (cold targets).
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let info = api.ok("info", json!({}));
        let q = api.ok("objects/query", json!({"objects": {"configfile": ["settings"]}}));
        if info["state"] == "ready"
            && q["status"]["configfile"]["settings"]["extruder"]["pid_kp"] == json!(kp)
        {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "never reopened with pid_kp {kp}: {info} {q}"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    assert_eq!(api.status("extruder")["target"], json!(0.0));
    let _ = std::fs::remove_dir_all(&dir);
}
