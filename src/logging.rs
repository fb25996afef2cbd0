//! The print's logger thread ([`Logging`]): the only thread that formats or writes log text while
//! the real-time threads run; they push fixed-size records into rt-core's bounded queue.

use std::path::PathBuf;
use std::thread::JoinHandle;

use rt_core::logger::{Level, Logger, LoggerConfig, LoggerError, LoggerHandle};

/// The print's logger thread: the only thread that formats or writes log text during a print.
#[derive(Debug)]
pub struct Logging {
    pub handle: LoggerHandle,
    join: Option<JoinHandle<u64>>,
}

impl Logging {
    /// Starts the logger thread (stderr, plus `file` if given).
    pub fn start(level: Level, file: Option<PathBuf>) -> Result<Logging, LoggerError> {
        Logging::start_with(level, file, true)
    }

    /// Starts the logger thread writing to `file` if given, and to stderr if `stderr`.
    pub fn start_with(level: Level, file: Option<PathBuf>, stderr: bool) -> Result<Logging, LoggerError> {
        let (handle, join) = Logger::start(LoggerConfig {
            level,
            file,
            stderr,
            ..LoggerConfig::default()
        })?;
        Ok(Logging {
            handle,
            join: Some(join),
        })
    }

    /// A handle for thread `tag`.
    pub fn handle(&self, tag: &'static str) -> LoggerHandle {
        self.handle.with_tag(tag)
    }

    /// Drains and stops the logger thread; returns the report line (records written, dropped).
    pub fn finish(mut self) -> String {
        let written = self.stop();
        format!(
            "log: {written} records written, {} dropped (queue full)",
            self.handle.dropped()
        )
    }

    fn stop(&mut self) -> u64 {
        self.handle.shutdown();
        self.join.take().and_then(|j| j.join().ok()).unwrap_or(0)
    }
}

impl Drop for Logging {
    fn drop(&mut self) {
        if self.join.is_some() {
            self.stop();
        }
    }
}
