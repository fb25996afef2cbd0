//! `cadence-mcu`: the firmware core as a Linux process on a pseudo-terminal (the simulator).
//!
//! Start-up: block SIGTERM/SIGINT/SIGHUP and receive them through a signalfd; open the pty;
//! build the dictionary; open the trace; then print `cadence-mcu: pty <slave>` and run the
//! event loop ([`event_loop`]) until the host hangs up, a signal arrives or the parent dies.
//! On exit the trace is flushed and the step lateness percentiles go to stderr.
//!
//! Real time is off by default. `--cpu N`, `--fifo PRIO` and `--lock-memory` ask rt-core's OS
//! layer ([`rt_core::os::apply_rt`]) to pin the loop thread, run it under SCHED_FIFO and
//! `mlockall` + prefault its stack, once everything is allocated and before the pty line is
//! printed; each refusal is reported once on stderr and the simulator runs on without it.
//! `--spin-us` bounds the loop's busy-waiting ([`spin`]).
//!
//! The core ([`SimMcu`]) is large (a 65534-move pool inline), so it lives on the heap and the
//! loop runs on a thread with a generous stack (a debug build may copy the value through the
//! stack while boxing it).

pub mod adc_ref;
pub mod bltouch;
pub mod board;
pub mod cli;
pub mod clock;
pub mod event_loop;
pub mod fan;
pub mod faults;
pub mod heater;
pub mod mcu_temp;
pub mod pty;
pub mod sensor_curve;
pub mod smart_effector;
pub mod spi_sensor;
pub mod spin;
pub mod surface;
pub mod tmc;
pub mod trace_file;
pub mod world;

use crate::core::{Mcu, McuConfig};
use crate::trace::TraceWriter;
use board::SimBoard;
use clap::Parser;
use cli::Cli;
use clock::SimClock;
use event_loop::{EventLoop, Exit};
use faults::TxFaults;
use nix::sys::signal::{SigSet, Signal};
use nix::sys::signalfd::{SfdFlags, SignalFd};
use rt_core::WireClock;
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// Oid slots of the simulated MCU (every `allocate_oids count=%c` fits).
pub const SIM_OIDS: usize = 255;
/// Move pool capacity of the simulated MCU (the largest the pool supports).
pub const SIM_MOVES: usize = 65534;
/// The simulated MCU.
pub type SimMcu = Mcu<SimBoard, SIM_OIDS, SIM_MOVES>;

const LOOP_STACK: usize = 32 << 20;

/// Why the simulator could not run.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// A system call on the pty, signalfd or poll failed.
    #[error("{what}: {source}")]
    Sys {
        /// The operation.
        what: &'static str,
        /// The errno.
        source: nix::Error,
    },
    /// The trace file could not be created or written.
    #[error("trace file {path}: {source}")]
    Trace {
        /// The trace path.
        path: PathBuf,
        /// The I/O error.
        source: io::Error,
    },
    /// The `--pty-link` symlink could not be made.
    #[error("pty link {path}: {source}")]
    Link {
        /// The link path.
        path: PathBuf,
        /// The I/O error.
        source: io::Error,
    },
    /// Writing the pty line to stdout failed.
    #[error("stdout: {0}")]
    Stdout(io::Error),
    /// `--heater-fault` names a pin no `--heater` drives.
    #[error("--heater-fault: pin {0} is not the heater pin of any --heater")]
    UnknownHeater(u8),
    /// The lateness histogram could not be created.
    #[error("histogram: {0}")]
    Histogram(#[from] hdrhistogram::CreationError),
    /// The shared world could not be joined.
    #[error(transparent)]
    World(#[from] world::WorldError),
    /// The event loop thread could not be started or panicked.
    #[error("event loop thread: {0}")]
    Thread(String),
}

fn sys(what: &'static str) -> impl FnOnce(nix::Error) -> SimError {
    move |source| SimError::Sys { what, source }
}

/// Runs `cadence-mcu` with `args` (the first item is the program name, as in `std::env::args`).
/// Returns the process exit code.
pub fn main_with_args(args: impl IntoIterator<Item = String>) -> i32 {
    let cli = match Cli::try_parse_from(args) {
        Ok(cli) => cli,
        Err(e) => {
            let _ = e.print();
            return e.exit_code();
        }
    };
    match run(cli) {
        Ok(()) => 0,
        Err(e) => {
            eprintln!("cadence-mcu: error: {e}");
            1
        }
    }
}

/// Runs the simulator to completion.
pub fn run(cli: Cli) -> Result<(), SimError> {
    // Block the exit signals in this thread before spawning, so every thread inherits the
    // mask and the signals are only ever seen through the signalfd.
    let mut mask = SigSet::empty();
    for s in [Signal::SIGTERM, Signal::SIGINT, Signal::SIGHUP] {
        mask.add(s);
    }
    mask.thread_block().map_err(sys("block signals"))?;
    let sigfd = SignalFd::with_flags(&mask, SfdFlags::SFD_NONBLOCK | SfdFlags::SFD_CLOEXEC)
        .map_err(sys("signalfd"))?;
    std::thread::Builder::new()
        .name("cadence-mcu".into())
        .stack_size(LOOP_STACK)
        .spawn(move || run_on_this_thread(cli, sigfd))
        .map_err(|e| SimError::Thread(e.to_string()))?
        .join()
        .map_err(|_| SimError::Thread("panicked".into()))?
}

fn run_on_this_thread(cli: Cli, sigfd: SignalFd) -> Result<(), SimError> {
    // Wake-ups as precise as the kernel allows (the default slack is 50 µs); best effort.
    let _ = nix::sys::prctl::set_timerslack(1);
    let parent = nix::unistd::getppid();
    if let Some(f) = cli
        .heater_faults
        .iter()
        .find(|f| !cli.heaters.iter().any(|h| h.heater_pin == f.heater_pin))
    {
        return Err(SimError::UnknownHeater(f.heater_pin));
    }
    let pty = pty::Pty::open().map_err(sys("open pty"))?;
    let link = cli
        .pty_link
        .as_deref()
        .map(|p| make_link(pty.slave_path(), p))
        .transpose()?;
    let trace = match &cli.trace {
        Some(path) => Some(
            trace_file::TraceFile::create(path)
                .and_then(|file| {
                    TraceWriter::new(
                        file,
                        cli.trace_format.into(),
                        cli.clock_freq as u64,
                        cli.time_scale,
                    )
                })
                .map_err(|source| SimError::Trace {
                    path: path.clone(),
                    source,
                })?,
        ),
        None => None,
    };
    let mut world = world::World::new(cli.world.as_deref(), cli.axes.clone(), cli.endstops.clone())?;
    world.set_surfaces(cli.surfaces.clone());
    world.set_gantries(cli.gantries.clone());
    let board = SimBoard::new(cli.clock_freq, trace)?
        .with_world(world)
        .with_heaters(&cli.heaters, &cli.heater_faults)
        .with_adc_refs(&cli.adc_refs)
        .with_fans(&cli.fans)
        .with_sensor_curves(&cli.sensor_curves)
        .with_bltouch(&cli.bltouch)
        .with_smart_effectors(&cli.smart_effectors)
        .with_tmc(&cli.tmc)
        .with_spi_sensors(&cli.spi_sensors)
        .with_remote_heaters(&cli.heater_exports, &cli.remote_sensors);
    let dictionary: &'static [u8] = Box::leak(crate::dictionary_bytes(cli.clock_freq).into_boxed_slice());
    let config = McuConfig {
        clock_freq: cli.clock_freq,
        move_count: cli.move_count,
        late_limit: u32::try_from(cli.late_limit_us as u64 * cli.clock_freq as u64 / 1_000_000)
            .unwrap_or(u32::MAX),
    };
    let clock = SimClock::start(cli.clock_freq, cli.time_scale);
    if let Some(path) = &cli.trace {
        write_epoch(path, &clock)?;
    }
    let mut mcu = Box::new(SimMcu::new(
        board,
        dictionary,
        config,
        WireClock(clock.now() as u32),
    ));
    // Steps and endstop samples in CLOCK_MONOTONIC time, shared by every process of the world.
    if let Some(start_ns) = clock.monotonic_start_ns() {
        mcu.board_mut().world.set_time_base(world::TimeBase {
            start_ns: start_ns as f64,
            ticks_per_ns: clock.ticks_per_ns(),
        });
    }

    if cli.wants_rt() {
        // After every allocation and mapping above (mlockall's MCL_FUTURE could otherwise make
        // later mappings fail), before the host can connect. Each refusal is printed once on
        // stderr by the runtime and the loop runs on without that guarantee.
        let got = rt_core::os::apply_rt(&cli.rt_spec());
        if got != rt_core::os::RtApplied::default() {
            eprintln!(
                "cadence-mcu: real time: pinned={} fifo={} memory_locked={} stack_prefaulted={}",
                got.pinned, got.fifo, got.memory_locked, got.stack_prefaulted
            );
        }
    }

    let mut stdout = io::stdout().lock();
    writeln!(stdout, "cadence-mcu: pty {}", pty.slave_path().display())
        .and_then(|()| stdout.flush())
        .map_err(SimError::Stdout)?;
    drop(stdout);

    let faults = TxFaults::new(
        cli.drop_tx,
        Duration::from_millis(cli.tx_delay_ms),
        cli.fault_seed,
    );
    let mut event_loop = EventLoop::new(&pty, &sigfd, clock, parent)
        .with_faults(faults)
        .with_spin(Duration::from_micros(cli.spin_us))
        .with_keep_open(cli.keep_open);
    if let (Some(after), Some(length)) = (cli.freeze_after_ms, cli.freeze_ms) {
        event_loop = event_loop.with_freeze(Duration::from_millis(after), Duration::from_millis(length));
    }
    let exit = event_loop.run(&mut mcu);
    if event_loop.dropped_tx() > 0 {
        eprintln!("cadence-mcu: --drop-tx dropped {} bytes", event_loop.dropped_tx());
    }

    let board = mcu.board_mut();
    let trace_result = board.finish_trace();
    report(board, &exit);
    if let Some(link) = link {
        remove_link(&link, pty.slave_path());
    }
    exit?;
    trace_result.map_err(|source| SimError::Trace {
        path: cli.trace.unwrap_or_default(),
        source,
    })
}

fn report(board: &mut SimBoard, exit: &Result<Exit, SimError>) {
    let why = match exit {
        Ok(Exit::HostClosed) => "host closed the pty".to_owned(),
        Ok(Exit::Signal(s)) => format!("signal {s}"),
        Ok(Exit::ParentDied) => "parent process exited".to_owned(),
        Err(e) => format!("error: {e}"),
    };
    let l = board.lateness_summary();
    eprintln!(
        "cadence-mcu: exit ({why}); queue_steps={} steps={}; step lateness µs (MCU time): \
         p50={} p99={} p99.9={} max={}",
        board.queue_steps(),
        l.steps,
        l.p50,
        l.p99,
        l.p999,
        l.max
    );
    // At exit the control lines stay as they are: every message sent is complete.
    for e in board.smart_effectors(u64::MAX) {
        eprintln!("cadence-mcu: {}", e.report());
    }
    if board.dropped_output > 0 {
        eprintln!(
            "cadence-mcu: dropped {} output bytes (host not reading)",
            board.dropped_output
        );
    }
}

/// The file next to trace `path` that says when the MCU clock was 0:
/// `<path>.epoch`, one line `monotonic_ns <CLOCK_MONOTONIC ns at tick 0>`. With it, trace clocks
/// of several simulated MCUs convert to one time base exactly (`cadence home --trace`).
pub fn epoch_path(path: &Path) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(".epoch");
    PathBuf::from(name)
}

/// Reads an epoch file written by the simulator: CLOCK_MONOTONIC seconds at tick 0.
pub fn read_epoch(trace: &Path) -> Option<f64> {
    let text = std::fs::read_to_string(epoch_path(trace)).ok()?;
    let ns: u64 = text.trim().strip_prefix("monotonic_ns ")?.parse().ok()?;
    Some(ns as f64 * 1e-9)
}

fn write_epoch(trace: &Path, clock: &SimClock) -> Result<(), SimError> {
    let path = epoch_path(trace);
    let err = |source| SimError::Trace {
        path: path.clone(),
        source,
    };
    match clock.monotonic_start_ns() {
        Some(ns) => std::fs::write(&path, format!("monotonic_ns {ns}\n")).map_err(err),
        // No clock reading: leave no stale file behind.
        None => match std::fs::remove_file(&path) {
            Err(e) if e.kind() != io::ErrorKind::NotFound => Err(err(e)),
            _ => Ok(()),
        },
    }
}

/// Points `link` at the pty slave, replacing an existing symlink or file.
fn make_link(slave: &Path, link: &Path) -> Result<PathBuf, SimError> {
    let err = |source| SimError::Link {
        path: link.to_path_buf(),
        source,
    };
    if let Ok(meta) = std::fs::symlink_metadata(link) {
        if meta.is_dir() {
            return Err(err(io::Error::new(
                io::ErrorKind::AlreadyExists,
                "is a directory",
            )));
        }
        std::fs::remove_file(link).map_err(err)?;
    }
    std::os::unix::fs::symlink(slave, link).map_err(err)?;
    Ok(link.to_path_buf())
}

/// Removes `link` if it still points at our pty.
fn remove_link(link: &Path, slave: &Path) {
    if std::fs::read_link(link).is_ok_and(|t| t == slave) {
        let _ = std::fs::remove_file(link);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn link_replaces_and_is_removed() {
        let dir = std::env::temp_dir().join(format!("cadence-link-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let link = dir.join("ttyCadence");
        std::fs::write(&link, b"stale").unwrap();
        let made = make_link(Path::new("/dev/pts/999"), &link).unwrap();
        assert_eq!(std::fs::read_link(&made).unwrap(), Path::new("/dev/pts/999"));
        remove_link(&made, Path::new("/dev/pts/1"));
        assert!(std::fs::symlink_metadata(&made).is_ok(), "not ours: kept");
        remove_link(&made, Path::new("/dev/pts/999"));
        assert!(std::fs::symlink_metadata(&made).is_err());
        assert!(make_link(Path::new("/dev/pts/999"), &dir).is_err());
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn bad_arguments_exit_with_usage_code() {
        let code = main_with_args(["cadence-mcu".to_owned(), "--bogus".to_owned()]);
        assert_eq!(code, 2);
    }
}
