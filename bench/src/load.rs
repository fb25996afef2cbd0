//! `--load cpu|io|mem`: a bounded stressor beside a measurement. Debian's `stress-ng` when it
//! is on `PATH` (`--cpu N`, `--hdd 1`, `--vm 1`, with a `--timeout` a little past the run as a
//! backstop), else built-in threads under normal scheduling: a spinner per CPU, a writer that
//! rewrites and fsyncs a 64 MiB temp file, or a copier streaming between two 64 MiB buffers.
//! [`Load::stop`] ends it (SIGTERM to the stress-ng process we started, or the threads' flag).

use std::io::Write;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use crate::error::BenchError;
use crate::report::LoadInfo;

/// What to stress.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LoadKind {
    Cpu,
    Io,
    Mem,
}

impl LoadKind {
    pub fn name(self) -> &'static str {
        match self {
            LoadKind::Cpu => "cpu",
            LoadKind::Io => "io",
            LoadKind::Mem => "mem",
        }
    }
}

impl std::str::FromStr for LoadKind {
    type Err = String;
    fn from_str(s: &str) -> Result<LoadKind, String> {
        match s {
            "cpu" => Ok(LoadKind::Cpu),
            "io" => Ok(LoadKind::Io),
            "mem" => Ok(LoadKind::Mem),
            _ => Err(format!("load {s:?}: expected cpu, io or mem")),
        }
    }
}

/// Which stressor to use.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LoadTool {
    /// stress-ng when installed, else built-in.
    Auto,
    StressNg,
    Builtin,
}

impl std::str::FromStr for LoadTool {
    type Err = String;
    fn from_str(s: &str) -> Result<LoadTool, String> {
        match s {
            "auto" => Ok(LoadTool::Auto),
            "stress-ng" => Ok(LoadTool::StressNg),
            "builtin" => Ok(LoadTool::Builtin),
            _ => Err(format!("load tool {s:?}: expected auto, stress-ng or builtin")),
        }
    }
}

const CHUNK: usize = 1 << 20;
const BUFFER: usize = 64 << 20;

/// A running stressor.
#[derive(Debug)]
pub struct Load {
    kind: LoadKind,
    child: Option<Child>,
    stop: Arc<AtomicBool>,
    threads: Vec<JoinHandle<()>>,
}

impl Load {
    /// Starts `kind` for at most about `bound` (stress-ng's own timeout; threads run until
    /// [`Load::stop`]).
    pub fn start(kind: LoadKind, tool: LoadTool, bound: Duration) -> Result<Load, BenchError> {
        let stress_ng = crate::find_on_path("stress-ng");
        let mut load = Load {
            kind,
            child: None,
            stop: Arc::new(AtomicBool::new(false)),
            threads: Vec::new(),
        };
        match (tool, stress_ng) {
            (LoadTool::StressNg, None) => {
                return Err(BenchError::Tool {
                    tool: "stress-ng",
                    reason: "not installed (Debian package stress-ng); --load-tool builtin runs without it"
                        .into(),
                })
            }
            (LoadTool::Auto | LoadTool::StressNg, Some(exe)) => {
                let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
                let timeout = format!("{}s", bound.as_secs() + 5);
                let mut cmd = Command::new(&exe);
                match kind {
                    LoadKind::Cpu => cmd.args(["--cpu", &cpus.to_string()]),
                    LoadKind::Io => cmd
                        .args(["--hdd", "1", "--hdd-bytes", "64m", "--temp-path"])
                        .arg(std::env::temp_dir()),
                    LoadKind::Mem => cmd.args(["--vm", "1", "--vm-bytes", "256m"]),
                };
                let child = cmd
                    .args(["--timeout", &timeout, "--quiet"])
                    .stdin(Stdio::null())
                    .stdout(Stdio::null())
                    .stderr(Stdio::null())
                    .spawn()
                    .map_err(|e| BenchError::Tool {
                        tool: "stress-ng",
                        reason: format!("{}: {e}", exe.display()),
                    })?;
                load.child = Some(child);
            }
            (LoadTool::Builtin | LoadTool::Auto, _) => load.spawn_builtin()?,
        }
        Ok(load)
    }

    fn spawn_builtin(&mut self) -> Result<(), BenchError> {
        let n = match self.kind {
            LoadKind::Cpu => std::thread::available_parallelism().map_or(1, |n| n.get()),
            LoadKind::Io | LoadKind::Mem => 1,
        };
        for i in 0..n {
            let (stop, kind) = (self.stop.clone(), self.kind);
            let t = std::thread::Builder::new()
                .name(format!("bench-load{i}"))
                .spawn(move || match kind {
                    LoadKind::Cpu => spin(&stop),
                    LoadKind::Io => write_files(&stop),
                    LoadKind::Mem => copy_memory(&stop),
                })
                .map_err(|e| BenchError::Thread(format!("load thread: {e}")))?;
            self.threads.push(t);
        }
        Ok(())
    }

    /// What ran, for the report.
    pub fn info(&self) -> LoadInfo {
        LoadInfo {
            kind: self.kind.name().into(),
            tool: if self.child.is_some() {
                "stress-ng"
            } else {
                "builtin"
            }
            .into(),
        }
    }

    /// Stops the stressor and waits for it.
    pub fn stop(mut self) -> LoadInfo {
        let info = self.info();
        self.halt();
        info
    }

    fn halt(&mut self) {
        // Relaxed: the threads only poll the flag; join() below orders the rest.
        self.stop.store(true, Ordering::Relaxed);
        if let Some(mut child) = self.child.take() {
            if let Ok(pid) = i32::try_from(child.id()) {
                let _ = nix::sys::signal::kill(
                    nix::unistd::Pid::from_raw(pid),
                    nix::sys::signal::Signal::SIGTERM,
                );
            }
            let _ = child.wait();
        }
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

impl Drop for Load {
    fn drop(&mut self) {
        self.halt();
    }
}

fn spin(stop: &AtomicBool) {
    let mut x = 0u64;
    while !stop.load(Ordering::Relaxed) {
        for _ in 0..10_000 {
            x = std::hint::black_box(x.wrapping_mul(6364136223846793005).wrapping_add(1));
        }
    }
}

fn write_files(stop: &AtomicBool) {
    let path = std::env::temp_dir().join(format!("cadence-bench-load-{}", std::process::id()));
    let chunk = vec![0x5au8; CHUNK];
    while !stop.load(Ordering::Relaxed) {
        let Ok(mut f) = std::fs::File::create(&path) else {
            return;
        };
        for _ in 0..BUFFER / CHUNK {
            if stop.load(Ordering::Relaxed) || f.write_all(&chunk).and_then(|_| f.sync_data()).is_err() {
                break;
            }
        }
    }
    let _ = std::fs::remove_file(&path);
}

fn copy_memory(stop: &AtomicBool) {
    let src = vec![1u8; BUFFER];
    let mut dst = vec![0u8; BUFFER];
    while !stop.load(Ordering::Relaxed) {
        for (d, s) in dst.chunks_mut(CHUNK).zip(src.chunks(CHUNK)) {
            d.copy_from_slice(s);
            std::hint::black_box(&d);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kinds_parse() {
        assert_eq!("cpu".parse(), Ok(LoadKind::Cpu));
        assert_eq!("mem".parse::<LoadKind>().map(LoadKind::name), Ok("mem"));
        assert!("disk".parse::<LoadKind>().unwrap_err().contains("cpu, io or mem"));
        assert_eq!("builtin".parse(), Ok(LoadTool::Builtin));
        assert!("x".parse::<LoadTool>().is_err());
    }

    #[test]
    fn builtin_loads_start_and_stop() {
        for kind in [LoadKind::Cpu, LoadKind::Io, LoadKind::Mem] {
            let load = Load::start(kind, LoadTool::Builtin, Duration::from_secs(1)).unwrap();
            std::thread::sleep(Duration::from_millis(20));
            let info = load.stop();
            assert_eq!((info.kind.as_str(), info.tool.as_str()), (kind.name(), "builtin"));
        }
    }

    #[test]
    fn stress_ng_when_installed() {
        if crate::find_on_path("stress-ng").is_none() {
            println!("skipped: stress-ng is not installed");
            assert!(Load::start(LoadKind::Cpu, LoadTool::StressNg, Duration::from_secs(1)).is_err());
            return;
        }
        let load = Load::start(LoadKind::Cpu, LoadTool::StressNg, Duration::from_secs(1)).unwrap();
        std::thread::sleep(Duration::from_millis(50));
        assert_eq!(load.stop().tool, "stress-ng");
    }
}
