//! A client of `cadence serve`'s API socket as a front end (Moonraker) drives it: Klipper's
//! protocol, JSON messages each ended by 0x03, replies matched by id with the notifications
//! read on the way kept; and the service process, killed when the test ends.

use std::ffi::OsStr;
use std::io::{Read, Write};
use std::os::unix::net::UnixStream;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::{json, Value};

/// A client of the API socket.
#[derive(Debug)]
pub struct Api {
    stream: UnixStream,
    pending: Vec<u8>,
    next_id: u64,
    /// Notifications read while waiting for replies.
    pub notes: Vec<Value>,
}

impl Api {
    /// Connects to the socket at `path`; a read waits at most `read_timeout`. The socket's
    /// file appears at `bind`, a moment before the service listens on it: a refused connection
    /// is tried again for up to 60 s.
    pub fn connect(path: &Path, read_timeout: Duration) -> Api {
        let deadline = Instant::now() + Duration::from_secs(60);
        let stream = loop {
            match UnixStream::connect(path) {
                Ok(stream) => break stream,
                Err(e) if e.kind() == std::io::ErrorKind::ConnectionRefused && Instant::now() < deadline => {
                    std::thread::sleep(Duration::from_millis(20));
                }
                Err(e) => panic!("connect to the API socket {}: {e}", path.display()),
            }
        };
        stream.set_read_timeout(Some(read_timeout)).expect("timeout");
        Api {
            stream,
            pending: Vec::new(),
            next_id: 1,
            notes: Vec::new(),
        }
    }

    /// Writes `bytes` as they are (a test of malformed messages).
    pub fn send_raw(&mut self, bytes: &[u8]) {
        self.stream.write_all(bytes).expect("write");
    }

    /// The next message (reply or notification).
    pub fn read(&mut self) -> Value {
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

    /// The reply to `id` (notifications on the way are kept).
    pub fn reply(&mut self, id: &Value) -> Value {
        loop {
            let msg = self.read();
            if msg.get("id") == Some(id) {
                return msg;
            }
            self.notes.push(msg);
        }
    }

    /// Calls `method` with `params`; its reply (result or error).
    pub fn call(&mut self, method: &str, params: Value) -> Value {
        let id = json!(self.next_id);
        self.next_id += 1;
        let mut bytes =
            serde_json::to_vec(&json!({"id": id, "method": method, "params": params})).expect("json");
        bytes.push(0x03);
        self.send_raw(&bytes);
        self.reply(&id)
    }

    /// The result of a call that must succeed.
    pub fn ok(&mut self, method: &str, params: Value) -> Value {
        let r = self.call(method, params);
        assert!(r.get("error").is_none(), "{method}: {r}");
        r["result"].clone()
    }

    /// The message of a call that must fail with Klipper's `WebRequestError`.
    pub fn error(&mut self, method: &str, params: Value) -> String {
        let r = self.call(method, params);
        assert_eq!(r["error"]["error"], "WebRequestError", "{method}: {r}");
        r["error"]["message"].as_str().expect("message").to_string()
    }

    /// `info` until the printer's state is `want` (at most 120 s); the last `info`.
    pub fn wait_state(&mut self, want: &str) -> Value {
        let deadline = Instant::now() + Duration::from_secs(120);
        loop {
            let info = self.ok("info", json!({}));
            if info["state"] == want {
                return info;
            }
            assert!(Instant::now() < deadline, "never {want}: {info}");
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// Status object `object` now (`objects/query`).
    pub fn status(&mut self, object: &str) -> Value {
        let q = self.ok("objects/query", json!({"objects": {object: null}}));
        q["status"][object].clone()
    }
}

/// Starts `cadence serve --no-realtime -a SOCKET ARGS…` in the workspace (its stderr to
/// `dir/stderr.txt`) and waits (at most 60 s) for its API socket.
pub fn start_service(dir: &Path, socket: &Path, args: &[&OsStr]) -> Service {
    let child = Command::new(crate::bin("cadence"))
        .args(["serve", "--no-realtime", "-a"])
        .arg(socket)
        .args(args)
        .current_dir(crate::workspace())
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(dir.join("stderr.txt")).expect("stderr file"))
        .spawn()
        .expect("start cadence serve");
    let service = Service(child);
    let deadline = Instant::now() + Duration::from_secs(60);
    while !socket.exists() {
        assert!(Instant::now() < deadline, "no API socket after 60 s");
        std::thread::sleep(Duration::from_millis(20));
    }
    service
}

/// The service process, killed (and reaped) when the test ends, passed or failed.
#[derive(Debug)]
pub struct Service(pub Child);

impl Drop for Service {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}
