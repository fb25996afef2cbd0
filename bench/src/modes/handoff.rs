//! `cadence bench handoff`: hand-off latency of each transport ([`crate::handoff`]), one series
//! per transport, with the common options (JSON, interval log, plot, load).

use std::io::Write;
use std::time::Instant;

use hdrhistogram::Histogram;

use crate::error::BenchError;
use crate::handoff::{run_one, ChildCommand, HandoffOpts, TRANSPORTS};
use crate::plot::PlotSeries;
use crate::report::Report;
use crate::run::{Common, Session};

/// Runs every transport (the `proc-` ones only with `child`) and reports them.
pub fn run(
    o: &HandoffOpts,
    child: Option<&ChildCommand>,
    common: &Common,
    out: &mut dyn Write,
) -> Result<Report, BenchError> {
    let names: Vec<&str> = TRANSPORTS
        .iter()
        .copied()
        .filter(|t| child.is_some() || !t.starts_with("proc-"))
        .collect();
    // About gap per sample per transport, plus set-up.
    let expected = o.gap.saturating_mul(u32::try_from(o.samples).unwrap_or(u32::MAX)) * names.len() as u32;
    let describe = format!(
        "handoff: {} samples per transport, gap {} µs, producer CPU {}, consumer CPU {}, {}",
        o.samples,
        o.gap.as_micros(),
        o.cores.0,
        o.cores.1,
        o.fifo
            .map_or("SCHED_OTHER".to_string(), |p| format!("SCHED_FIFO {p}"))
    );
    let mut s = Session::start("handoff", &describe, common, None, expected, out)?;
    s.report.set("samples", o.samples);
    s.report.set("gap_us", o.gap.as_micros() as u64);
    s.report.set("cores", vec![o.cores.0, o.cores.1]);
    s.report.set("fifo", o.fifo);
    s.report.set("process", child.is_some());
    let started = Instant::now();
    let mut done: Vec<(&str, Histogram<u64>)> = Vec::new();
    for name in names {
        let t0 = crate::wakeup::mono_ns()?;
        match run_one(name, o, child) {
            Ok(h) => {
                s.interval(name, t0, crate::wakeup::mono_ns()?, &h)?;
                s.series(name, &h);
                done.push((name, h));
            }
            Err(e) => s.report.notes.push(format!("{name} failed: {e}")),
        }
        s.progress(started.elapsed());
    }
    for line in rt_core::os::rt_report() {
        s.report.notes.push(line);
    }
    if done.is_empty() {
        return Err(BenchError::Thread(format!(
            "every transport failed: {}",
            s.report.notes.join("; ")
        )));
    }
    let plot: Vec<PlotSeries<'_>> = done
        .iter()
        .map(|(name, hist)| PlotSeries { name, hist })
        .collect();
    let title = format!(
        "hand-off latency, {} samples, gap {} µs",
        o.samples,
        o.gap.as_micros()
    );
    s.finish(&title, &plot, out)
}
