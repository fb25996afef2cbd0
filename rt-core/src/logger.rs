//! The logger: the only thread that formats or writes log text.
//!
//! Other threads call [`LoggerHandle::log`], which copies a fixed-size [`Record`] (level,
//! `&'static str` message, up to [`MAX_ARGS`] numeric arguments, timestamp) into a bounded
//! [`HandoffQueue`] (never waits on the logger thread, even when it was preempted half-way
//! through a read: crossbeam's `ArrayQueue` would spin there, forever under SCHED_FIFO on a
//! shared core): no allocation, no syscall, never blocks. When the queue is
//! full the record is dropped and counted; the logger thread reports the drop count with the
//! next record it writes ("N records dropped"). The logger thread sleeps for `poll` between
//! drains (a bounded park, no busy loop) and is unparked early by a handle when the queue passes
//! half full.
//!
//! Output line: `<seconds since start> <LEVEL> <thread tag> <message with its args>`. The
//! arguments go where the message says (see [`Record::format_into`]):
//! - `{}` placeholders take the arguments in order: `"late by {} ms"` → `late by 3.2 ms`;
//! - otherwise a message that ends in a list of names, one per argument (after the last `": "`,
//!   separated by `", "`), gets each value beside its name, before a unit word at the end or
//!   after one at the start: `"planner started: start time s, lines"` with `[6.5, 12]` →
//!   `planner started: start time 6.5 s, lines 12`; `"behind: ms before due"` with `[-3]` →
//!   `behind: -3 ms before due`;
//! - anything else gets its arguments appended.
//!
//! Floats are written with at most 6 decimals (trailing zeros trimmed).

use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicU8, Ordering};
use std::sync::Arc;
use std::thread::{JoinHandle, Thread};
use std::time::{Duration, Instant};

use crate::handoff::HandoffQueue;

/// Numeric arguments a record carries.
pub const MAX_ARGS: usize = 4;

/// Log levels, most severe first.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[repr(u8)]
pub enum Level {
    Error = 0,
    Warn = 1,
    Info = 2,
    Debug = 3,
    Trace = 4,
}

impl Level {
    /// Upper-case name as written in the log.
    pub fn name(self) -> &'static str {
        match self {
            Level::Error => "ERROR",
            Level::Warn => "WARN",
            Level::Info => "INFO",
            Level::Debug => "DEBUG",
            Level::Trace => "TRACE",
        }
    }
}

/// `error`, `warn`, `info`, `debug` or `trace` (any case).
impl std::str::FromStr for Level {
    type Err = String;
    fn from_str(s: &str) -> Result<Level, String> {
        match s.to_ascii_lowercase().as_str() {
            "error" => Ok(Level::Error),
            "warn" | "warning" => Ok(Level::Warn),
            "info" => Ok(Level::Info),
            "debug" => Ok(Level::Debug),
            "trace" => Ok(Level::Trace),
            _ => Err(format!(
                "unknown log level '{s}' (error, warn, info, debug, trace)"
            )),
        }
    }
}

/// One numeric log argument.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Arg {
    I(i64),
    U(u64),
    F(f64),
}

impl From<i64> for Arg {
    fn from(v: i64) -> Arg {
        Arg::I(v)
    }
}
impl From<u64> for Arg {
    fn from(v: u64) -> Arg {
        Arg::U(v)
    }
}
impl From<u32> for Arg {
    fn from(v: u32) -> Arg {
        Arg::U(v as u64)
    }
}
impl From<i32> for Arg {
    fn from(v: i32) -> Arg {
        Arg::I(v as i64)
    }
}
impl From<usize> for Arg {
    fn from(v: usize) -> Arg {
        Arg::U(v as u64)
    }
}
impl From<f64> for Arg {
    fn from(v: f64) -> Arg {
        Arg::F(v)
    }
}

/// A fixed-size log record (`Copy`, no heap).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Record {
    pub level: Level,
    /// Who logged (a static tag such as "planner", "io:mcu").
    pub tag: &'static str,
    pub msg: &'static str,
    pub nargs: u8,
    pub args: [Arg; MAX_ARGS],
    /// Nanoseconds since the logger started.
    pub t_ns: u64,
}

/// Words that read as a unit when a field name ends (or starts) with them.
const UNITS: &[&str] = &[
    "s", "ms", "us", "µs", "ns", "ticks", "mm", "mm/s", "mm/s^2", "Hz", "%", "bytes",
];

/// Writes one argument; floats with at most 6 decimals, trailing zeros trimmed.
fn write_arg(out: &mut String, a: Arg) {
    use std::fmt::Write as _;
    let _ = match a {
        Arg::I(v) => write!(out, "{v}"),
        Arg::U(v) => write!(out, "{v}"),
        Arg::F(v) if v.is_finite() && v.abs() < 1e15 => {
            let start = out.len();
            let _ = write!(out, "{v:.6}");
            if out[start..].contains('.') {
                let trimmed = out.trim_end_matches('0').trim_end_matches('.').len();
                out.truncate(trimmed);
            }
            if &out[start..] == "-0" {
                out.truncate(start);
                out.push('0');
            }
            Ok(())
        }
        Arg::F(v) => write!(out, "{v}"),
    };
}

impl Record {
    /// Appends the formatted line (with '\n') to `out`, the arguments placed as the module
    /// docs describe. Allocates only if `out` must grow.
    pub fn format_into(&self, out: &mut String) {
        use std::fmt::Write as _;
        let _ = write!(
            out,
            "{:>12.6} {:<5} {} ",
            self.t_ns as f64 * 1e-9,
            self.level.name(),
            self.tag,
        );
        let args = &self.args[..(self.nargs as usize).min(MAX_ARGS)];
        let msg = self.msg;
        if msg.contains("{}") {
            let mut rest = args.iter();
            let mut parts = msg.split("{}");
            if let Some(first) = parts.next() {
                out.push_str(first);
            }
            for part in parts {
                match rest.next() {
                    Some(a) => write_arg(out, *a),
                    None => out.push_str("{}"),
                }
                out.push_str(part);
            }
            for a in rest {
                out.push(' ');
                write_arg(out, *a);
            }
        } else {
            let (head, list) = match msg.rfind(": ") {
                Some(i) => msg.split_at(i + 2),
                None => ("", msg),
            };
            if !args.is_empty() && list.split(", ").count() == args.len() {
                out.push_str(head);
                for (i, (field, a)) in list.split(", ").zip(args).enumerate() {
                    if i > 0 {
                        out.push_str(", ");
                    }
                    match field.rsplit_once(' ') {
                        Some((name, unit)) if UNITS.contains(&unit) => {
                            out.push_str(name);
                            out.push(' ');
                            write_arg(out, *a);
                            out.push(' ');
                            out.push_str(unit);
                        }
                        _ if field.split(' ').next().is_some_and(|w| UNITS.contains(&w)) => {
                            write_arg(out, *a);
                            out.push(' ');
                            out.push_str(field);
                        }
                        _ => {
                            out.push_str(field);
                            out.push(' ');
                            write_arg(out, *a);
                        }
                    }
                }
            } else {
                out.push_str(msg);
                for a in args {
                    out.push(' ');
                    write_arg(out, *a);
                }
            }
        }
        out.push('\n');
    }
}

/// Logger configuration.
#[derive(Debug, Clone)]
pub struct LoggerConfig {
    /// Records kept in the queue (fixed at start).
    pub capacity: usize,
    /// Most verbose level that is recorded.
    pub level: Level,
    /// Write to stderr.
    pub stderr: bool,
    /// Also append to this file.
    pub file: Option<PathBuf>,
    /// Longest sleep between drains.
    pub poll: Duration,
}

impl Default for LoggerConfig {
    fn default() -> Self {
        LoggerConfig {
            capacity: 4096,
            level: Level::Info,
            stderr: true,
            file: None,
            poll: Duration::from_millis(5),
        }
    }
}

/// Errors starting the logger.
#[derive(Debug, thiserror::Error)]
pub enum LoggerError {
    /// The log file could not be opened.
    #[error("log file {path}: {source}")]
    File { path: PathBuf, source: io::Error },
    /// The logger thread could not be spawned.
    #[error("spawning the logger thread: {0}")]
    Spawn(io::Error),
}

#[derive(Debug)]
struct Shared {
    queue: HandoffQueue<Record>,
    level: AtomicU8,
    dropped: AtomicU64,
    written: AtomicU64,
    stop: AtomicBool,
    start: Instant,
    logger: Thread,
}

/// Cheap, clonable sender side. All methods are allocation-free and never block.
#[derive(Debug, Clone)]
pub struct LoggerHandle {
    shared: Arc<Shared>,
    tag: &'static str,
}

impl LoggerHandle {
    /// The same logger with another thread tag.
    pub fn with_tag(&self, tag: &'static str) -> LoggerHandle {
        LoggerHandle {
            shared: self.shared.clone(),
            tag,
        }
    }

    /// True when `level` would be recorded.
    #[inline]
    pub fn enabled(&self, level: Level) -> bool {
        // Relaxed: the level is a filter hint; a stale read only logs or skips one record.
        (level as u8) <= self.shared.level.load(Ordering::Relaxed)
    }

    /// Changes the level filter.
    pub fn set_level(&self, level: Level) {
        self.shared.level.store(level as u8, Ordering::Relaxed);
    }

    /// Queues a record; returns false (and counts a drop) if the queue is full.
    #[inline]
    pub fn log<const N: usize>(&self, level: Level, msg: &'static str, args: [Arg; N]) -> bool {
        if !self.enabled(level) {
            return true;
        }
        let mut rec = Record {
            level,
            tag: self.tag,
            msg,
            nargs: N.min(MAX_ARGS) as u8,
            args: [Arg::U(0); MAX_ARGS],
            t_ns: u64::try_from(self.shared.start.elapsed().as_nanos()).unwrap_or(u64::MAX),
        };
        for (dst, src) in rec.args.iter_mut().zip(args) {
            *dst = src;
        }
        let ok = self.shared.queue.push(rec).is_ok();
        if !ok {
            // Relaxed: a statistics counter; read by the logger thread with Relaxed too.
            self.shared.dropped.fetch_add(1, Ordering::Relaxed);
        }
        if self.shared.queue.len() * 2 >= self.shared.queue.capacity() {
            self.shared.logger.unpark();
        }
        ok
    }

    /// Records dropped because the queue was full.
    pub fn dropped(&self) -> u64 {
        self.shared.dropped.load(Ordering::Relaxed)
    }

    /// Records written so far.
    pub fn written(&self) -> u64 {
        self.shared.written.load(Ordering::Relaxed)
    }

    /// Asks the logger thread to drain and exit; join its handle afterwards.
    pub fn shutdown(&self) {
        // Release pairs with the Acquire load in the logger loop: records pushed before this
        // store are seen by the final drain.
        self.shared.stop.store(true, Ordering::Release);
        self.shared.logger.unpark();
    }
}

/// The logger thread's entry point.
#[derive(Debug)]
pub struct Logger;

impl Logger {
    /// Starts the logger thread (named "logger"); it exits after [`LoggerHandle::shutdown`]
    /// once the queue is drained, returning the number of records written.
    pub fn start(cfg: LoggerConfig) -> Result<(LoggerHandle, JoinHandle<u64>), LoggerError> {
        let file = match &cfg.file {
            Some(path) => Some(BufWriter::new(
                std::fs::OpenOptions::new()
                    .create(true)
                    .append(true)
                    .open(path)
                    .map_err(|source| LoggerError::File {
                        path: path.clone(),
                        source,
                    })?,
            )),
            None => None,
        };
        let (tx, rx) = std::sync::mpsc::sync_channel::<Arc<Shared>>(1);
        let capacity = cfg.capacity.max(1);
        let poll = cfg.poll;
        let stderr = cfg.stderr;
        let level = cfg.level;
        let join = std::thread::Builder::new()
            .name("logger".into())
            .spawn(move || match rx.recv() {
                Ok(shared) => run(&shared, stderr, file, poll),
                Err(_) => 0,
            })
            .map_err(LoggerError::Spawn)?;
        let shared = Arc::new(Shared {
            queue: HandoffQueue::new(capacity),
            level: AtomicU8::new(level as u8),
            dropped: AtomicU64::new(0),
            written: AtomicU64::new(0),
            stop: AtomicBool::new(false),
            start: Instant::now(),
            logger: join.thread().clone(),
        });
        // The logger thread waits for exactly this message; it cannot be gone yet.
        let _ = tx.send(shared.clone());
        Ok((LoggerHandle { shared, tag: "main" }, join))
    }
}

fn run(shared: &Shared, stderr: bool, mut file: Option<BufWriter<File>>, poll: Duration) -> u64 {
    let mut line = String::with_capacity(256);
    let mut reported_drops = 0u64;
    loop {
        // Acquire pairs with the Release store in `shutdown`.
        let stopping = shared.stop.load(Ordering::Acquire);
        let mut err = io::stderr().lock();
        while let Some(rec) = shared.queue.pop() {
            line.clear();
            let dropped = shared.dropped.load(Ordering::Relaxed);
            if dropped > reported_drops {
                use std::fmt::Write as _;
                let _ = writeln!(
                    line,
                    "logger: {} records dropped (queue full)",
                    dropped - reported_drops
                );
                reported_drops = dropped;
            }
            rec.format_into(&mut line);
            if stderr {
                let _ = err.write_all(line.as_bytes());
            }
            if let Some(f) = file.as_mut() {
                let _ = f.write_all(line.as_bytes());
            }
            shared.written.fetch_add(1, Ordering::Relaxed);
        }
        drop(err);
        if let Some(f) = file.as_mut() {
            let _ = f.flush();
        }
        if stopping {
            break;
        }
        std::thread::park_timeout(poll);
    }
    shared.written.load(Ordering::Relaxed)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_reach_the_file_in_order() {
        let dir = std::env::temp_dir().join(format!("cadence-logger-{}", std::process::id()));
        let _ = std::fs::create_dir_all(&dir);
        let path = dir.join("log.txt");
        let _ = std::fs::remove_file(&path);
        let (log, join) = Logger::start(LoggerConfig {
            stderr: false,
            file: Some(path.clone()),
            level: Level::Info,
            ..LoggerConfig::default()
        })
        .unwrap();
        let planner = log.with_tag("planner");
        assert!(planner.log(Level::Info, "moves", [Arg::U(3), Arg::F(1.5)]));
        assert!(planner.log(Level::Debug, "filtered", []));
        assert!(log.log(Level::Error, "late by ns", [Arg::I(-7)]));
        log.shutdown();
        assert_eq!(join.join().unwrap(), 2);
        let text = std::fs::read_to_string(&path).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 2, "{text}");
        assert!(lines[0].ends_with("INFO  planner moves 3 1.5"), "{}", lines[0]);
        assert!(lines[1].ends_with("ERROR main late by -7 ns"), "{}", lines[1]);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn full_queue_drops_and_counts() {
        let (log, join) = Logger::start(LoggerConfig {
            capacity: 4,
            stderr: false,
            poll: Duration::from_secs(3600),
            ..LoggerConfig::default()
        })
        .unwrap();
        // The logger drains concurrently (it is unparked at half full), so whether a push is
        // dropped depends on scheduling: check the accounting identity, not a drop count.
        let mut ok = 0u64;
        for i in 0..10_000u64 {
            if log.log(Level::Warn, "x", [Arg::U(i)]) {
                ok += 1;
            }
        }
        log.shutdown();
        let written = join.join().unwrap();
        assert_eq!(written, ok);
        assert_eq!(ok + log.dropped(), 10_000);
    }

    fn line(msg: &'static str, args: &[Arg]) -> String {
        let mut rec = Record {
            level: Level::Info,
            tag: "t",
            msg,
            nargs: args.len() as u8,
            args: [Arg::U(0); MAX_ARGS],
            t_ns: 0,
        };
        rec.args[..args.len()].copy_from_slice(args);
        let mut out = String::new();
        rec.format_into(&mut out);
        out.trim_start()
            .trim_start_matches("0.000000 INFO  t ")
            .trim_end()
            .to_string()
    }

    #[test]
    fn args_read_naturally() {
        use Arg::*;
        assert_eq!(
            line(
                "planner started: start print time s, high water s",
                &[F(6.728827975430295), F(10.0)]
            ),
            "planner started: start print time 6.728828 s, high water 10 s"
        );
        assert_eq!(
            line(
                "planner fell behind: stepper index, ms before due",
                &[U(2), F(-3.25)]
            ),
            "planner fell behind: stepper index 2, -3.25 ms before due"
        );
        assert_eq!(
            line("homing axes x, y, z", &[U(1), U(0), U(1)]),
            "homing axes x 1, y 0, z 1"
        );
        assert_eq!(
            line("a: b, c: batches, end clock", &[U(5), U(123)]),
            "a: b, c: batches 5, end clock 123"
        );
        assert_eq!(
            line("late by {} ms, {} left", &[F(0.5), I(-2), U(9)]),
            "late by 0.5 ms, -2 left 9"
        );
        assert_eq!(line("missing {} and {}", &[U(1)]), "missing 1 and {}");
        assert_eq!(line("moves", &[U(3), F(1.5)]), "moves 3 1.5");
        assert_eq!(line("io stage subscribed", &[]), "io stage subscribed");
        assert_eq!(
            line("x", &[F(-0.0000001), F(f64::NAN), F(1e20)]),
            "x 0 NaN 100000000000000000000"
        );
    }

    #[test]
    fn levels_parse() {
        assert_eq!("WARN".parse::<Level>(), Ok(Level::Warn));
        assert_eq!("trace".parse::<Level>(), Ok(Level::Trace));
        assert!("loud".parse::<Level>().is_err());
    }

    #[test]
    fn missing_directory_is_an_error() {
        let e = Logger::start(LoggerConfig {
            file: Some("/nonexistent-dir/x/log".into()),
            ..LoggerConfig::default()
        })
        .unwrap_err();
        assert!(e.to_string().contains("/nonexistent-dir/x/log"));
    }
}
