//! The process-wide real-time report: which guarantees the OS refused. Each kind of guarantee
//! is reported once (the first refusal), both to stderr and to [`rt_report`], so a print log
//! says up front what is off without repeating it for every thread.

use std::sync::Mutex;

/// A kind of real-time guarantee.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Guarantee {
    /// Thread pinned to a core.
    Affinity,
    /// SCHED_FIFO priority.
    Fifo,
    /// `mlockall`.
    LockMemory,
    /// Stack prefaulting.
    Stack,
    /// `/dev/cpu_dma_latency` held at 0.
    DmaLatency,
    /// Idle CPUs kept polling ([`super::IdlePoll`]).
    IdlePoll,
}

static REPORT: Mutex<Vec<(Guarantee, String)>> = Mutex::new(Vec::new());

/// Records a refusal of `what` (first one per kind only) and prints it once to stderr.
pub(crate) fn refused(what: Guarantee, thread: &str, error: &dyn std::fmt::Display, consequence: &str) {
    let mut report = REPORT.lock().unwrap_or_else(|p| p.into_inner());
    if report.iter().any(|(g, _)| *g == what) {
        return;
    }
    let line = format!("realtime: {error} (thread '{thread}'): {consequence}");
    eprintln!("cadence: {line}");
    report.push((what, line));
}

/// Records a refused guarantee from outside the runtime (e.g. a failed
/// [`super::hold_cpu_dma_latency_zero`]); reported once per kind like the others.
pub fn report_refusal(what: Guarantee, error: &dyn std::fmt::Display, consequence: &str) {
    refused(what, "process", error, consequence);
}

/// `result`'s value, or `None` after reporting its error as a refusal of `what` (once per
/// kind, like [`report_refusal`]): for a guarantee the caller goes on without.
pub fn ok_or_report<T, E: std::fmt::Display>(
    result: Result<T, E>,
    what: Guarantee,
    consequence: &str,
) -> Option<T> {
    result.map_err(|e| report_refusal(what, &e, consequence)).ok()
}

/// The refusals so far, one line each, in the order they happened. Empty = every requested
/// guarantee holds.
pub fn rt_report() -> Vec<String> {
    let report = REPORT.lock().unwrap_or_else(|p| p.into_inner());
    report.iter().map(|(_, l)| l.clone()).collect()
}

/// Forgets all refusals (tests only: the report is process-wide).
#[doc(hidden)]
pub fn clear_rt_report_for_tests() {
    REPORT.lock().unwrap_or_else(|p| p.into_inner()).clear();
}
