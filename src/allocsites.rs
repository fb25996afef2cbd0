//! Where do the real-time threads still allocate? A diagnostic behind an environment variable:
//! with `CADENCE_ALLOC_SITES=PATH`, a live print's planner thread captures a backtrace at each
//! of its allocations after warm-up (rt-core's `AllocSites`) and, at the end, writes them
//! grouped by call stack, most frequent first, to `PATH.<thread>.txt`. Capturing slows the
//! thread down: use a low `--time-scale`.
//!
//! The variable is read once at start-up ([`init`]) so that checking it later allocates
//! nothing.

use std::io::Write;
use std::path::PathBuf;
use std::sync::OnceLock;

use rt_core::alloc_count::AllocSites;

/// The environment variable naming the report's base path.
pub const ENV: &str = "CADENCE_ALLOC_SITES";

static REQUESTED: OnceLock<Option<PathBuf>> = OnceLock::new();

/// Reads [`ENV`] (call once, early in `main`).
pub fn init() {
    let _ = REQUESTED.set(std::env::var_os(ENV).map(PathBuf::from));
}

fn requested() -> Option<&'static PathBuf> {
    REQUESTED.get().and_then(Option::as_ref)
}

/// Starts capturing on the calling thread if [`ENV`] was set (allocation-free otherwise).
pub fn start_if_requested() {
    if requested().is_some() {
        AllocSites::start();
    }
}

/// Stops capturing and writes the report `PATH.<thread>.txt` if [`ENV`] was set; failures to
/// write are reported on stderr (a diagnostic must not fail the print).
pub fn finish_if_requested(thread: &str) {
    let Some(base) = requested() else { return };
    let sites = AllocSites::take();
    let groups = AllocSites::report(&sites, 24);
    let path = PathBuf::from(format!("{}.{thread}.txt", base.display()));
    let write = || -> std::io::Result<()> {
        let mut f = std::io::BufWriter::new(std::fs::File::create(&path)?);
        writeln!(f, "{} allocations after warm-up on thread {thread}", sites.len())?;
        for (count, bytes, stack) in &groups {
            writeln!(f, "\n== {count} allocations, {bytes} bytes\n{stack}")?;
        }
        f.flush()
    };
    if let Err(e) = write() {
        eprintln!("cadence: {}: {e}", path.display());
    }
}
