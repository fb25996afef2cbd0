//! Moonraker, unmodified, attached to `cadence serve` on the simulated printer, driven through
//! its HTTP API as Mainsail or Fluidd drive it: `/printer/info` ready, an objects query, G28,
//! a file upload and print start, pause, resume, cancel, an emergency stop (shutdown with the
//! reason) and a firmware restart (ready again).
//!
//! Moonraker is found through `$MOONRAKER` (its `moonraker` executable, e.g. from
//! `python3 -m venv V && V/bin/pip install moonraker`) or `moonraker` on PATH; without it the
//! test says so and passes without running.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use cadence_tests::{bin, scratch, workspace};
use serde_json::Value;

/// Kills the process when the test ends (SIGTERM first, as a service manager would).
struct Proc(Child, &'static str);

impl Drop for Proc {
    fn drop(&mut self) {
        let pid = nix::unistd::Pid::from_raw(self.0.id() as i32);
        let _ = nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGTERM);
        let deadline = Instant::now() + Duration::from_secs(20);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.0.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        eprintln!("{} did not stop on SIGTERM: killed", self.1);
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn moonraker() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("MOONRAKER") {
        return Some(PathBuf::from(p)).filter(|p| p.is_file());
    }
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|d| d.join("moonraker"))
            .find(|p| p.is_file())
    })
}

/// One HTTP/1.1 request to Moonraker; the status code and the JSON body.
fn http(port: u16, method: &str, path: &str, body: Option<(&str, &[u8])>) -> (u16, Value) {
    let mut s = TcpStream::connect(("127.0.0.1", port)).expect("connect to Moonraker");
    s.set_read_timeout(Some(Duration::from_secs(60)))
        .expect("timeout");
    let mut req = format!("{method} {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n");
    match body {
        Some((ctype, data)) => {
            req.push_str(&format!(
                "Content-Type: {ctype}\r\nContent-Length: {}\r\n\r\n",
                data.len()
            ));
            s.write_all(req.as_bytes()).expect("write");
            s.write_all(data).expect("write body");
        }
        None => {
            req.push_str("Content-Length: 0\r\n\r\n");
            s.write_all(req.as_bytes()).expect("write");
        }
    }
    let mut out = Vec::new();
    s.read_to_end(&mut out).expect("read the response");
    let text = String::from_utf8_lossy(&out);
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    let code = head
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = if head.to_ascii_lowercase().contains("transfer-encoding: chunked") {
        dechunk(body)
    } else {
        body.to_string()
    };
    (code, serde_json::from_str(&body).unwrap_or(Value::String(body)))
}

fn dechunk(mut body: &str) -> String {
    let mut out = String::new();
    while let Some((size, rest)) = body.split_once("\r\n") {
        let n = usize::from_str_radix(size.trim(), 16).unwrap_or(0);
        if n == 0 || rest.len() < n {
            break;
        }
        out.push_str(&rest[..n]);
        body = rest[n..].trim_start_matches("\r\n");
    }
    out
}

fn get(port: u16, path: &str) -> Value {
    let (code, v) = http(port, "GET", path, None);
    assert_eq!(code, 200, "GET {path}: {v}");
    v["result"].clone()
}

fn post(port: u16, path: &str) -> Value {
    let (code, v) = http(port, "POST", path, None);
    assert_eq!(code, 200, "POST {path}: {v}");
    v["result"].clone()
}

/// Waits until `probe` gives `want` (Moonraker relays the host's state a little later).
fn wait_for(what: &str, mut probe: impl FnMut() -> Value, want: &str) -> Value {
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let v = probe();
        if v == want {
            return v;
        }
        assert!(Instant::now() < deadline, "{what} stayed {v}, not {want}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn print_state(port: u16) -> Value {
    get(port, "/printer/objects/query?print_stats=state")["status"]["print_stats"]["state"].clone()
}

fn info_state(port: u16) -> Value {
    let (code, v) = http(port, "GET", "/printer/info", None);
    if code != 200 {
        return Value::Null;
    }
    v["result"]["state"].clone()
}

/// The simulated printer without endstops (G28 homes without motion), with a virtual sdcard.
fn printer_cfg(dir: &Path, gcodes: &Path) -> PathBuf {
    let text = std::fs::read_to_string(workspace().join("examples/simulated-cartesian.cfg"))
        .expect("example config");
    let mut body: Vec<String> = text
        .lines()
        .filter(|l| {
            let l = l.trim_start();
            !(l.starts_with("endstop_pin")
                || l.starts_with("position_endstop")
                || l.starts_with("homing_speed"))
        })
        .map(str::to_string)
        .collect();
    body.push(format!(
        "\n[virtual_sdcard]\npath: {}\n\n[pause_resume]\n\n[display_status]\n",
        gcodes.display()
    ));
    let path = dir.join("printer.cfg");
    std::fs::write(&path, body.join("\n")).expect("write config");
    path
}

#[test]
fn moonraker_attaches_and_prints() {
    let Some(moonraker) = moonraker() else {
        println!(
            "SKIPPED: Moonraker not found ($MOONRAKER or `moonraker` on PATH; \
             `python3 -m venv V && V/bin/pip install moonraker` provides it)"
        );
        return;
    };
    let dir = scratch("serve-moonraker");
    let data = dir.join("data");
    let gcodes = data.join("gcodes");
    std::fs::create_dir_all(data.join("config")).expect("config dir");
    std::fs::create_dir_all(&gcodes).expect("gcodes dir");
    let socket = dir.join("klippy.sock");
    let cfg = printer_cfg(&dir, &gcodes);
    let port = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").expect("a free port");
        l.local_addr().expect("port").port()
    };
    std::fs::write(
        data.join("config/moonraker.conf"),
        format!(
            "[server]\nhost: 127.0.0.1\nport: {port}\nklippy_uds_address: {}\n\n\
             [authorization]\ntrusted_clients:\n    127.0.0.0/8\n",
            socket.display()
        ),
    )
    .expect("moonraker.conf");

    let _cadence = Proc(
        Command::new(bin("cadence"))
            .args(["serve", "--no-realtime", "--config"])
            .arg(&cfg)
            .arg("-a")
            .arg(&socket)
            .current_dir(workspace())
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.join("cadence.txt")).expect("log"))
            .spawn()
            .expect("start cadence serve"),
        "cadence serve",
    );
    let _moonraker = Proc(
        Command::new(&moonraker)
            .arg("-d")
            .arg(&data)
            .stdin(Stdio::null())
            .stdout(std::fs::File::create(dir.join("moonraker.txt")).expect("log"))
            .stderr(Stdio::null())
            .spawn()
            .expect("start moonraker"),
        "moonraker",
    );
    // Moonraker up and attached: /printer/info ready.
    let deadline = Instant::now() + Duration::from_secs(120);
    while TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(Instant::now() < deadline, "Moonraker did not listen on {port}");
        std::thread::sleep(Duration::from_millis(200));
    }
    wait_for("printer state", || info_state(port), "ready");
    let info = get(port, "/printer/info");
    assert_eq!(info["state_message"], "Printer is ready", "{info}");

    let q = get(port, "/printer/objects/query?toolhead&print_stats");
    assert!(q["status"]["toolhead"]["position"].is_array(), "{q}");
    assert_eq!(q["status"]["print_stats"]["state"], "standby", "{q}");

    assert_eq!(post(port, "/printer/gcode/script?script=G28"), "ok");
    let q = get(port, "/printer/objects/query?toolhead=homed_axes");
    assert_eq!(q["status"]["toolhead"]["homed_axes"], "xyz", "{q}");

    // Upload a file (multipart, as a browser does) and print it.
    let mut text = String::from("G28\n");
    for k in 0..120 {
        text.push_str(&format!("G1 X{} Y10 F1200\n", if k % 2 == 0 { 5 } else { 0 }));
    }
    let boundary = "cadence-test-boundary";
    let mut form = format!(
        "--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"zigzag.gcode\"\r\n\
         Content-Type: application/octet-stream\r\n\r\n"
    )
    .into_bytes();
    form.extend_from_slice(text.as_bytes());
    form.extend_from_slice(format!("\r\n--{boundary}--\r\n").as_bytes());
    let (code, up) = http(
        port,
        "POST",
        "/server/files/upload",
        Some((&format!("multipart/form-data; boundary={boundary}"), &form)),
    );
    assert!(code == 200 || code == 201, "upload: {code} {up}");
    assert!(
        gcodes.join("zigzag.gcode").is_file(),
        "the upload is in the sdcard directory"
    );

    assert_eq!(post(port, "/printer/print/start?filename=zigzag.gcode"), "ok");
    wait_for("print state", || print_state(port), "printing");
    assert_eq!(post(port, "/printer/print/pause"), "ok");
    wait_for("print state", || print_state(port), "paused");
    let q = get(
        port,
        "/printer/objects/query?pause_resume&virtual_sdcard=progress",
    );
    assert_eq!(q["status"]["pause_resume"]["is_paused"], true, "{q}");
    assert_eq!(post(port, "/printer/print/resume"), "ok");
    wait_for("print state", || print_state(port), "printing");
    assert_eq!(post(port, "/printer/print/cancel"), "ok");
    wait_for("print state", || print_state(port), "cancelled");

    // Emergency stop: shutdown with the reason; a firmware restart brings it back.
    assert_eq!(post(port, "/printer/emergency_stop"), "ok");
    wait_for("printer state", || info_state(port), "shutdown");
    let info = get(port, "/printer/info");
    let message = info["state_message"].as_str().unwrap_or("");
    assert!(message.contains("emergency stop"), "{info}");
    assert_eq!(post(port, "/printer/firmware_restart"), "ok");
    wait_for("printer state", || info_state(port), "ready");
    assert_eq!(post(port, "/printer/gcode/script?script=G28"), "ok");
    let _ = std::fs::remove_dir_all(&dir);
}
