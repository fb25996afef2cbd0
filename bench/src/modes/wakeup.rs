//! `cadence bench wakeup`: the wake-up measurement ([`crate::wakeup`]) with memory locked and
//! `/dev/cpu_dma_latency` held at 0 (as cyclictest does), and with `--compare-cyclictest`
//! cyclictest run with the same settings in alternating slices of the same run: Cadence for a
//! slice, cyclictest for a slice, and so on, so both see the same machine state.
//!
//! The ratios compare Cadence's figures over cyclictest's at cyclictest's resolution: every
//! Cadence sample truncated to whole microseconds, as cyclictest counts them.

use std::io::Write;
use std::time::{Duration, Instant};

use hdrhistogram::Histogram;

use crate::cyclictest::{self, CyclictestRun};
use crate::error::BenchError;
use crate::plot::PlotSeries;
use crate::report::{Compare, Ratio, Report};
use crate::run::{series, Common, Session};
use crate::stats::{merge, new_hist, Percentiles, COLUMNS};
use crate::wakeup::{self, Stop, Wait, WakeupOptions};

/// Options of `cadence bench wakeup`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WakeupMode {
    pub measure: WakeupOptions,
    /// `mlockall(MCL_CURRENT|MCL_FUTURE)` before the threads start.
    pub lock_memory: bool,
    /// Run cyclictest in alternating slices with the same settings.
    pub compare_cyclictest: bool,
    /// Length of one slice of each tool (whole seconds).
    pub slice: Duration,
}

/// Runs it (see the module doc).
pub fn run(mode: &WakeupMode, common: &Common, out: &mut dyn Write) -> Result<Report, BenchError> {
    let m = &mode.measure;
    let cyclictest_exe = if mode.compare_cyclictest {
        check_compare(mode)?
    } else {
        None
    };
    let expected = match m.stop {
        Stop::Duration(d) => d,
        Stop::Loops(n) => m.interval.saturating_mul(u32::try_from(n).unwrap_or(u32::MAX)),
    };
    let mut notes = Vec::new();
    if mode.lock_memory {
        if let Err(e) = rt_core::os::lock_memory() {
            notes.push(format!("{e}: pages may be swapped"));
        }
    }
    let dma = rt_core::os::hold_cpu_dma_latency_zero();
    if let Err(e) = &dma {
        notes.push(format!(
            "{e}: idle CPUs may sleep deeply (cyclictest holds it at 0 too)"
        ));
    }
    let total_expected = if cyclictest_exe.is_some() {
        expected * 2
    } else {
        expected
    };
    let mut s = Session::start(
        "wakeup",
        &describe(mode),
        common,
        Some(super::HOMING_BUDGET_NS),
        total_expected,
        out,
    )?;
    settings(&mut s.report, mode);
    let n = m.cpus.len();
    let mut ours: Vec<Histogram<u64>> = (0..n).map(|_| new_hist()).collect::<Result<_, _>>()?;
    let mut theirs: Vec<Histogram<u64>> = (0..n).map(|_| new_hist()).collect::<Result<_, _>>()?;
    let (mut overruns, mut unpinned, mut no_fifo, mut overflows) = (0u64, false, false, 0u64);
    let mut version = String::new();
    let started = Instant::now();
    let slices: Vec<Stop> = match (cyclictest_exe.is_some(), m.stop) {
        (true, Stop::Duration(d)) => {
            let k = d.as_secs().div_ceil(mode.slice.as_secs().max(1)).max(1);
            (0..k).map(|_| Stop::Duration(mode.slice)).collect()
        }
        (_, stop) => vec![stop],
    };
    for slice in slices {
        let o = WakeupOptions {
            stop: slice,
            ..m.clone()
        };
        let cpus = m.cpus.clone();
        let threads = wakeup::run(
            &o,
            &mut |i, iv| {
                s.progress(started.elapsed());
                s.interval(&format!("cpu{}", cpus[i]), iv.start_ns, iv.end_ns, &iv.hist)
            },
            &mut |_| {},
        )?;
        for (i, t) in threads.iter().enumerate() {
            merge(&mut ours[i], &t.hist)?;
            overruns += t.overruns;
            unpinned |= !t.applied.pinned;
            no_fifo |= m.priority.is_some() && !t.applied.fifo;
        }
        s.progress(started.elapsed());
        if let (Some(exe), Stop::Duration(d)) = (&cyclictest_exe, slice) {
            let run = CyclictestRun {
                cpus: m.cpus.clone(),
                priority: m.priority,
                interval: m.interval,
                seconds: d.as_secs().max(1),
            };
            let t0 = wakeup::mono_ns()?;
            let (threads, v) = run.run(exe)?;
            let t1 = wakeup::mono_ns()?;
            version = v;
            for (i, t) in threads.iter().enumerate().take(n) {
                s.interval(&format!("cyclictest-cpu{}", m.cpus[i]), t0, t1, &t.hist)?;
                merge(&mut theirs[i], &t.hist)?;
                overflows += t.overflows;
            }
            s.progress(started.elapsed());
        }
    }
    for (i, h) in ours.iter().enumerate() {
        s.series(&format!("cpu{}", m.cpus[i]), h);
    }
    let all_ours = merged(&ours)?;
    if n > 1 {
        s.series("all", &all_ours);
    }
    if cyclictest_exe.is_some() {
        let all_theirs = merged(&theirs)?;
        let mut c = Compare {
            tool: "cyclictest".into(),
            version,
            series: Vec::new(),
            ratios: ratios(&truncated_to_us(&all_ours)?, &all_theirs),
        };
        for (i, h) in theirs.iter().enumerate() {
            c.series.push(series(&format!("cpu{}", m.cpus[i]), h));
        }
        if n > 1 {
            c.series.push(series("all", &all_theirs));
        }
        if overflows > 0 {
            notes.push(format!(
                "{overflows} cyclictest samples over its {} ms histogram, counted at its maximum",
                cyclictest::HIST_LIMIT_US / 1000
            ));
        }
        s.report.compare = Some(c);
    }
    if overruns > 0 {
        notes.push(format!(
            "{overruns} deadlines skipped (woke after the next one had passed)"
        ));
    }
    if unpinned {
        notes.push("some threads could not be pinned (see the realtime: line above)".into());
    }
    if no_fifo {
        notes.push(format!(
            "SCHED_FIFO {} refused: measured under normal scheduling",
            m.priority.unwrap_or(0)
        ));
    }
    s.report.verdict = verdict(&Percentiles::of(&all_ours), s.report.budget_ns);
    s.report.notes.extend(notes);
    drop(dma);
    let mut plot: Vec<(String, &Histogram<u64>)> = Vec::new();
    for (i, h) in ours.iter().enumerate() {
        plot.push((format!("cadence cpu{}", m.cpus[i]), h));
    }
    if cyclictest_exe.is_some() {
        for (i, h) in theirs.iter().enumerate() {
            plot.push((format!("cyclictest cpu{}", m.cpus[i]), h));
        }
    }
    let plot: Vec<PlotSeries<'_>> = plot
        .iter()
        .map(|(name, hist)| PlotSeries { name, hist })
        .collect();
    s.finish(&title(mode, common), &plot, out)
}

/// The cyclictest executable, after checking the options allow a comparison.
fn check_compare(mode: &WakeupMode) -> Result<Option<std::path::PathBuf>, BenchError> {
    if mode.measure.wait == Wait::Busy {
        return Err(BenchError::Options(
            "--compare-cyclictest needs the sleeping mode (cyclictest has no busy-wait)".into(),
        ));
    }
    if let Stop::Loops(_) = mode.measure.stop {
        return Err(BenchError::Options(
            "--compare-cyclictest alternates slices of time: give --duration, not --loops".into(),
        ));
    }
    if mode.slice.as_secs() == 0 || mode.slice.subsec_nanos() != 0 {
        return Err(BenchError::Options(
            "--slice must be whole seconds (cyclictest's -D)".into(),
        ));
    }
    match cyclictest::find() {
        Some(exe) => Ok(Some(exe)),
        None => Err(BenchError::Tool {
            tool: "cyclictest",
            reason: "not found on PATH (Debian: apt install rt-tests)".into(),
        }),
    }
}

fn merged(hists: &[Histogram<u64>]) -> Result<Histogram<u64>, BenchError> {
    let mut all = new_hist()?;
    for h in hists {
        merge(&mut all, h)?;
    }
    Ok(all)
}

/// `h` with every value truncated to whole microseconds (cyclictest's resolution).
pub fn truncated_to_us(h: &Histogram<u64>) -> Result<Histogram<u64>, BenchError> {
    let mut t = new_hist()?;
    for v in h.iter_recorded() {
        t.saturating_record_n(v.value_iterated_to() / 1000 * 1000, v.count_at_value());
    }
    Ok(t)
}

/// Cadence over the tool, per column.
pub fn ratios(ours: &Histogram<u64>, theirs: &Histogram<u64>) -> Vec<Ratio> {
    let (a, b) = (Percentiles::of(ours).columns(), Percentiles::of(theirs).columns());
    COLUMNS
        .iter()
        .zip(a.iter().zip(b.iter()))
        .map(|(name, (&x, &y))| Ratio {
            percentile: (*name).into(),
            cadence_us: x / 1e3,
            tool_us: y / 1e3,
            ratio: (y > 0.0).then(|| x / y),
        })
        .collect()
}

fn verdict(p: &Percentiles, budget_ns: Option<u64>) -> Option<String> {
    let b = budget_ns? as f64;
    let fmt = rt_core::hist::fmt_ns;
    Some(if (p.max_ns as f64) <= b {
        format!(
            "within the {} budget: max {} ({:.1} % of it), p99.99 {}",
            fmt(b),
            fmt(p.max_ns as f64),
            p.max_ns as f64 / b * 100.0,
            fmt(p.p99_99_ns as f64)
        )
    } else {
        format!(
            "OVER the {} budget: max {}, p99.99 {}",
            fmt(b),
            fmt(p.max_ns as f64),
            fmt(p.p99_99_ns as f64)
        )
    })
}

fn settings(r: &mut Report, mode: &WakeupMode) {
    let m = &mode.measure;
    r.set("cpus", m.cpus.clone());
    r.set("priority", m.priority);
    r.set("interval_us", m.interval.as_micros() as u64);
    match m.stop {
        Stop::Duration(d) => r.set("duration_s", d.as_secs_f64()),
        Stop::Loops(n) => r.set("loops", n),
    }
    r.set("busy_wait", m.wait == Wait::Busy);
    r.set("lock_memory", mode.lock_memory);
    r.set("compare_cyclictest", mode.compare_cyclictest);
    if mode.compare_cyclictest {
        r.set("slice_s", mode.slice.as_secs());
    }
}

fn describe(mode: &WakeupMode) -> String {
    let m = &mode.measure;
    let cpus: Vec<String> = m.cpus.iter().map(|c| c.to_string()).collect();
    let sched = m
        .priority
        .map_or("SCHED_OTHER".to_string(), |p| format!("SCHED_FIFO {p}"));
    let stop = match m.stop {
        Stop::Duration(d) => format!("{} s", d.as_secs_f64()),
        Stop::Loops(n) => format!("{n} loops"),
    };
    let wait = match m.wait {
        Wait::Sleep => "clock_nanosleep(TIMER_ABSTIME)",
        Wait::Busy => "busy-wait",
    };
    let mut s = format!(
        "wakeup: {} thread(s) on CPU {}, {sched}, interval {} µs, {stop}, {wait}",
        m.cpus.len(),
        cpus.join(","),
        m.interval.as_micros()
    );
    if mode.compare_cyclictest {
        s.push_str(&format!(
            ", alternating {} s slices with cyclictest",
            mode.slice.as_secs()
        ));
    }
    s
}

fn title(mode: &WakeupMode, common: &Common) -> String {
    let m = &mode.measure;
    let load = common
        .load
        .map_or(String::new(), |l| format!(", --load {}", l.name()));
    format!(
        "wake-up latency, interval {} µs, {}{load}",
        m.interval.as_micros(),
        m.priority
            .map_or("SCHED_OTHER".to_string(), |p| format!("SCHED_FIFO {p}"))
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn truncation_and_ratios() {
        let mut h = new_hist().unwrap();
        h.record(5_700).unwrap();
        h.record(12_300).unwrap();
        let t = truncated_to_us(&h).unwrap();
        assert_eq!((t.min(), t.len()), (5_000, 2));
        let r = ratios(&t, &t);
        assert_eq!(r.len(), COLUMNS.len());
        assert!(r.iter().all(|x| x.ratio == Some(1.0)), "{r:?}");
        let empty = new_hist().unwrap();
        assert!(ratios(&t, &empty).iter().all(|x| x.ratio.is_none()));
    }

    #[test]
    fn compare_refuses_busy_and_loops() {
        let mut mode = WakeupMode {
            measure: WakeupOptions {
                wait: Wait::Busy,
                ..WakeupOptions::default()
            },
            lock_memory: false,
            compare_cyclictest: true,
            slice: Duration::from_secs(1),
        };
        assert!(check_compare(&mode).unwrap_err().to_string().contains("busy"));
        mode.measure.wait = Wait::Sleep;
        mode.measure.stop = Stop::Loops(10);
        assert!(check_compare(&mode)
            .unwrap_err()
            .to_string()
            .contains("--duration"));
        mode.measure.stop = Stop::Duration(Duration::from_secs(1));
        mode.slice = Duration::from_millis(1500);
        assert!(check_compare(&mode)
            .unwrap_err()
            .to_string()
            .contains("whole seconds"));
    }

    #[test]
    fn verdict_against_the_budget() {
        let p = Percentiles {
            max_ns: 5_000_000,
            p99_99_ns: 1_000_000,
            ..Percentiles::default()
        };
        let v = verdict(&p, Some(HOMING)).unwrap();
        assert!(
            v.starts_with("within the 25.00 ms budget: max 5.00 ms (20.0 %"),
            "{v}"
        );
        let over = Percentiles {
            max_ns: 30_000_000,
            ..p
        };
        assert!(verdict(&over, Some(HOMING)).unwrap().starts_with("OVER"));
        assert_eq!(verdict(&p, None), None);
    }

    const HOMING: u64 = super::super::HOMING_BUDGET_NS;
}
