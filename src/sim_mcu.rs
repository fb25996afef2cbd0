//! Starts the simulated MCU (`cadence-mcu`, the firmware's Linux-process target) as a child
//! process and learns the path of the pseudo-terminal it opened.
//!
//! The executable is `cadence-mcu` beside the running binary (or one directory up, for test
//! harnesses in `deps/`); when it was not built (e.g. after `cargo run` of the `cadence` package
//! alone), the running `cadence` binary serves the same firmware code through its hidden
//! `mcu` subcommand.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

/// How long the child may take to print its pty path.
const START_TIMEOUT: Duration = Duration::from_secs(10);

/// A running simulated MCU.
#[derive(Debug)]
pub struct SimMcu {
    pub pty: PathBuf,
    child: Child,
}

/// Options passed to the simulated MCU.
#[derive(Debug, Clone)]
pub struct SimOptions {
    pub clock_freq: u64,
    pub time_scale: f64,
    pub trace: Option<PathBuf>,
    /// Further arguments (the simulated world: axes, endstops; `--clock-freq` here replaces
    /// `clock_freq`).
    pub extra: Vec<String>,
}

/// Why a simulated MCU did not start; each names the MCU but the first two.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// The running executable cannot be found.
    #[error("cannot locate the running executable: {0}")]
    Executable(#[source] std::io::Error),
    /// Neither `cadence-mcu` nor `cadence mcu` is at hand.
    #[error(
        "cannot find the simulated MCU executable 'cadence-mcu' next to {}: build it with `cargo build --workspace`",
        .exe.display()
    )]
    NotFound { exe: PathBuf },
    /// The process did not start.
    #[error("mcu '{mcu}': cannot start the simulated MCU: {source}")]
    Spawn {
        mcu: String,
        #[source]
        source: std::io::Error,
    },
    /// The process has no stdout to read its pty from.
    #[error("mcu '{mcu}': simulated MCU has no stdout")]
    NoStdout { mcu: String },
    /// The thread that reads its stdout did not start.
    #[error("mcu '{mcu}': cannot start a reader thread: {source}")]
    Reader {
        mcu: String,
        #[source]
        source: std::io::Error,
    },
    /// Its first output line could not be read.
    #[error("mcu '{mcu}': reading the simulated MCU's output failed: {source}")]
    Read {
        mcu: String,
        #[source]
        source: std::io::Error,
    },
    /// It did not announce its pty in time.
    #[error("mcu '{mcu}': the simulated MCU did not announce its pty within {secs} s")]
    Timeout { mcu: String, secs: u64 },
    /// It exited before opening its pty.
    #[error("mcu '{mcu}': the simulated MCU exited ({status}) before opening its pty")]
    Exited {
        mcu: String,
        status: std::process::ExitStatus,
    },
    /// Its first line is not the pty announcement.
    #[error("mcu '{mcu}': unexpected output from the simulated MCU: {line:?}")]
    Unexpected { mcu: String, line: String },
}

fn mcu_command() -> Result<Command, SimError> {
    let exe = std::env::current_exe().map_err(SimError::Executable)?;
    let dirs: Vec<&Path> = exe
        .parent()
        .into_iter()
        .flat_map(|d| [Some(d), d.parent()])
        .flatten()
        .collect();
    for dir in dirs {
        let candidate = dir.join("cadence-mcu");
        if candidate.is_file() {
            return Ok(Command::new(candidate));
        }
    }
    let is_cadence = exe
        .file_name()
        .and_then(|n| n.to_str())
        .map(|n| n == "cadence")
        .unwrap_or(false);
    if is_cadence {
        let mut cmd = Command::new(exe);
        cmd.arg("mcu");
        return Ok(cmd);
    }
    Err(SimError::NotFound { exe })
}

impl SimMcu {
    /// Spawns the simulated MCU and waits (bounded) for it to announce its pty.
    pub fn spawn(name: &str, opts: &SimOptions) -> Result<SimMcu, SimError> {
        let mcu = || name.to_string();
        let mut cmd = mcu_command()?;
        // Extra arguments may give this MCU a clock of its own (e.g. a 16 MHz toolhead board
        // next to a 50 MHz main board, through `CADENCE_SIM_ARGS_<NAME>`).
        if !opts.extra.iter().any(|a| a == "--clock-freq") {
            cmd.arg("--clock-freq").arg(opts.clock_freq.to_string());
        }
        cmd.arg("--time-scale").arg(opts.time_scale.to_string());
        if let Some(trace) = &opts.trace {
            cmd.arg("--trace").arg(trace);
        }
        cmd.args(&opts.extra);
        // Its own process group: a Ctrl-C on the terminal goes to the host, which stops the
        // print cleanly; the simulator ends when the host does (it watches its parent).
        std::os::unix::process::CommandExt::process_group(&mut cmd, 0);
        cmd.stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit());
        let mut child = cmd
            .spawn()
            .map_err(|source| SimError::Spawn { mcu: mcu(), source })?;
        let Some(stdout) = child.stdout.take() else {
            let _ = child.kill();
            return Err(SimError::NoStdout { mcu: mcu() });
        };
        let (tx, rx) = mpsc::channel();
        std::thread::Builder::new()
            .name(format!("sim-{name}-stdout"))
            .spawn(move || {
                let mut reader = BufReader::new(stdout);
                let mut line = String::new();
                let first = reader.read_line(&mut line).map(|_| line.clone());
                let _ = tx.send(first);
                // Keep draining so the child never blocks on a full pipe.
                let mut sink = String::new();
                while matches!(reader.read_line(&mut sink), Ok(n) if n > 0) {
                    sink.clear();
                }
            })
            .map_err(|source| SimError::Reader { mcu: mcu(), source })?;
        let line = match rx.recv_timeout(START_TIMEOUT) {
            Ok(Ok(line)) => line,
            Ok(Err(source)) => {
                let _ = child.kill();
                let _ = child.wait();
                return Err(SimError::Read { mcu: mcu(), source });
            }
            Err(_) => {
                let _ = child.kill();
                let _ = child.wait();
                return Err(SimError::Timeout {
                    mcu: mcu(),
                    secs: START_TIMEOUT.as_secs(),
                });
            }
        };
        let Some(path) = line.trim().strip_prefix("cadence-mcu: pty ") else {
            let status = child.try_wait().ok().flatten();
            let _ = child.kill();
            let _ = child.wait();
            return Err(match status {
                Some(status) => SimError::Exited { mcu: mcu(), status },
                None => SimError::Unexpected {
                    mcu: mcu(),
                    line: line.trim().to_string(),
                },
            });
        };
        Ok(SimMcu {
            pty: PathBuf::from(path),
            child,
        })
    }

    /// Waits (bounded) for the MCU process to exit after the host closed its pty; kills it
    /// if it does not. Returns a description of how it ended.
    pub fn finish(mut self, timeout: Duration) -> String {
        let deadline = std::time::Instant::now() + timeout;
        loop {
            match self.child.try_wait() {
                Ok(Some(status)) => return format!("exited ({status})"),
                Ok(None) if std::time::Instant::now() < deadline => {
                    std::thread::sleep(Duration::from_millis(10))
                }
                _ => {
                    let _ = self.child.kill();
                    let _ = self.child.wait();
                    return "killed after not exiting in time".to_string();
                }
            }
        }
    }
}

impl Drop for SimMcu {
    fn drop(&mut self) {
        if matches!(self.child.try_wait(), Ok(None)) {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}
