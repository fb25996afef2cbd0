//! `cadence bench pipeline`: a live print on the simulated printer (or a printer.cfg) through
//! the library's [`Printer`], measured as it runs: the lead margin of every step message when
//! its bytes left for the MCU (against the 100 ms lead), the planner → IO stage hand-off (the
//! IO stage has no timer: the planner's event wakes it, so this is its wake-up latency) and the
//! planner thread's wake-up lateness after its flow-control sleeps, plus each MCU link's serial
//! round trip. On simulated MCUs the MCU's own view joins them, read back from their step
//! traces: each `queue_step`'s lead when it arrived (first step − receipt, MCU time) and each
//! step's lateness (executed − scheduled). The verdict says whether the 100 ms lead held, or
//! the first violation and where.

use super::trace_dir::TraceDir;
use std::io::Write;
use std::path::PathBuf;
use std::time::Duration;

use bench::hdrhistogram::Histogram;
use bench::run::{Common, Session};
use bench::stats::new_hist;
use bench::wakeup::mono_ns;
use bench::BenchError;

use super::{BenchCmdError, McuTraceError, PrintFailure};
use cadence::latency::HistSnapshot;
use cadence::printer::{PrinterOptions, PrinterSource};
use cadence::{Printer, MIN_LEAD_S};
use rt_core::hist::LatencyHist;

/// The reference print run when no file is given (the repository's `examples/square.gcode`).
pub const REFERENCE_NAME: &str = "examples/square.gcode";
const REFERENCE: &str = include_str!("../../examples/square.gcode");

/// Options of `cadence bench pipeline`.
#[derive(Debug, Clone, PartialEq)]
pub struct PipelineMode {
    /// The G-code file (`None`: the built-in reference print).
    pub file: Option<PathBuf>,
    /// printer.cfg (`None`: the built-in simulated printer).
    pub config: Option<PathBuf>,
    /// Simulated MCU clocks this many times faster than the wall clock (`None`: the config's).
    pub time_scale: Option<f64>,
    /// Step compression bound (µs).
    pub max_error_us: f64,
    /// Pin threads, SCHED_FIFO, locked memory (printer.cfg's `[realtime]`).
    pub realtime: bool,
}

/// Series names, in report order.
pub const SERIES: [&str; 3] = ["lead-margin", "handoff", "planner-wake"];
/// The MCU-side series (simulated MCUs only), in report order.
pub const MCU_SERIES: [&str; 2] = ["mcu-lead", "mcu-step-late"];

/// Prints the file and reports (see the module docs). A print that failed still writes its
/// report (with the reason as verdict) before the error is returned.
pub fn run(
    m: &PipelineMode,
    common: &Common,
    out: &mut dyn Write,
) -> Result<bench::report::Report, BenchCmdError> {
    let (file_name, describe) = describe(m);
    let budget = Some((MIN_LEAD_S * 1e9) as u64);
    let err = BenchCmdError::Bench;
    let mut s = Session::start("pipeline", &describe, common, budget, Duration::ZERO, out).map_err(err)?;
    s.report.set("file", file_name.clone());
    s.report
        .set("config", m.config.as_ref().map(|c| c.display().to_string()));
    s.report.set("time_scale", m.time_scale);
    s.report.set("max_error_us", m.max_error_us);
    s.report.set("realtime", m.realtime);
    let traces = TraceDir::new(&format!("pipeline-{}", std::process::id())).map_err(|source| {
        BenchCmdError::TraceDir {
            mode: "pipeline",
            source,
        }
    })?;
    let t0 = mono_ns().map_err(err)?;
    let (hists, outcome) = print(m, traces.base(), &mut s.report.figures);
    let t1 = mono_ns().map_err(err)?;
    let mcu = mcu_view(&traces).map_err(BenchCmdError::McuTraces)?;
    drop(traces);
    let lead = lead_ns(&hists.lead, hists.clock_freq).map_err(err)?;
    let mut series: Vec<(&str, Histogram<u64>)> = vec![
        (SERIES[0], lead),
        (SERIES[1], hists.handoff.histogram().clone()),
        (SERIES[2], hists.wake_planner.histogram().clone()),
    ];
    if let Some(v) = &mcu {
        series.push((MCU_SERIES[0], v.lead.clone()));
        series.push((MCU_SERIES[1], v.step_late.clone()));
        report_mcu_view(&mut s.report, v);
    }
    for (name, h) in &series {
        if h.is_empty() {
            s.report.notes.push(format!(
                "{name}: no samples (none of its events happened in this run: e.g. the planner never \
                 waited for the MCU clock)"
            ));
        } else {
            s.series(name, h);
            s.interval(name, t0, t1, h).map_err(err)?;
        }
    }
    let lead_summary = hists.lead.summary();
    s.report
        .figures
        .insert("lead_late_messages".into(), lead_summary.negative as f64);
    let under = under_budget(&series[0].1);
    s.report
        .figures
        .insert("lead_under_100ms_messages".into(), under as f64);
    let failed = outcome.as_ref().err().map(|e| e as &dyn std::fmt::Display);
    let mut v = verdict(&series[0].1, lead_summary.negative, under, failed);
    if let Some(m) = mcu.as_ref().filter(|m| !m.lead.is_empty()) {
        v.push_str(&format!(
            "; at the MCU: min lead {:.1} ms on arrival over {} queue_step, steps late max {}",
            m.lead.min() as f64 / 1e6,
            m.lead.len(),
            rt_core::hist::fmt_ns(m.step_late.max() as f64)
        ));
    }
    s.report.verdict = Some(v);
    if m.time_scale.is_some_and(|t| t != 1.0) {
        s.report.notes.push(
            "lead margins are print time, which runs time-scale times faster than the wall clock".into(),
        );
    }
    s.report.notes.push(
        "handoff: planner sent a step batch → the IO stage woke and took it (the IO stage has no timer of its own)"
            .into(),
    );
    let plot: Vec<bench::plot::PlotSeries<'_>> = series
        .iter()
        .filter(|(_, h)| !h.is_empty())
        .map(|(name, hist)| bench::plot::PlotSeries { name, hist })
        .collect();
    let title = format!("live print of {file_name}: lead margin and stage latencies");
    let report = s.finish(&title, &plot, out).map_err(err)?;
    Ok(outcome.map(|()| report)?)
}

/// The G-code file's name and the run's one-line description.
fn describe(m: &PipelineMode) -> (String, String) {
    let file_name = m
        .file
        .as_ref()
        .map_or(format!("{REFERENCE_NAME} (built in)"), |f| {
            f.display().to_string()
        });
    let printer_name = m
        .config
        .as_ref()
        .map_or("the built-in simulated printer".to_string(), |c| {
            c.display().to_string()
        });
    let describe = format!(
        "pipeline: {file_name} on {printer_name}, time scale {}, real time {}",
        m.time_scale
            .map_or("as configured".to_string(), |s| s.to_string()),
        if m.realtime { "on" } else { "off" }
    );
    (file_name, describe)
}

/// The MCU traces' figures and what their series mean, in the report.
fn report_mcu_view(report: &mut bench::report::Report, v: &McuView) {
    report.figures.insert("mcu_traces".into(), v.traces as f64);
    report
        .figures
        .insert("mcu_steps".into(), v.step_late.len() as f64);
    report
        .figures
        .insert("mcu_queue_steps".into(), v.lead.len() as f64);
    report
        .figures
        .insert("mcu_late_queue_steps".into(), v.late_on_arrival as f64);
    report.notes.push(
        "mcu-lead: each queue_step's first step − its arrival at the MCU; mcu-step-late: each step's \
         execution − its scheduled clock; both in MCU time, read from the simulated MCUs' step traces"
            .into(),
    );
}

/// Runs the print; returns the histograms (whatever happened) and the outcome. Figures of the
/// run (lines, moves, times, link round trips) go to `figures`.
fn print(
    m: &PipelineMode,
    trace: PathBuf,
    figures: &mut std::collections::BTreeMap<String, f64>,
) -> (HistSnapshot, Result<(), PrintFailure>) {
    let empty = HistSnapshot {
        lead: LatencyHist::new(),
        handoff: LatencyHist::new(),
        wake_planner: LatencyHist::new(),
        clock_freq: 1.0,
    };
    let source = match &m.config {
        Some(p) => PrinterSource::ConfigFile(p.clone()),
        None => PrinterSource::Simulated,
    };
    let opts = PrinterOptions {
        time_scale: m.time_scale,
        max_error_us: m.max_error_us,
        realtime: m.realtime,
        trace: Some(trace),
        ..PrinterOptions::default()
    };
    let printer = match Printer::open(source, opts) {
        Ok(p) => p,
        Err(e) => return (empty, Err(e.into())),
    };
    let ran = match &m.file {
        Some(f) => printer.run_gcode_file(f),
        None => printer.run_gcode_stream(REFERENCE_NAME, REFERENCE.as_bytes()),
    }
    .and_then(|()| printer.wait_moves())
    .map_err(PrintFailure::from);
    let hists = printer.latency_histograms();
    let closed = printer.close();
    let outcome = match (ran, closed) {
        (Err(e), _) => Err(e),
        (Ok(()), Err(e)) => Err(e.into()),
        (Ok(()), Ok(r)) => {
            let sm = &r.summary;
            figures.insert("lines".into(), sm.lines as f64);
            figures.insert("moves".into(), sm.moves as f64);
            figures.insert("queue_steps".into(), sm.queue_steps as f64);
            figures.insert("print_time_s".into(), sm.print_time);
            figures.insert("wall_s".into(), sm.wall);
            for (name, st) in &r.link_stats {
                figures.insert(format!("{name}_srtt_us"), st.queue.srtt * 1e6);
                figures.insert(format!("{name}_rttvar_us"), st.queue.rttvar * 1e6);
                figures.insert(format!("{name}_retransmits"), st.queue.retransmits as f64);
            }
            Ok(())
        }
    };
    (hists, outcome)
}

/// What the MCUs saw, from their step traces.
struct McuView {
    /// Traces read (one per simulated MCU).
    traces: usize,
    /// Each `queue_step`'s lead on arrival (ns of MCU time).
    lead: Histogram<u64>,
    /// `queue_step`s that arrived after their first step's clock.
    late_on_arrival: u64,
    /// Each step's lateness (ns of MCU time, µs resolution).
    step_late: Histogram<u64>,
}

/// Reads every trace the simulated MCUs wrote; `None` when there is none (real MCUs only).
fn mcu_view(dir: &TraceDir) -> Result<Option<McuView>, McuTraceError> {
    use firmware::trace::{for_each_record, TraceRecord};
    let mut paths: Vec<PathBuf> = std::fs::read_dir(&dir.0)
        .map_err(|source| McuTraceError::Read {
            path: dir.0.clone(),
            source,
        })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "trace"))
        .collect();
    paths.sort();
    if paths.is_empty() {
        return Ok(None);
    }
    let mut view = McuView {
        traces: paths.len(),
        lead: new_hist()?,
        late_on_arrival: 0,
        step_late: new_hist()?,
    };
    for path in &paths {
        // The frequency is known once the file is read: collect ticks, scale after.
        let mut leads: Vec<u64> = Vec::new();
        let (freq, _) = for_each_record(path, |r| match *r {
            TraceRecord::Step { lateness_us, .. } => {
                view.step_late.saturating_record(u64::from(lateness_us) * 1000);
            }
            TraceRecord::QueueStep {
                received_clock,
                first_step_clock,
                ..
            } => {
                if first_step_clock <= received_clock {
                    view.late_on_arrival += 1;
                }
                leads.push(first_step_clock.saturating_sub(received_clock));
            }
            TraceRecord::Shutdown { .. } => {}
        })
        .map_err(|source| McuTraceError::Read {
            path: path.clone(),
            source,
        })?;
        let ns_per_tick = 1e9 / freq.max(1) as f64;
        for ticks in leads {
            view.lead
                .saturating_record((ticks as f64 * ns_per_tick).round() as u64);
        }
    }
    Ok(Some(view))
}

/// The lead margins (ticks of `clock_freq`) in nanoseconds.
pub fn lead_ns(lead: &LatencyHist, clock_freq: f64) -> Result<Histogram<u64>, BenchError> {
    let mut h = new_hist()?;
    let ns_per_tick = 1e9 / clock_freq;
    for v in lead.histogram().iter_recorded() {
        h.saturating_record_n(
            (v.value_iterated_to() as f64 * ns_per_tick).round() as u64,
            v.count_at_value(),
        );
    }
    Ok(h)
}

/// Step messages whose margin was under the 100 ms lead.
fn under_budget(lead_ns: &Histogram<u64>) -> u64 {
    let limit = (MIN_LEAD_S * 1e9) as u64;
    lead_ns
        .iter_recorded()
        .filter(|v| v.value_iterated_to() < limit)
        .map(|v| v.count_at_value())
        .sum()
}

/// "100 ms lead held: min margin X ms over N step messages", or what broke it and where.
fn verdict(
    lead_ns: &Histogram<u64>,
    late: u64,
    under: u64,
    failed: Option<&dyn std::fmt::Display>,
) -> String {
    let ms = |ns: u64| ns as f64 / 1e6;
    let lead_ms = MIN_LEAD_S * 1e3;
    if let Some(reason) = failed {
        return format!("{lead_ms:.0} ms lead NOT held: the print stopped: {reason}");
    }
    if lead_ns.is_empty() {
        return "no step message was sent: nothing to judge".into();
    }
    if under == 0 {
        format!(
            "{lead_ms:.0} ms lead held: min margin {:.1} ms over {} step messages",
            ms(lead_ns.min()),
            lead_ns.len()
        )
    } else {
        format!(
            "{lead_ms:.0} ms lead NOT held: {under} of {} step messages left the MCU link with less \
             ({late} after their clock), min margin {:.1} ms (stage: the MCU link's IO thread)",
            lead_ns.len(),
            ms(lead_ns.min())
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lead_ticks_become_ns_and_the_verdict_judges_the_minimum() {
        let mut lead = LatencyHist::with_bounds(1, 1 << 42, 3, 1.0).unwrap();
        lead.record(50_000_000); // 1 s at 50 MHz
        lead.record(10_000_000); // 200 ms
        let h = lead_ns(&lead, 50e6).unwrap();
        assert_eq!(h.len(), 2);
        assert!((h.min() as f64 - 200e6).abs() < 200e6 * 1e-3, "{}", h.min());
        assert_eq!(under_budget(&h), 0);
        let v = verdict(&h, 0, 0, None);
        assert!(
            v.starts_with("100 ms lead held: min margin 200.0 ms over 2"),
            "{v}"
        );
        lead.record(2_500_000); // 50 ms
        let h = lead_ns(&lead, 50e6).unwrap();
        assert_eq!(under_budget(&h), 1);
        assert!(verdict(&h, 0, 1, None).contains("NOT held: 1 of 3"));
        let why = "the IO stage fell behind".to_string();
        assert!(verdict(&h, 0, 1, Some(&why)).contains("stopped: the IO stage fell behind"));
    }
}
