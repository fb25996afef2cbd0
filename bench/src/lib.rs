//! Cadence's benchmarks as a library, run by the `cadence bench` family of commands:
//!
//! - [`wakeup`]: cyclictest-class wake-up latency (pinned threads, SCHED_FIFO, absolute
//!   deadlines, busy-wait mode), and [`cyclictest`]: the same settings run by cyclictest itself.
//! - [`handoff`]: hand-off latency of the project's queues and iceoryx2 channels.
//! - [`plan`]: planner + step compression throughput, and [`callgrind`]: instruction counts of
//!   a whole process under valgrind; [`stream`]: the step commands of a wire stream, to
//!   compare with (`bench plan --compare`).
//!
//! Shared by all: [`stats`] (ns histograms and their percentiles), [`report`] (the one `--json`
//! schema), [`hlog`] (HdrHistogram interval logs), [`plot`] (SVG/PNG charts), [`load`]
//! (stressors), [`host`] (the host facts header) and [`run`] (options and outputs common to
//! every mode).

pub mod callgrind;
pub mod cyclictest;
pub mod error;
pub mod handoff;
pub mod hlog;
pub mod host;
pub mod load;
pub mod modes;
pub mod plan;
pub mod plot;
pub mod report;
pub mod run;
pub mod stats;
pub mod stream;
pub mod wakeup;

pub use error::BenchError;
/// The histogram type of every series, for modes run outside this crate (`cadence bench
/// pipeline|homing`).
pub use hdrhistogram;

/// An executable named `name` in one of the `PATH` directories.
pub fn find_on_path(name: &str) -> Option<std::path::PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|d| d.join(name))
        .find(|p| p.is_file())
}
