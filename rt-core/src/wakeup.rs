//! The machine's own timing noise, measured like cyclictest: a thread sleeps a fixed period
//! over and over and records how late each wake-up comes.
//!
//! Every latency Cadence measures (step lead, homing trigger → stop) is a chain of such
//! wake-ups, so on a noisy host (a VM whose vCPUs pause for milliseconds) their tails move with
//! the machine's. A [`WakeupProbe`] running beside a measurement gives its noise floor in the
//! same run: a tail is then judged as a ratio to the probe's, not against a fixed number.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crate::hist::LatencyHist;

/// Sleeps `period` and records the wake-up's lateness in `hist`, again until `done()` (asked
/// after each sample) says stop: at least one sample.
pub fn sleep_loop(period: Duration, hist: &mut LatencyHist, mut done: impl FnMut() -> bool) {
    loop {
        let t = Instant::now();
        std::thread::sleep(period);
        hist.record_duration(t.elapsed().saturating_sub(period));
        if done() {
            break;
        }
    }
}

/// A background sleeper thread measuring wake-up latency until [`WakeupProbe::finish`].
#[derive(Debug)]
pub struct WakeupProbe {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<(LatencyHist, bool)>>,
    period: Duration,
}

/// What a probe measured.
#[derive(Debug)]
pub struct WakeupReport {
    /// Lateness of every wake-up.
    pub hist: LatencyHist,
    /// The sleeper ran under SCHED_FIFO (false: it was refused, or not asked for).
    pub fifo: bool,
    /// The sleep period.
    pub period: Duration,
}

impl WakeupProbe {
    /// Starts the sleeper (SCHED_FIFO at `fifo_priority` when given and allowed). The thread
    /// inherits the caller's CPU affinity: start it before pinning the caller to let it run on
    /// any core.
    pub fn start(period: Duration, fifo_priority: Option<i32>) -> std::io::Result<WakeupProbe> {
        let stop = Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        let thread = std::thread::Builder::new()
            .name("wakeup-probe".to_string())
            .spawn(move || {
                let fifo = fifo_priority.is_some_and(|p| crate::os::set_current_thread_fifo(p).is_ok());
                let mut hist = LatencyHist::new();
                sleep_loop(period, &mut hist, || flag.load(Ordering::Relaxed));
                (hist, fifo)
            })?;
        Ok(WakeupProbe {
            stop,
            thread: Some(thread),
            period,
        })
    }

    /// Stops the sleeper and returns its histogram (empty if the thread panicked).
    pub fn finish(mut self) -> WakeupReport {
        self.stop.store(true, Ordering::Relaxed);
        let (hist, fifo) = self
            .thread
            .take()
            .and_then(|t| t.join().ok())
            .unwrap_or_else(|| (LatencyHist::new(), false));
        WakeupReport {
            hist,
            fifo,
            period: self.period,
        }
    }
}

impl Drop for WakeupProbe {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl WakeupReport {
    /// `tail_ns` (a latency's p99.9, say) as a multiple of the probe's p99.9; `None` without
    /// samples or with a zero tail.
    pub fn ratio_to_p999(&self, tail_ns: f64) -> Option<f64> {
        let p = self.hist.summary().p999 as f64 * self.hist.ns_per_unit();
        (self.hist.count() > 0 && p > 0.0).then(|| tail_ns / p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_probe_records_until_finished() {
        let probe = WakeupProbe::start(Duration::from_millis(1), None).expect("spawn");
        std::thread::sleep(Duration::from_millis(20));
        let r = probe.finish();
        // No bound from wall time (a loaded machine may run the sleeper rarely): at least the
        // first sample is always taken.
        assert!(r.hist.count() >= 1, "{}", r.hist.count());
        assert!(!r.fifo);
        assert_eq!(r.period, Duration::from_millis(1));
        assert!(r.ratio_to_p999(1e9).is_some_and(|x| x > 0.0));
    }

    #[test]
    fn sleep_loop_stops_when_told() {
        let mut hist = LatencyHist::new();
        let mut n = 0;
        sleep_loop(Duration::from_micros(10), &mut hist, || {
            n += 1;
            n == 3
        });
        assert_eq!(hist.count(), 3);
    }

    #[test]
    fn no_samples_no_ratio() {
        let r = WakeupReport {
            hist: LatencyHist::new(),
            fifo: false,
            period: Duration::from_millis(1),
        };
        assert_eq!(r.ratio_to_p999(1e6), None);
    }
}
