//! The latency histograms of a live print ([`Hists`]): lead margin of every step message when
//! its bytes leave (recorded in the MCU link's IO thread), planner → IO stage hand-off, and the
//! planner thread's wake-up lateness; their report lines, HdrHistogram log and telemetry
//! summaries.

use std::fs::File;
use std::sync::atomic::{AtomicI64, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use links::mcu::McuLink;
use rt_core::hist::LatencyHist;
use rt_core::logger::{Arg, Level, LoggerHandle};
use rt_core::shm::{telemetry_kind, ShmPublisher, Telemetry};

use crate::mcus::Mcus;
use crate::MIN_LEAD_S;

/// MCUs whose lead margins [`Hists::lead_hook`] records (the first ones in `[mcu]` order;
/// the link statistics of every MCU keep its minimum anyway).
pub const LEAD_MCUS: usize = 8;

/// Latency histograms recorded during a live print.
#[derive(Debug)]
pub struct Hists {
    /// Lead margin of each step message when its bytes left, every MCU's, in ticks of the
    /// main MCU's clock (print ticks: another MCU's margins are scaled).
    pub lead: Mutex<LatencyHist>,
    /// Planner → IO stage hand-off (ns).
    pub handoff: Mutex<LatencyHist>,
    /// Planner thread wake-up lateness after a flow-control sleep (ns).
    pub wake_planner: Mutex<LatencyHist>,
    /// Per MCU: a step message leaving with less lead than this (its ticks) is logged as an
    /// error (0 until the MCU's clock frequency is known: then only negative margins are).
    pub min_lead_ticks: [AtomicI64; LEAD_MCUS],
    /// Per MCU: main ticks per tick of this MCU (f64 bits; 1.0 until known).
    lead_scale: [AtomicU64; LEAD_MCUS],
}

/// A copy of the histograms of a live print so far, in their recorded units (for a caller that
/// wants more than the summaries: `cadence bench pipeline`'s percentiles, logs and plots).
#[derive(Debug, Clone)]
pub struct HistSnapshot {
    /// Lead margin of each step message when its bytes left, in ticks of the main MCU's clock
    /// (`clock_freq`); negative margins are counted in its summary's `negative` (recorded as 0).
    pub lead: LatencyHist,
    /// Planner → IO stage hand-off (ns): how long after the planner sent a batch the IO stage
    /// woke and took it.
    pub handoff: LatencyHist,
    /// Planner thread wake-up lateness after a flow-control sleep (ns).
    pub wake_planner: LatencyHist,
    /// The main MCU's CLOCK_FREQ (Hz): the unit of `lead`.
    pub clock_freq: f64,
}

impl Hists {
    /// A copy of every histogram (each locked in turn; empty where a lock was poisoned).
    pub fn snapshot(&self, clock_freq: f64) -> HistSnapshot {
        let copy = |m: &Mutex<LatencyHist>| m.lock().map(|h| h.clone()).unwrap_or_default();
        HistSnapshot {
            lead: copy(&self.lead),
            handoff: copy(&self.handoff),
            wake_planner: copy(&self.wake_planner),
            clock_freq,
        }
    }

    pub fn new() -> Arc<Hists> {
        let ticks = || LatencyHist::with_bounds(1, 1 << 42, 3, 1.0).unwrap_or_else(|_| LatencyHist::new());
        Arc::new(Hists {
            lead: Mutex::new(ticks()),
            handoff: Mutex::new(LatencyHist::new()),
            wake_planner: Mutex::new(LatencyHist::new()),
            min_lead_ticks: std::array::from_fn(|_| AtomicI64::new(0)),
            lead_scale: std::array::from_fn(|_| AtomicU64::new(1f64.to_bits())),
        })
    }

    /// A link margin hook for MCU `mcu` (index in `[mcu]` order) recording into `lead` (runs
    /// in the link's IO thread; a `try_lock` so the IO thread never waits on a reader) and
    /// logging a message that left late. `None` past [`LEAD_MCUS`].
    pub fn lead_hook(
        self: &Arc<Self>,
        log: LoggerHandle,
        mcu: usize,
    ) -> Option<links::serialqueue::MarginHook> {
        if mcu >= LEAD_MCUS {
            return None;
        }
        let h = Arc::clone(self);
        let hook: links::serialqueue::MarginHook = Box::new(move |req: u64, margin: i64| {
            // Relaxed: a scale and threshold set once before the print starts.
            let scale = f64::from_bits(h.lead_scale[mcu].load(Ordering::Relaxed));
            if let Ok(mut hist) = h.lead.try_lock() {
                hist.record_signed((margin as f64 * scale) as i64);
            }
            if margin < h.min_lead_ticks[mcu].load(Ordering::Relaxed) {
                log.log(
                    Level::Error,
                    "step message left with too little lead: mcu index, req_clock, margin ticks",
                    [Arg::U(mcu as u64), Arg::U(req), Arg::I(margin)],
                );
            }
        });
        Some(hook)
    }

    /// Hooks for `ConnectOptions::lead_hooks`.
    pub fn lead_hooks(self: &Arc<Self>, log: LoggerHandle) -> crate::mcus::LeadHooks {
        let h = Arc::clone(self);
        Box::new(move |mcu| {
            h.lead_hook(log.clone(), mcu)
                .unwrap_or_else(|| -> links::serialqueue::MarginHook { Box::new(|_, _| {}) })
        })
    }

    /// Sets, for every connected MCU, the lead below which a step message is logged as late
    /// and the scale of its margins into the main MCU's ticks.
    pub fn set_min_lead(&self, mcus: &Mcus) {
        let main_freq = mcus.main().clock_freq;
        for (i, m) in mcus.list.iter().enumerate().take(LEAD_MCUS) {
            self.min_lead_ticks[i].store((MIN_LEAD_S * m.clock_freq) as i64, Ordering::Relaxed);
            self.lead_scale[i].store((main_freq / m.clock_freq).to_bits(), Ordering::Relaxed);
        }
    }

    /// Report lines (margins in ms of print time).
    pub fn report(&self, clock_freq: f64) -> Vec<String> {
        let mut out = Vec::new();
        if let Ok(h) = self.lead.lock() {
            let s = h.summary();
            if s.count > 0 {
                let ms = |t: u64| t as f64 / clock_freq * 1e3;
                out.push(format!(
                    "lead margin (ms): min {:.1} p0.1 {:.1} p1 {:.1} p50 {:.1} over {} step messages{}",
                    ms(s.min),
                    ms(s.p0_1),
                    ms(s.p1),
                    ms(s.p50),
                    s.count,
                    if s.negative > 0 {
                        format!(", {} LATE", s.negative)
                    } else {
                        String::new()
                    }
                ));
            }
        }
        for (name, m) in [
            ("hand-off planner→io", &self.handoff),
            ("wake-up lateness planner", &self.wake_planner),
        ] {
            if let Ok(h) = m.lock() {
                let s = h.summary();
                if s.count > 0 {
                    out.push(format!("{name}: {} ({} samples)", s.format_latency(), s.count));
                }
            }
        }
        out
    }

    /// Publishes a summary of each histogram on the telemetry service (see the module docs):
    /// kind `HIST_SUMMARY`, values = [count, negative, min, p0.1, p1, p50, p99, p99.9, max,
    /// mean, ns_per_unit], source 0 = lead margin (MCU ticks), 1 = hand-off (ns), 2 = planner
    /// wake-up lateness (ns). Monitors never stall the printer (safe overflow on). Only the
    /// sources in `sources` (bit n = source n) are published: with the IO stage in another
    /// process, each process publishes the histograms it records.
    pub(crate) fn publish<S: iceoryx2::service::Service>(
        &self,
        publisher: &mut ShmPublisher<S, Telemetry>,
        t_ns: u64,
        sources: u32,
    ) {
        for (source, m) in [(0u32, &self.lead), (1, &self.handoff), (2, &self.wake_planner)] {
            if sources & (1 << source) == 0 {
                continue;
            }
            let Ok(h) = m.try_lock() else { continue };
            let x = h.summary();
            drop(h);
            let values = [
                x.count as f64,
                x.negative as f64,
                x.min as f64,
                x.p0_1 as f64,
                x.p1 as f64,
                x.p50 as f64,
                x.p99 as f64,
                x.p999 as f64,
                x.max as f64,
                x.mean,
                x.ns_per_unit,
            ];
            let _ = publisher.send_with(|t| {
                t.kind = telemetry_kind::HIST_SUMMARY;
                t.source = source;
                t.t_ns = t_ns;
                t.count = values.len() as u32;
                t.values[..values.len()].copy_from_slice(&values);
            });
        }
    }

    /// Saves every histogram as an HdrHistogram V2 interval log.
    pub fn save(&self, path: &std::path::Path, wall_s: f64) -> Result<(), HistogramsError> {
        let file = File::create(path).map_err(|source| HistogramsError::Create {
            path: path.to_path_buf(),
            source,
        })?;
        let err = |source: rt_core::hist::HistError| HistogramsError::Write {
            path: path.to_path_buf(),
            source,
        };
        let mut log = rt_core::hist::IntervalLog::begin(
            std::io::BufWriter::new(file),
            "cadence print latency histograms",
        )
        .map_err(err)?;
        for (tag, m) in [
            ("lead_margin_ticks", &self.lead),
            ("handoff_ns", &self.handoff),
            ("wake_planner_ns", &self.wake_planner),
        ] {
            if let Ok(h) = m.lock() {
                log.write(tag, &h, Duration::ZERO, Duration::from_secs_f64(wall_s.max(0.0)))
                    .map_err(err)?;
            }
        }
        log.finish().map_err(err)?;
        Ok(())
    }
}

/// Why the histograms file (`--histograms`) could not be written.
#[derive(Debug, thiserror::Error)]
pub enum HistogramsError {
    /// The file could not be created.
    #[error("{}: {source}", .path.display())]
    Create {
        path: std::path::PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A histogram could not be written.
    #[error("{}: {source}", .path.display())]
    Write {
        path: std::path::PathBuf,
        #[source]
        source: rt_core::hist::HistError,
    },
}

/// Telemetry sources of [`Hists::publish`].
pub(crate) const ALL_SOURCES: u32 = 0b111;
pub(crate) const LEAD_SOURCE: u32 = 0b001;
pub(crate) const PLANNER_SOURCES: u32 = 0b110;

pub(crate) fn mono_ns() -> u64 {
    (McuLink::system_now() * 1e9) as u64
}
