//! Instruction counts of a whole process (every thread) under valgrind's callgrind: the figure
//! that repeats on a noisy machine where wall time does not (`cadence bench plan
//! --instructions`). The process runs under `valgrind --tool=callgrind` with its output file in
//! a scratch directory; the count is the `summary:` (else `totals:`) line of each output file
//! (one per process), summed.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use crate::error::BenchError;

/// The valgrind executable on `PATH`.
pub fn find() -> Option<PathBuf> {
    crate::find_on_path("valgrind")
}

/// Runs `exe args` under callgrind and returns the instructions it executed (all threads).
pub fn count(valgrind: &Path, exe: &Path, args: &[String]) -> Result<u64, BenchError> {
    let dir = std::env::temp_dir().join(format!("cadence-callgrind-{}", std::process::id()));
    std::fs::create_dir_all(&dir).map_err(|e| BenchError::file(&dir, e))?;
    let result = run_in(&dir, valgrind, exe, args);
    let _ = std::fs::remove_dir_all(&dir);
    result
}

fn run_in(dir: &Path, valgrind: &Path, exe: &Path, args: &[String]) -> Result<u64, BenchError> {
    let tool = |reason: String| BenchError::Tool {
        tool: "valgrind",
        reason,
    };
    let out = Command::new(valgrind)
        .arg("--tool=callgrind")
        .arg(format!("--callgrind-out-file={}/callgrind.out.%p", dir.display()))
        .arg(exe)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .output()
        .map_err(|e| tool(format!("cannot run {}: {e}", valgrind.display())))?;
    let stderr = String::from_utf8_lossy(&out.stderr);
    if !out.status.success() {
        let tail: Vec<&str> = stderr.lines().rev().take(5).collect();
        return Err(tool(format!(
            "{} exited with {} under callgrind: {}",
            exe.display(),
            out.status,
            tail.into_iter().rev().collect::<Vec<_>>().join(" | ")
        )));
    }
    let mut total = 0u64;
    let mut files = 0;
    for entry in std::fs::read_dir(dir).map_err(|e| BenchError::file(dir, e))? {
        let path = entry.map_err(|e| BenchError::file(dir, e))?.path();
        let text = std::fs::read_to_string(&path).map_err(|e| BenchError::file(&path, e))?;
        total += instructions_of(&text)
            .ok_or_else(|| tool(format!("{}: no summary: or totals: line", path.display())))?;
        files += 1;
    }
    if files == 0 {
        return Err(tool("callgrind wrote no output file".into()));
    }
    Ok(total)
}

/// The first event count (Ir) of a callgrind output's `summary:` line, else its `totals:` line.
pub fn instructions_of(text: &str) -> Option<u64> {
    let field = |key: &str| {
        text.lines()
            .find_map(|l| l.strip_prefix(key))
            .and_then(|rest| rest.split_whitespace().next())
            .and_then(|n| n.parse::<u64>().ok())
    };
    field("summary:").or_else(|| field("totals:"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_summary_line_gives_the_count() {
        let out = "# callgrind format\nversion: 1\ncmd: cadence bench plan x.gcode\nevents: Ir\n\
                   summary: 3140000123\nfn=(1) main\n5 7\ntotals: 3140000123\n";
        assert_eq!(instructions_of(out), Some(3_140_000_123));
        assert_eq!(instructions_of("events: Ir\ntotals: 42 7\n"), Some(42));
        assert_eq!(instructions_of("events: Ir\nsummary: lots\n"), None);
        assert_eq!(instructions_of(""), None);
    }
}
