//! The one error type of the `cadence bench` family: each variant says which part of a run
//! failed (an option, a thread, a tool such as cyclictest, an output file).

use std::path::PathBuf;

/// Why a benchmark could not run or write its results.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// The options do not make a run (e.g. `--compare-cyclictest` with busy-wait).
    #[error("{0}")]
    Options(String),
    /// A measurement thread could not be started or died.
    #[error("measurement thread: {0}")]
    Thread(String),
    /// A histogram could not be built, merged or serialized.
    #[error("histogram: {0}")]
    Histogram(String),
    /// Reading or writing a file.
    #[error("{}: {source}", path.display())]
    File {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// An external tool (cyclictest, stress-ng) failed or gave output we cannot read.
    #[error("{tool}: {reason}")]
    Tool { tool: &'static str, reason: String },
    /// Drawing a plot.
    #[error("plot {}: {reason}", path.display())]
    Plot { path: PathBuf, reason: String },
}

impl BenchError {
    /// A file error naming the path.
    pub fn file(path: impl Into<PathBuf>, source: std::io::Error) -> BenchError {
        BenchError::File {
            path: path.into(),
            source,
        }
    }
}
