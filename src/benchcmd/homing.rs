//! `cadence bench homing`: repeated homing cycles on the simulated printers through the
//! library's homing cycles ([`cadence::home_cycles`]): the built-in single-MCU printer (every
//! endstop on the steppers' MCU: the MCU stops itself) and the multi-MCU one
//! (`examples/simulated-multi-mcu.cfg`: the Z endstop on `probe_mcu`, the host relays the
//! trigger to the steppers' MCU), or one printer.cfg.
//!
//! Per axis and printer: trigger → stop, measured as the first step the stop cancelled minus
//! the endstop's trigger (an upper bound of the stop latency; the last executed step is its
//! lower bound), against the 25 ms homing budget; the overshoot (mm past the trigger point);
//! and the machine's own wake-up latency meanwhile (1 ms sleeps at the IO threads' priority)
//! as a series and as the ratio of each p99.9 to its p99.9.
//!
//! On the simulated MCUs the exact figure joins it, read from their step traces
//! ([`cadence::home_cycles::TraceStops`]): the endstop's trigger record to the steppers' MCU's
//! trsync trigger record (the moment its steppers stopped), per printer and axis as
//! `<printer>-<axis>-exact`.

use super::trace_dir::TraceDir;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Duration;

use bench::hdrhistogram::Histogram;
use bench::modes::HOMING_BUDGET_NS;
use bench::run::{Common, Session};
use bench::stats::{merge, new_hist, Percentiles};
use bench::wakeup::mono_ns;
use bench::BenchError;

use super::BenchCmdError;
use cadence::home_cycles::{CycleFigures, HomeOptions, HomeOutput};
use cadence::homing::{HomingReport, AXIS_NAMES};

const MULTI_MCU_CFG: &str = include_str!("../../examples/simulated-multi-mcu.cfg");

/// Which printers to home.
#[derive(Debug, Clone, PartialEq)]
pub enum Printers {
    /// The built-in single-MCU printer, then the multi-MCU one.
    Both,
    /// The built-in simulated printer (one MCU).
    Single,
    /// `examples/simulated-multi-mcu.cfg` (built in): Z endstop on a second MCU.
    Multi,
    /// A printer.cfg.
    Config(PathBuf),
}

/// Options of `cadence bench homing`.
#[derive(Debug, Clone, PartialEq)]
pub struct HomingMode {
    pub printers: Printers,
    /// Axes to home (`None`: X, Y and Z on the single-MCU printer and a config, Z on the
    /// multi-MCU one, its relayed axis).
    pub axes: Option<[bool; 3]>,
    /// Homing cycles per printer.
    pub cycles: u32,
    /// mm the axes move off their endstops between cycles.
    pub away: f64,
    pub time_scale: Option<f64>,
    pub realtime: bool,
}

/// Notes of the homing cycles go to the report; their own text report is not repeated.
#[derive(Default)]
struct Collect {
    notes: Vec<String>,
}

impl HomeOutput for Collect {
    fn out(&mut self, _line: String) {}
    fn err(&mut self, line: String) {
        self.notes.push(line);
    }
}

/// One series: passes of one axis on one printer.
struct Group {
    name: String,
    mcus: Vec<String>,
    stop: Histogram<u64>,
    /// Overshoot in nm.
    overshoot: Histogram<u64>,
}

/// Homes and reports (see the module docs).
pub fn run(
    m: &HomingMode,
    common: &Common,
    out: &mut dyn Write,
) -> Result<bench::report::Report, BenchCmdError> {
    if m.cycles == 0 {
        return Err(BenchCmdError::NoCycles);
    }
    let err = BenchCmdError::Bench;
    let printers = printers_of(m)?;
    let names: Vec<String> = printers
        .iter()
        .map(|(n, _, axes)| format!("{n} ({})", axes_str(*axes)))
        .collect();
    let (describe, expected) = describe(m, &printers, &names);
    let mut s =
        Session::start("homing", &describe, common, Some(HOMING_BUDGET_NS), expected, out).map_err(err)?;
    s.report.set("printers", names.clone());
    s.report.set("cycles", m.cycles);
    s.report.set("away_mm", m.away);
    s.report.set("time_scale", m.time_scale);
    s.report.set("realtime", m.realtime);
    let mut groups: Vec<Group> = Vec::new();
    let mut wakeup = new_hist().map_err(err)?;
    let mut timeouts = 0u32;
    let mut scales = Vec::new();
    let mut exact: Vec<(String, Histogram<u64>)> = Vec::new();
    let t0 = mono_ns().map_err(err)?;
    for (name, config, axes) in &printers {
        let (figures, notes) = home_printer(name, config, *axes, m)?;
        s.report
            .notes
            .extend(notes.into_iter().map(|n| format!("{name}: {n}")));
        timeouts += figures.timeouts;
        scales.push(figures.time_scale);
        group_passes(name, &figures.reports, &mut groups).map_err(err)?;
        for t in &figures.trace_stops {
            let axis = AXIS_NAMES[t.axis.min(2)].to_ascii_lowercase();
            exact.push((format!("{name}-{axis}-exact"), to_ns(&t.stop).map_err(err)?));
        }
        merge(&mut wakeup, figures.noise.hist.histogram()).map_err(err)?;
        s.progress(Duration::from_secs_f64(
            (mono_ns().map_err(err)?.saturating_sub(t0)) as f64 * 1e-9,
        ));
    }
    if let Printers::Both | Printers::Multi = m.printers {
        if let Some((_, Some(p), _)) = printers.iter().find(|(n, _, _)| n == "multi") {
            let _ = std::fs::remove_file(p);
        }
    }
    let t1 = mono_ns().map_err(err)?;
    let wake_p999 = Percentiles::of(&wakeup).p99_9_ns as f64;
    report_groups(&mut s, &groups, wake_p999, (t0, t1)).map_err(err)?;
    let has_exact = !exact.is_empty();
    // After the groups: the exact series, then the machine's wake-up.
    let mut more = exact;
    more.push(("machine-wakeup".into(), wakeup));
    more.retain(|(_, h)| !h.is_empty());
    for (name, h) in &more {
        s.series(name, h);
        s.interval(name, t0, t1, h).map_err(err)?;
    }
    s.report.figures.insert("timeouts".into(), f64::from(timeouts));
    explain(&mut s.report, scales.iter().any(|&x| x != 1.0), has_exact);
    s.report.verdict = verdict(&groups, timeouts, wake_p999, s.report.budget_ns);
    let mut plot: Vec<bench::plot::PlotSeries<'_>> = groups
        .iter()
        .map(|g| bench::plot::PlotSeries {
            name: &g.name,
            hist: &g.stop,
        })
        .collect();
    plot.extend(
        more.iter()
            .map(|(name, hist)| bench::plot::PlotSeries { name, hist }),
    );
    let title = format!("homing trigger → stop, {} cycles", m.cycles);
    s.finish(&title, &plot, out).map_err(err)
}

/// The run's one-line description and its expected duration: about 2 s per axis and cycle at
/// the simulated printers' homing speeds.
fn describe(m: &HomingMode, printers: &[PrinterRun], names: &[String]) -> (String, Duration) {
    let describe = format!(
        "homing: {} cycles on each of {}, {} mm away between cycles, time scale {}, real time {}",
        m.cycles,
        names.join(", "),
        m.away,
        m.time_scale
            .map_or("as configured".to_string(), |s| s.to_string()),
        if m.realtime { "on" } else { "off" }
    );
    let passes: u32 = printers
        .iter()
        .map(|(_, _, a)| a.iter().filter(|x| **x).count() as u32)
        .sum();
    (describe, Duration::from_secs(2) * m.cycles.saturating_mul(passes))
}

/// The report's notes on what its series measure (`scaled`: a time scale other than 1;
/// `exact`: there are series from the MCU traces).
fn explain(report: &mut bench::report::Report, scaled: bool, exact: bool) {
    if scaled {
        report.notes.push(
            "trigger → stop and overshoot are MCU print time, which ran time-scale times faster than \
             the wall clock (the machine's wake-up is wall time)"
                .into(),
        );
    }
    report.notes.push(
        "trigger → stop: first step the stop cancelled − the endstop's trigger (an upper bound; MCU time)"
            .into(),
    );
    if exact {
        report.notes.push(
            "*-exact: the endstop MCU's trigger record → the steppers' MCU's trsync trigger record (its \
             steppers stopped), from the simulated MCUs' traces, in system time"
                .into(),
        );
    }
}

/// One printer to home: its name, its printer.cfg (`None`: the built-in one) and the axes.
type PrinterRun = (String, Option<PathBuf>, [bool; 3]);

/// The printers to home. The
/// multi-MCU printer's config is written to a temporary file (removed after its cycles).
fn printers_of(m: &HomingMode) -> Result<Vec<PrinterRun>, BenchCmdError> {
    let all = [true; 3];
    let z = [false, false, true];
    let multi = || -> Result<PathBuf, BenchCmdError> {
        let p = std::env::temp_dir().join(format!("cadence-bench-multi-mcu-{}.cfg", std::process::id()));
        std::fs::write(&p, MULTI_MCU_CFG).map_err(|source| BenchCmdError::File {
            path: p.clone(),
            source,
        })?;
        Ok(p)
    };
    Ok(match &m.printers {
        Printers::Both => vec![
            ("single".into(), None, m.axes.unwrap_or(all)),
            ("multi".into(), Some(multi()?), m.axes.unwrap_or(z)),
        ],
        Printers::Single => vec![("single".into(), None, m.axes.unwrap_or(all))],
        Printers::Multi => vec![("multi".into(), Some(multi()?), m.axes.unwrap_or(z))],
        Printers::Config(p) => vec![(stem(p), Some(p.clone()), m.axes.unwrap_or(all))],
    })
}

/// Each group's trigger → stop series and interval log, overshoot figures, ratio to the
/// machine's wake-up p99.9 and trigger group note.
fn report_groups(
    s: &mut Session,
    groups: &[Group],
    wake_p999: f64,
    (t0, t1): (u64, u64),
) -> Result<(), BenchError> {
    for g in groups {
        s.series(&g.name, &g.stop);
        s.interval(&g.name, t0, t1, &g.stop)?;
        let mm = |nm: u64| nm as f64 * 1e-6;
        let ov = Percentiles::of(&g.overshoot);
        let f = &mut s.report.figures;
        f.insert(format!("{}_overshoot_p50_mm", g.name), mm(ov.p50_ns));
        f.insert(format!("{}_overshoot_p99_mm", g.name), mm(ov.p99_ns));
        f.insert(format!("{}_overshoot_p99_9_mm", g.name), mm(ov.p99_9_ns));
        f.insert(format!("{}_overshoot_max_mm", g.name), mm(ov.max_ns));
        if wake_p999 > 0.0 {
            f.insert(
                format!("{}_p99_9_over_wakeup_p99_9", g.name),
                Percentiles::of(&g.stop).p99_9_ns as f64 / wake_p999,
            );
        }
        s.report.notes.push(format!(
            "{}: trigger group {} ({})",
            g.name,
            g.mcus.join("+"),
            if g.mcus.len() > 1 {
                "the host relays the trigger between MCUs"
            } else {
                "the MCU stops its own steppers"
            }
        ));
    }
    Ok(())
}

/// A latency histogram (negative values counted as 0) in nanoseconds.
fn to_ns(h: &rt_core::hist::LatencyHist) -> Result<Histogram<u64>, BenchError> {
    let mut out = new_hist()?;
    for v in h.histogram().iter_recorded() {
        out.saturating_record_n(
            (v.value_iterated_to() as f64 * h.ns_per_unit()).round() as u64,
            v.count_at_value(),
        );
    }
    Ok(out)
}

/// Homes printer `name` `m.cycles` times, its simulated MCUs tracing into a scratch directory
/// (removed after).
fn home_printer(
    name: &str,
    config: &Option<PathBuf>,
    axes: [bool; 3],
    m: &HomingMode,
) -> Result<(CycleFigures, Vec<String>), BenchCmdError> {
    let traces = TraceDir::new(&format!("homing-{}-{name}", std::process::id())).map_err(|source| {
        BenchCmdError::TraceDir {
            mode: "homing",
            source,
        }
    })?;
    let opts = HomeOptions {
        config: config.clone(),
        axes,
        cycles: m.cycles,
        away: m.away,
        cpu_load: false,
        time_scale: m.time_scale,
        trace: Some(traces.base()),
        max_error_us: 25.0,
        no_realtime: !m.realtime,
    };
    home_in_thread(opts)
}

/// Runs the cycles on a thread of their own: they pin their thread and give it SCHED_FIFO,
/// which the next printer's simulated MCUs and sleeper must not inherit.
fn home_in_thread(opts: HomeOptions) -> Result<(CycleFigures, Vec<String>), BenchCmdError> {
    std::thread::Builder::new()
        .name("bench-homing".into())
        .spawn(move || {
            let mut o = Collect::default();
            cadence::home_cycles::run_figures(&opts, &mut o).map(|f| (f, o.notes))
        })
        .map_err(BenchCmdError::HomingThread)?
        .join()
        .map_err(|_| BenchCmdError::HomingPanicked)?
        .map_err(BenchCmdError::from)
}

/// Adds every pass of `reports` to the group of its printer and axis.
fn group_passes(printer: &str, reports: &[HomingReport], groups: &mut Vec<Group>) -> Result<(), BenchError> {
    for r in reports {
        for a in &r.axes {
            let name = format!("{printer}-{}", AXIS_NAMES[a.axis.min(2)]);
            let i = match groups.iter().position(|g| g.name == name) {
                Some(i) => i,
                None => {
                    groups.push(Group {
                        name,
                        mcus: a.mcus.clone(),
                        stop: new_hist()?,
                        overshoot: new_hist()?,
                    });
                    groups.len() - 1
                }
            };
            let g = &mut groups[i];
            for p in &a.passes {
                g.stop
                    .saturating_record((p.next_step_after_s.max(0.0) * 1e9) as u64);
                g.overshoot
                    .saturating_record((p.overshoot_mm.max(0.0) * 1e6) as u64);
            }
        }
    }
    Ok(())
}

/// "25 ms homing budget held: …" or "OVER …", with the worst group and the wake-up ratio.
fn verdict(groups: &[Group], timeouts: u32, wake_p999: f64, budget_ns: Option<u64>) -> Option<String> {
    let budget = budget_ns? as f64;
    let fmt = rt_core::hist::fmt_ns;
    let Some(worst) = groups.iter().max_by_key(|g| g.stop.max()) else {
        return Some(format!(
            "OVER the {} homing budget: no homing pass completed ({timeouts} cycles ended in a \
             communication timeout)",
            fmt(budget)
        ));
    };
    let passes: u64 = groups.iter().map(|g| g.stop.len()).sum();
    let max = worst.stop.max() as f64;
    let p999 = Percentiles::of(&worst.stop).p99_9_ns as f64;
    let ratio = if wake_p999 > 0.0 {
        format!(
            ", its p99.9 {} = {:.1} x the machine's wake-up p99.9",
            fmt(p999),
            p999 / wake_p999
        )
    } else {
        String::new()
    };
    let timed_out = if timeouts > 0 {
        format!("; {timeouts} cycles ended in a communication timeout")
    } else {
        String::new()
    };
    Some(if max <= budget && timeouts == 0 {
        format!(
            "{} homing budget held: trigger → stop max {} ({}) over {passes} passes{ratio}",
            fmt(budget),
            fmt(max),
            worst.name
        )
    } else {
        format!(
            "OVER the {} homing budget: trigger → stop max {} ({}) over {passes} passes{ratio}{timed_out}",
            fmt(budget),
            fmt(max),
            worst.name
        )
    })
}

fn stem(p: &Path) -> String {
    p.file_stem()
        .map_or("config".to_string(), |s| s.to_string_lossy().into_owned())
}

fn axes_str(axes: [bool; 3]) -> String {
    axes.iter()
        .zip(AXIS_NAMES)
        .filter(|(on, _)| **on)
        .map(|(_, n)| n)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use cadence::homing::{AxisReport, PassReport};

    fn pass(next_step_after_s: f64, overshoot_mm: f64) -> PassReport {
        PassReport {
            speed: 10.0,
            trigger_mcu: "probe_mcu".into(),
            trigger_clock: 0,
            trigger_print_time: 0.0,
            overshoot_mm,
            trigger_position: 0.0,
            steps: 0,
            last_step_after_s: 0.0,
            next_step_after_s,
            trigger_received_at: 0.0,
            relay_written_at: None,
        }
    }

    #[test]
    fn passes_group_by_printer_and_axis_and_the_verdict_takes_the_worst() {
        let report = HomingReport {
            axes: vec![
                AxisReport {
                    axis: 2,
                    mcus: vec!["probe_mcu".into(), "mcu".into()],
                    passes: vec![pass(0.002, 0.01), pass(0.004, 0.02)],
                    position: 0.0,
                },
                AxisReport {
                    axis: 0,
                    mcus: vec!["mcu".into()],
                    passes: vec![pass(0.0002, 0.001)],
                    position: 0.0,
                },
            ],
        };
        let mut groups = Vec::new();
        group_passes("multi", &[report.clone(), report], &mut groups).unwrap();
        assert_eq!(groups.len(), 2);
        assert_eq!((groups[0].name.as_str(), groups[0].stop.len()), ("multi-z", 4));
        assert_eq!(groups[1].name, "multi-x");
        let v = verdict(&groups, 0, 1e6, Some(HOMING_BUDGET_NS)).unwrap();
        assert!(v.starts_with("25.00 ms homing budget held"), "{v}");
        assert!(v.contains("(multi-z) over 6 passes"), "{v}");
        let v = verdict(&groups, 1, 0.0, Some(HOMING_BUDGET_NS)).unwrap();
        assert!(v.starts_with("OVER") && v.contains("1 cycles ended"), "{v}");
        assert!(verdict(&groups, 0, 0.0, Some(3_000_000))
            .unwrap()
            .starts_with("OVER"));
        assert_eq!(verdict(&groups, 0, 0.0, None), None);
        let v = verdict(&[], 2, 0.0, Some(HOMING_BUDGET_NS)).unwrap();
        assert!(
            v.starts_with("OVER") && v.contains("no homing pass completed (2 cycles"),
            "{v}"
        );
    }
}
