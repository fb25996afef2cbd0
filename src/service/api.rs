//! Klipper's API server on a Unix socket: one thread polls the listener and every client
//! (non-blocking), answers requests (the printer's work goes to the [`worker`](super::worker)
//! and its answer comes back through a channel), and sends each subscriber the fields that
//! changed every 250 ms (`notify_status_update`). The socket is created owner-only (0600, or
//! 0660 with a group). Every client has a bounded outgoing buffer: one that falls behind by
//! more than [`MAX_BACKLOG`] bytes is disconnected with the reason logged, so a slow client
//! never holds up the printer or the other clients.

use std::collections::BTreeMap;
use std::io::{ErrorKind, Read, Write};
use std::os::fd::AsFd;
use std::os::unix::fs::PermissionsExt;
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::sync::mpsc::{Receiver, Sender};
use std::time::{Duration, Instant};

use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
use serde_json::{json, Map, Value};

use super::framing::{encode, parse_request, Framer, Request};
use super::objects::{self, Snapshot, SystemFacts};
use super::reply::ReplyError;
use super::worker::{Asker, Job, ToApi};
use super::Shared;

/// Bytes queued for one client before it is disconnected as too slow.
pub const MAX_BACKLOG: usize = 4 << 20;
/// Period of the subscription updates (Klipper's).
const REFRESH: Duration = Duration::from_millis(250);

/// Why the API socket could not be set up.
#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    #[error("API socket {path}: {why}")]
    Socket { path: PathBuf, why: String },
}

/// Creates the socket at `path` (replacing a stale one), owner-only; `group` (a gid) makes it
/// group-readable and -writable too.
pub fn bind(path: &Path, group: Option<u32>) -> Result<UnixListener, ApiError> {
    let err = |why: String| ApiError::Socket {
        path: path.to_path_buf(),
        why,
    };
    match std::fs::symlink_metadata(path) {
        Ok(meta) if std::os::unix::fs::FileTypeExt::is_socket(&meta.file_type()) => {
            std::fs::remove_file(path).map_err(|e| err(format!("cannot remove the old socket: {e}")))?;
        }
        Ok(_) => return Err(err("exists and is not a socket".into())),
        Err(_) => {}
    }
    // Created with no permission for others from the start: no window where it is open.
    let old = nix::sys::stat::umask(nix::sys::stat::Mode::from_bits_truncate(0o177));
    let bound = UnixListener::bind(path);
    nix::sys::stat::umask(old);
    let listener = bound.map_err(|e| err(e.to_string()))?;
    let mode = match group {
        Some(gid) => {
            std::os::unix::fs::chown(path, None, Some(gid))
                .map_err(|e| err(format!("cannot give it to group {gid}: {e}")))?;
            0o660
        }
        None => 0o600,
    };
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(mode)).map_err(|e| err(e.to_string()))?;
    listener.set_nonblocking(true).map_err(|e| err(e.to_string()))?;
    Ok(listener)
}

/// A status subscription: the objects and fields asked for, the reply template and the
/// values last sent.
#[derive(Debug, Default)]
struct Subscription {
    objects: BTreeMap<String, Option<Vec<String>>>,
    template: Map<String, Value>,
    last: Map<String, Value>,
}

#[derive(Debug)]
struct Client {
    id: u64,
    stream: UnixStream,
    framer: Framer,
    out: Vec<u8>,
    subscription: Option<Subscription>,
    output_template: Option<Map<String, Value>>,
    /// Why it is being disconnected.
    closing: Option<String>,
}

impl Client {
    fn send(&mut self, value: &Value) {
        if self.closing.is_some() {
            return;
        }
        let bytes = encode(value);
        if self.out.len() + bytes.len() > MAX_BACKLOG {
            self.closing = Some(format!(
                "too slow: more than {MAX_BACKLOG} bytes waiting to be read"
            ));
            return;
        }
        self.out.extend_from_slice(&bytes);
        self.flush();
    }

    fn flush(&mut self) {
        while !self.out.is_empty() {
            match self.stream.write(&self.out) {
                Ok(0) => {
                    self.closing = Some("closed".into());
                    return;
                }
                Ok(n) => {
                    self.out.drain(..n);
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock => return,
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(e) => {
                    self.closing = Some(format!("write error: {e}"));
                    return;
                }
            }
        }
    }

    fn reply(&mut self, id: &Option<Value>, result: Result<Value, ReplyError>) {
        let Some(id) = id else {
            return;
        };
        let msg = match result {
            Ok(r) => json!({"id": id, "result": r}),
            Err(e) => json!({"id": id, "error": {"error": "WebRequestError", "message": e.to_string()}}),
        };
        self.send(&msg);
    }
}

/// The API server's loop (see the module docs); returns when the service quits.
pub fn serve(
    listener: &UnixListener,
    shared: &Shared,
    jobs: &Sender<Job>,
    from_worker: &Receiver<ToApi>,
    software_version: &str,
    config_file: Option<&Path>,
    log_file: Option<&Path>,
) {
    let mut server = Server {
        clients: Vec::new(),
        next_id: 1,
        shared,
        jobs,
        remote_methods: Vec::new(),
        info: Info {
            software_version: software_version.to_string(),
            config_file: config_file.map(|p| p.display().to_string()),
            log_file: log_file.map(|p| p.display().to_string()),
        },
    };
    let mut next_refresh = Instant::now() + REFRESH;
    let mut buf = vec![0u8; 64 * 1024];
    while !shared.quit.load(Ordering::Acquire) {
        let ready = {
            let mut fds = Vec::with_capacity(server.clients.len() + 1);
            fds.push(PollFd::new(listener.as_fd(), PollFlags::POLLIN));
            for c in &server.clients {
                let mut flags = PollFlags::POLLIN;
                if !c.out.is_empty() {
                    flags |= PollFlags::POLLOUT;
                }
                fds.push(PollFd::new(c.stream.as_fd(), flags));
            }
            match poll(&mut fds, PollTimeout::from(20u8)) {
                Ok(_) => fds
                    .iter()
                    .map(|f| f.revents().unwrap_or(PollFlags::empty()))
                    .collect(),
                Err(_) => Vec::new(),
            }
        };
        if ready.first().is_some_and(|r| !r.is_empty()) {
            server.accept(listener);
        }
        for (k, revents) in ready.iter().enumerate().skip(1) {
            if revents.is_empty() {
                continue;
            }
            // Clients accepted in this round were added after the polled ones.
            if k - 1 < server.clients.len() {
                server.read_client(k - 1, &mut buf);
                server.clients[k - 1].flush();
            }
        }
        while let Ok(msg) = from_worker.try_recv() {
            server.worker_said(msg);
        }
        if Instant::now() >= next_refresh {
            next_refresh = Instant::now() + REFRESH;
            server.refresh();
        }
        server.drop_closing();
    }
}

#[derive(Debug)]
struct Info {
    software_version: String,
    config_file: Option<String>,
    log_file: Option<String>,
}

/// A method a client offers (Klipper calls such methods from G-code macros; kept so
/// `register_remote_method` succeeds as front ends expect, dropped with the client).
#[derive(Debug)]
#[allow(dead_code)]
struct RemoteMethod {
    name: String,
    client: u64,
    template: Map<String, Value>,
}

struct Server<'a> {
    clients: Vec<Client>,
    next_id: u64,
    shared: &'a Shared,
    jobs: &'a Sender<Job>,
    /// Remote methods registered by clients (`register_remote_method`).
    remote_methods: Vec<RemoteMethod>,
    info: Info,
}

impl Server<'_> {
    fn accept(&mut self, listener: &UnixListener) {
        loop {
            match listener.accept() {
                Ok((stream, _)) => {
                    if let Err(e) = stream.set_nonblocking(true) {
                        eprintln!("cadence serve: API client refused: {e}");
                        continue;
                    }
                    let id = self.next_id;
                    self.next_id += 1;
                    self.clients.push(Client {
                        id,
                        stream,
                        framer: Framer::default(),
                        out: Vec::new(),
                        subscription: None,
                        output_template: None,
                        closing: None,
                    });
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock => return,
                Err(e) => {
                    eprintln!("cadence serve: API accept: {e}");
                    return;
                }
            }
        }
    }

    fn read_client(&mut self, idx: usize, buf: &mut [u8]) {
        let mut messages = Vec::new();
        loop {
            let client = &mut self.clients[idx];
            match client.stream.read(buf) {
                Ok(0) => {
                    client.closing = Some("closed".into());
                    break;
                }
                Ok(n) => {
                    if let Err(e) = client.framer.push(&buf[..n], &mut messages) {
                        client.closing = Some(e.to_string());
                        break;
                    }
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock => break,
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(e) => {
                    client.closing = Some(format!("read error: {e}"));
                    break;
                }
            }
        }
        for msg in messages {
            match parse_request(&msg) {
                Ok(req) => self.request(idx, req),
                Err((id, e)) => {
                    eprintln!("cadence serve: API client {}: {e}", self.clients[idx].id);
                    let id = Some(id.unwrap_or(Value::Null));
                    self.clients[idx].reply(&id, Err(e.into()));
                }
            }
        }
    }

    fn snapshot_all(&self) -> Map<String, Value> {
        let p = self.shared.get();
        let (status, latency) = match &p.handle {
            Some(h) => (Some(h.status()), h.latency()),
            None => (None, None),
        };
        objects::all(&Snapshot {
            state: p.state,
            state_message: &p.message,
            status,
            latency,
            config: p.config.as_deref(),
            print: &p.print,
            system: SystemFacts::read(),
        })
    }

    fn request(&mut self, idx: usize, req: Request) {
        let Request { id, method, params } = req;
        let asker = Asker {
            client: self.clients[idx].id,
            id: id.clone(),
            via: None,
        };
        let result: Result<Value, ReplyError> = match method.as_str() {
            "info" => Ok(self.info()),
            "list_endpoints" => Ok(json!({"endpoints": ENDPOINTS})),
            "emergency_stop" => {
                if let Some(h) = self.shared.get().handle {
                    h.emergency_stop();
                }
                Ok(json!({}))
            }
            "register_remote_method" => {
                match (params.get("response_template"), params.get("remote_method")) {
                    (Some(Value::Object(t)), Some(Value::String(m))) => {
                        self.remote_methods.push(RemoteMethod {
                            name: m.clone(),
                            client: asker.client,
                            template: t.clone(),
                        });
                        Ok(json!({}))
                    }
                    (None, _) => Err(ReplyError::MissingArgument("response_template")),
                    (Some(_), None) => Err(ReplyError::MissingArgument("remote_method")),
                    _ => Err(ReplyError::InvalidArgumentType("remote_method")),
                }
            }
            "objects/list" => {
                let published = self.shared.get();
                Ok(json!({"objects": objects::names(&published.mcus, published.config.as_deref())}))
            }
            "objects/query" | "objects/subscribe" => self.query(idx, &params, method == "objects/subscribe"),
            "gcode/help" => Ok(gcode_help()),
            "gcode/script" => match params.get("script") {
                Some(Value::String(text)) => {
                    let _ = self.jobs.send(Job::Script {
                        text: text.clone(),
                        asker,
                    });
                    return;
                }
                None => Err(ReplyError::MissingArgument("script")),
                Some(_) => Err(ReplyError::InvalidArgumentType("script")),
            },
            "pause_resume/pause" | "pause_resume/resume" | "pause_resume/cancel" => {
                let text = match method.as_str() {
                    "pause_resume/pause" => "PAUSE",
                    "pause_resume/resume" => "RESUME",
                    _ => "CANCEL_PRINT",
                };
                let _ = self.jobs.send(Job::Script {
                    text: text.to_string(),
                    asker,
                });
                return;
            }
            "gcode/restart" | "gcode/firmware_restart" => {
                let _ = self.jobs.send(Job::Restart { asker });
                return;
            }
            "gcode/subscribe_output" => match params.get("response_template") {
                None => {
                    self.clients[idx].output_template = Some(Map::new());
                    Ok(json!({}))
                }
                Some(Value::Object(t)) => {
                    self.clients[idx].output_template = Some(t.clone());
                    Ok(json!({}))
                }
                Some(_) => Err(ReplyError::InvalidArgumentType("response_template")),
            },
            other => Err(ReplyError::NoCallback(other.to_string())),
        };
        self.clients[idx].reply(&id, result);
    }

    fn info(&self) -> Value {
        let p = self.shared.get();
        let hostname = std::fs::read_to_string("/proc/sys/kernel/hostname")
            .map(|h| h.trim().to_string())
            .unwrap_or_default();
        // The owner of /proc/self is this process's user and group.
        let (uid, gid) = std::fs::metadata("/proc/self")
            .map(|m| {
                (
                    std::os::unix::fs::MetadataExt::uid(&m),
                    std::os::unix::fs::MetadataExt::gid(&m),
                )
            })
            .unwrap_or((0, 0));
        // Klipper's source and interpreter paths: Cadence's executable and its directory
        // (front ends store them; Moonraker requires both).
        let exe = std::env::current_exe().unwrap_or_default();
        let dir = exe.parent().map(Path::to_path_buf).unwrap_or_default();
        json!({
            "state": p.state.name(),
            "state_message": p.message,
            "hostname": hostname,
            "klipper_path": dir.display().to_string(),
            "python_path": exe.display().to_string(),
            "cpu_info": cpu_info(),
            "software_version": self.info.software_version,
            "config_file": self.info.config_file,
            "log_file": self.info.log_file,
            "process_id": std::process::id(),
            "user_id": uid,
            "group_id": gid,
            "app": "Cadence",
        })
    }

    /// `objects/query` and `objects/subscribe`: the fields asked for now; a subscription
    /// then gets the changed ones every 250 ms.
    fn query(
        &mut self,
        idx: usize,
        params: &Map<String, Value>,
        subscribe: bool,
    ) -> Result<Value, ReplyError> {
        let asked = match params.get("objects") {
            Some(Value::Object(o)) => o,
            None => return Err(ReplyError::MissingArgument("objects")),
            Some(_) => return Err(ReplyError::InvalidArgumentType("objects")),
        };
        let mut wanted = BTreeMap::new();
        for (name, fields) in asked {
            let fields = match fields {
                Value::Null => None,
                Value::Array(list) => Some(
                    list.iter()
                        .map(|f| f.as_str().map(str::to_string))
                        .collect::<Option<Vec<String>>>()
                        .ok_or(ReplyError::InvalidArgument)?,
                ),
                _ => return Err(ReplyError::InvalidArgument),
            };
            wanted.insert(name.clone(), fields);
        }
        let template = match params.get("response_template") {
            None => Map::new(),
            Some(Value::Object(t)) => t.clone(),
            Some(_) => return Err(ReplyError::InvalidArgumentType("response_template")),
        };
        let all = self.snapshot_all();
        let mut status = Map::new();
        for (name, fields) in &wanted {
            status.insert(
                name.clone(),
                Value::Object(objects::select(&all, name, fields.as_deref())),
            );
        }
        if subscribe {
            self.clients[idx].subscription = Some(Subscription {
                objects: wanted,
                template,
                last: status.clone(),
            });
        }
        Ok(json!({"eventtime": eventtime(), "status": status}))
    }

    /// Sends every subscriber the fields that changed since its last update.
    fn refresh(&mut self) {
        if self.clients.iter().all(|c| c.subscription.is_none()) {
            return;
        }
        let all = self.snapshot_all();
        let now = eventtime();
        for client in &mut self.clients {
            let Some(sub) = client.subscription.as_mut() else {
                continue;
            };
            let mut changed = Map::new();
            for (name, fields) in &sub.objects {
                let current = objects::select(&all, name, fields.as_deref());
                let last = sub.last.get(name).and_then(Value::as_object);
                let diff: Map<String, Value> = current
                    .iter()
                    .filter(|(k, v)| last.and_then(|l| l.get(*k)) != Some(*v))
                    .map(|(k, v)| (k.clone(), v.clone()))
                    .collect();
                if !diff.is_empty() {
                    changed.insert(name.clone(), Value::Object(diff));
                    sub.last.insert(name.clone(), Value::Object(current));
                }
            }
            if changed.is_empty() {
                continue;
            }
            let mut msg = sub.template.clone();
            msg.entry("method")
                .or_insert_with(|| Value::from("notify_status_update"));
            msg.insert("params".into(), json!({"eventtime": now, "status": changed}));
            client.send(&Value::Object(msg));
        }
    }

    fn worker_said(&mut self, msg: ToApi) {
        match msg {
            ToApi::Reply { asker, result } => {
                if let Some(c) = self.clients.iter_mut().find(|c| c.id == asker.client) {
                    c.reply(&asker.id, result);
                }
            }
            ToApi::Output(line) => {
                for c in &mut self.clients {
                    let Some(t) = &c.output_template else {
                        continue;
                    };
                    let mut msg = t.clone();
                    msg.entry("method")
                        .or_insert_with(|| Value::from("notify_gcode_response"));
                    msg.insert("params".into(), json!({"response": line}));
                    c.send(&Value::Object(msg));
                }
            }
        }
    }

    fn drop_closing(&mut self) {
        let remote = &mut self.remote_methods;
        self.clients.retain(|c| match &c.closing {
            None => true,
            Some(why) => {
                if why != "closed" {
                    eprintln!("cadence serve: API client {} disconnected: {why}", c.id);
                }
                remote.retain(|m| m.client != c.id);
                false
            }
        });
    }
}

/// The CPU model and count, as Klipper's `cpu_info` (e.g. "2 core Intel(R) Xeon(R) ...").
fn cpu_info() -> String {
    let text = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let model = text
        .lines()
        .find_map(|l| {
            l.strip_prefix("model name")
                .and_then(|r| r.split_once(':'))
                .map(|(_, m)| m.trim())
        })
        .unwrap_or("?");
    let cores = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    format!("{cores} core {model}")
}

/// Seconds of the monotonic clock, as Klipper's `eventtime`.
fn eventtime() -> f64 {
    nix::time::clock_gettime(nix::time::ClockId::CLOCK_MONOTONIC)
        .map(|t| t.tv_sec() as f64 + t.tv_nsec() as f64 * 1e-9)
        .unwrap_or(0.0)
}

/// The endpoints served.
const ENDPOINTS: &[&str] = &[
    "list_endpoints",
    "info",
    "emergency_stop",
    "register_remote_method",
    "objects/list",
    "objects/query",
    "objects/subscribe",
    "gcode/help",
    "gcode/script",
    "gcode/restart",
    "gcode/firmware_restart",
    "gcode/subscribe_output",
    "pause_resume/pause",
    "pause_resume/resume",
    "pause_resume/cancel",
];

/// `gcode/help`: the commands the service runs, with a line each.
fn gcode_help() -> Value {
    json!({
        "G0": "Move (rapid)", "G1": "Move", "G2": "Clockwise arc", "G3": "Counter-clockwise arc",
        "G4": "Dwell", "G28": "Home the axes", "G90": "Absolute coordinates",
        "G91": "Relative coordinates", "G92": "Set the position", "M82": "Absolute extrusion",
        "M83": "Relative extrusion", "M112": "Emergency stop", "M114": "Report the position",
    "RESTART": "Reload the config and restart the printer",
        "FIRMWARE_RESTART": "Restart the MCUs and the printer",
        "SET_GCODE_VARIABLE": "Set a macro variable",
        "SDCARD_PRINT_FILE": "Load a file from the virtual sdcard and print it",
        "SDCARD_RESET_FILE": "Clear the loaded file", "M23": "Select a file",
        "M24": "Start or resume the print", "M25": "Pause the print",
        "M26": "Set the file position", "M27": "Report the print's byte position",
        "PAUSE": "Pause the print", "RESUME": "Resume the paused print",
        "CANCEL_PRINT": "Cancel the print", "M73": "Set the progress shown",
        "M117": "Set the message shown",
        "M104": "Set the extruder temperature", "M109": "Set the extruder temperature and wait",
        "M140": "Set the bed temperature", "M190": "Set the bed temperature and wait",
        "M105": "Report the temperatures", "M106": "Set the fan speed", "M107": "Turn the fan off",
        "SET_HEATER_TEMPERATURE": "Set a heater's target",
        "TEMPERATURE_WAIT": "Wait for a temperature", "TURN_OFF_HEATERS": "Turn every heater off",
        "PID_CALIBRATE": "Run PID calibration test",
        "SAVE_CONFIG": "Overwrite config file and restart",
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_client_that_does_not_read_is_cut_off_at_the_backlog_limit() {
        let (ours, _theirs) = UnixStream::pair().expect("socket pair");
        ours.set_nonblocking(true).expect("non-blocking");
        let mut client = Client {
            id: 1,
            stream: ours,
            framer: Framer::default(),
            out: Vec::new(),
            subscription: None,
            output_template: None,
            closing: None,
        };
        let update = json!({"method": "notify_status_update", "params": {"pad": "x".repeat(64 * 1024)}});
        let mut sent = 0usize;
        while client.closing.is_none() {
            client.send(&update);
            sent += 1;
            assert!(sent < 1000, "never cut off");
        }
        assert!(
            client.closing.as_deref().is_some_and(|w| w.contains("too slow")),
            "{:?}",
            client.closing
        );
        assert!(client.out.len() <= MAX_BACKLOG);
    }

    #[test]
    fn the_socket_is_owner_only_and_a_stale_one_is_replaced() {
        let dir = std::env::temp_dir().join(format!("cadence-api-bind-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let path = dir.join("s.sock");
        let first = bind(&path, None).expect("bind");
        drop(first);
        let _second = bind(&path, None).expect("a stale socket is replaced");
        let mode = std::fs::metadata(&path).expect("socket").permissions().mode();
        assert_eq!(mode & 0o777, 0o600);
        let file = dir.join("plain");
        std::fs::write(&file, "x").expect("file");
        assert!(
            bind(&file, None).is_err(),
            "a file that is not a socket is left alone"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
