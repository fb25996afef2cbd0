//! A scratch folder for a benchmark's simulated MCU step traces, removed when dropped.

use std::path::PathBuf;

/// The folder `cadence-bench-<leaf>` under the temp dir.
pub(super) struct TraceDir(pub(super) PathBuf);

impl TraceDir {
    /// Creates `<temp>/cadence-bench-<leaf>` (the caller makes `leaf` unique: its pid…).
    pub(super) fn new(leaf: &str) -> std::io::Result<TraceDir> {
        let dir = std::env::temp_dir().join(format!("cadence-bench-{leaf}"));
        std::fs::create_dir_all(&dir)?;
        Ok(TraceDir(dir))
    }

    /// The main MCU's trace; the others' are named from it ([`cadence::mcus::trace_path`]).
    pub(super) fn base(&self) -> PathBuf {
        self.0.join("mcu.trace")
    }
}

impl Drop for TraceDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}
