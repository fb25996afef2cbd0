//! Why a `cadence bench` run failed: an argument combination clap cannot refuse, the bench
//! harness, the printer or homing cycles under test, or the files and threads around them.

use std::path::PathBuf;

/// Why a `cadence bench` run failed.
#[derive(Debug, thiserror::Error)]
pub enum BenchCmdError {
    /// The bench harness (histograms, reports, plots).
    #[error(transparent)]
    Bench(#[from] bench::BenchError),
    /// The bench harness's own message (its hand-off child, its planner options).
    #[error("{0}")]
    Harness(String),
    /// `--cores` is not two CPUs.
    #[error("--cores takes two CPUs, producer,consumer (got {0:?})")]
    Cores(Vec<usize>),
    /// The running executable cannot be found (to start a child).
    #[error("cannot find the cadence executable: {0}")]
    Executable(#[source] std::io::Error),
    /// `handoff-child` with a mode that is neither `poll` nor `event`.
    #[error("handoff-child mode {0:?}: expected poll or event")]
    ChildMode(String),
    /// printer.cfg could not be read or describes no printer Cadence can drive.
    #[error(transparent)]
    Config(#[from] cadence::hardware::HardwareError),
    /// The dictionary could not be loaded.
    #[error(transparent)]
    Dictionary(#[from] cadence::wire_check::DictionaryError),
    /// A mode builder got another subcommand (a bug).
    #[error("not a {0} command")]
    NotMode(&'static str),
    /// `--max-error-us` out of range.
    #[error("--max-error-us {0}: must be in (0, 1000]")]
    MaxError(f64),
    /// `--axes` with a letter that is not an axis.
    #[error("--axes {text}: '{letter}' is not x, y or z")]
    Axis { text: String, letter: char },
    /// `--axes` empty.
    #[error("--axes: give at least one of x, y, z")]
    NoAxes,
    /// `--away` not a positive distance.
    #[error("--away {0}: must be more than 0 mm")]
    Away(f64),
    /// `--cpus` names a CPU twice.
    #[error("--cpus: CPU {0} is given twice (one thread per CPU)")]
    CpuTwice(usize),
    /// `--cpus` names a CPU the machine does not have.
    #[error("--cpus: CPU {cpu} does not exist (this machine has CPUs 0..={last})")]
    NoSuchCpu { cpu: usize, last: usize },
    /// `--cycles 0`.
    #[error("--cycles must be at least 1")]
    NoCycles,
    /// The temporary trace directory (`mode`: the bench mode).
    #[error("bench {mode}: {source}")]
    TraceDir {
        mode: &'static str,
        #[source]
        source: std::io::Error,
    },
    /// The simulated MCUs' traces could not be read.
    #[error("bench pipeline: reading the MCU traces: {0}")]
    McuTraces(#[source] McuTraceError),
    /// A file the bench writes.
    #[error("{}: {source}", .path.display())]
    File {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The homing cycles failed.
    #[error(transparent)]
    Homing(Box<cadence::home_cycles::HomeCyclesError>),
    /// The homing thread did not start.
    #[error("cannot start the homing thread: {0}")]
    HomingThread(#[source] std::io::Error),
    /// The homing thread panicked.
    #[error("the homing thread panicked")]
    HomingPanicked,
    /// The benched print failed.
    #[error(transparent)]
    Print(Box<PrintFailure>),
}

impl From<cadence::home_cycles::HomeCyclesError> for BenchCmdError {
    fn from(e: cadence::home_cycles::HomeCyclesError) -> Self {
        Self::Homing(Box::new(e))
    }
}

impl From<PrintFailure> for BenchCmdError {
    fn from(e: PrintFailure) -> Self {
        Self::Print(Box::new(e))
    }
}

/// The CLI's view (the message as shown).
impl From<BenchCmdError> for String {
    fn from(e: BenchCmdError) -> String {
        e.to_string()
    }
}

/// Why the simulated MCUs' traces could not be read.
#[derive(Debug, thiserror::Error)]
pub enum McuTraceError {
    /// A trace or the directory.
    #[error("{}: {source}", .path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A histogram.
    #[error(transparent)]
    Hist(#[from] bench::BenchError),
}

/// Why the benched print failed: opening, running or closing the printer.
#[derive(Debug, thiserror::Error)]
pub enum PrintFailure {
    /// The printer did not open.
    #[error(transparent)]
    Open(#[from] cadence::printer::OpenError),
    /// Feeding the G-code or waiting for the moves failed.
    #[error(transparent)]
    Run(#[from] cadence::PrinterError),
    /// Closing found an error (the session's, or a check at the end).
    #[error(transparent)]
    Close(#[from] cadence::printer::CloseError),
}

/// A bench option's value that does not parse (clap shows it after the option's name).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ArgError {
    /// `--duration` that is not a number with a unit.
    #[error("duration {0:?}: expected e.g. 10, 10s, 500ms, 2m or 1h")]
    Duration(String),
    /// `--duration` of 0, below or more than a week.
    #[error("duration {0:?}: must be more than 0 and at most a week")]
    DurationRange(String),
    /// `--budget-us` below 0 or not a number.
    #[error("budget {0:?}: expected microseconds, 0 or more")]
    Budget(String),
    /// `--time-scale` outside (0, 50].
    #[error("time scale {0:?}: expected a number more than 0 and at most 50")]
    TimeScale(String),
    /// `--clock-freq` outside 1 MHz..1 GHz.
    #[error("clock frequency {0:?}: expected Hz between 1000000 and 1000000000")]
    ClockFreq(String),
}
