//! `cadence bench plan`: planner + step compression throughput ([`crate::plan`]) with the
//! common options. It measures throughput, not latency: its figures go to `figures` and it has
//! no histogram, so `--hlog` and `--plot` are refused. With an instruction command it also
//! counts the instructions of one whole planning process (every thread) under valgrind's
//! callgrind ([`crate::callgrind`]); without valgrind that figure is skipped with a note. With
//! another stream of the same file (`--compare STREAM`: Klipper's batch output), its step
//! commands ([`crate::stream`]) are printed beside this run's, stepper by stepper.

use std::io::Write;
use std::path::Path;
use std::time::Duration;

use sysconfig::printer::PrinterConfig;

use crate::error::BenchError;
use crate::handoff::ChildCommand;
use crate::plan::{plan_file, PlanOptions, PlanReport};
use crate::report::Report;
use crate::run::{Common, Session};
use crate::stream::{count_stream, StepperCounts, StreamCounts};

/// Another wire stream of the same G-code to print beside this run (`--compare STREAM`).
#[derive(Debug)]
pub struct Against<'a> {
    /// The stream file (read after the runs, so it does not count in their peak RSS).
    pub path: &'a Path,
    /// The dictionary it was encoded with.
    pub dict: &'a links::dict::Dictionary,
    /// The printer's steppers in the planner's order: name, and step pin in that dictionary
    /// (`None`: the stepper is not on the stream's MCU, or its pin is not in the dictionary).
    pub steppers: &'a [(String, Option<u32>)],
}

/// What a run adds besides planning.
#[derive(Debug, Default)]
pub struct Extras<'a> {
    /// A command that plans the same file once (e.g. `cadence bench plan FILE …`), whose
    /// instructions callgrind counts.
    pub instructions: Option<&'a ChildCommand>,
    /// A stream to compare with.
    pub against: Option<Against<'a>>,
}

/// Plans `file` `runs` times (every run must give the same commands) and reports the figures;
/// with [`Extras`], also the instruction count of a planning process under callgrind, and
/// another stream's step commands beside this run's.
pub fn run(
    file: &Path,
    cfg: &PrinterConfig,
    opts: &PlanOptions,
    runs: u32,
    extras: &Extras<'_>,
    common: &Common,
    out: &mut dyn Write,
) -> Result<Report, BenchError> {
    if common.hlog.is_some() || common.plot.is_some() {
        return Err(BenchError::Options(
            "bench plan measures throughput and records no latency histogram: --hlog and --plot \
             apply to wakeup and handoff"
                .into(),
        ));
    }
    let describe = format!(
        "plan: {}, {} threads, {} run(s)",
        file.display(),
        opts.threads,
        runs
    );
    let mut s = Session::start(
        "plan",
        &describe,
        common,
        None,
        Duration::from_secs(u64::from(runs)),
        out,
    )?;
    s.report.set("file", file.display().to_string());
    s.report.set("threads", opts.threads as u64);
    s.report.set("max_error_us", opts.max_error_s * 1e6);
    s.report.set("clock_freq", opts.clock_freq);
    s.report.set("runs", runs);
    let first = plan_file(file, cfg, opts).map_err(BenchError::Options)?;
    let mut walls = vec![first.wall_s];
    for run in 2..=runs.max(1) {
        let again = plan_file(file, cfg, opts).map_err(BenchError::Options)?;
        if (again.queue_steps, again.wire_bytes) != (first.queue_steps, first.wire_bytes) {
            return Err(BenchError::Options(format!(
                "run {run} gave {} queue_step in {} wire bytes, the first {} in {}: planning is \
                 not deterministic",
                again.queue_steps, again.wire_bytes, first.queue_steps, first.wire_bytes
            )));
        }
        walls.push(again.wall_s);
        s.progress(Duration::from_secs(u64::from(run)));
    }
    figures(&mut s.report, &first);
    if !common.json {
        writeln!(out, "{first}").map_err(|e| BenchError::file("(standard output)", e))?;
    }
    if let Some(cmd) = extras.instructions {
        match crate::callgrind::find() {
            Some(valgrind) => {
                let n = crate::callgrind::count(&valgrind, &cmd.exe, &cmd.args)?;
                let f = &mut s.report.figures;
                f.insert("instructions".into(), n as f64);
                let per_step = n as f64 / first.steps.max(1) as f64;
                f.insert("instructions_per_step".into(), per_step);
                if !common.json {
                    writeln!(
                        out,
                        "instructions (callgrind, whole process, all threads): {n} ({:.2} G, {per_step:.0} per step)",
                        n as f64 / 1e9
                    )
                    .map_err(|e| BenchError::file("(standard output)", e))?;
                }
            }
            None => s.report.notes.push(
                "instructions skipped: valgrind is not installed (Debian: apt install valgrind)".into(),
            ),
        }
    }
    if let Some(a) = &extras.against {
        compare_stream(&mut s.report, &first, a, common.json, out)?;
    }
    if runs > 1 {
        let (min, median, max) = spread(&mut walls);
        s.report.figures.insert("wall_min_s".into(), min);
        s.report.figures.insert("wall_median_s".into(), median);
        s.report.figures.insert("wall_max_s".into(), max);
        s.report.verdict = Some(format!(
            "wall over {runs} runs: min {min:.4} s, median {median:.4} s, max {max:.4} s"
        ));
    }
    s.take_baseline();
    // The text line above already says every figure; keep the table for JSON only.
    if !common.json {
        s.report.figures.clear();
    }
    s.finish("", &[], out)
}

fn figures(r: &mut Report, p: &PlanReport) {
    let f = &mut r.figures;
    f.insert("lines".into(), p.lines as f64);
    f.insert("moves".into(), p.moves as f64);
    f.insert("steps".into(), p.steps as f64);
    f.insert("queue_steps".into(), p.queue_steps as f64);
    f.insert("commands".into(), p.commands as f64);
    f.insert("wire_bytes".into(), p.wire_bytes as f64);
    f.insert("wall_s".into(), p.wall_s);
    f.insert("moves_per_s".into(), p.moves_per_s());
    f.insert("steps_per_s".into(), p.steps_per_s());
    f.insert("peak_rss_bytes".into(), p.peak_rss_bytes as f64);
    f.insert("print_time_s".into(), p.print_time_s);
    f.insert("skipped_unknown".into(), p.skipped_unknown as f64);
}

/// Counts the stream of `against` and prints (or, with `json`, adds to the figures) its step
/// commands beside `mine`: totals, then each stepper, matched by step pin.
fn compare_stream(
    report: &mut Report,
    mine: &PlanReport,
    against: &Against<'_>,
    json: bool,
    out: &mut dyn Write,
) -> Result<(), BenchError> {
    let name = against.path.display().to_string();
    let data = std::fs::read(against.path).map_err(|e| BenchError::file(against.path, e))?;
    let theirs: StreamCounts = count_stream(&data, against.dict)
        .map_err(|e| BenchError::Options(format!("--compare {name}: {e}")))?;
    let total = theirs.total();
    let mine_total = StepperCounts::sum(&mine.per_stepper);
    let mut rows: Vec<(String, String, Option<u64>, Option<u64>)> = vec![
        (
            "queue_step".into(),
            "queue_steps".into(),
            Some(mine.queue_steps),
            Some(total.queue_steps),
        ),
        (
            "set_next_step_dir".into(),
            "set_dirs".into(),
            Some(mine_total.set_dirs),
            Some(total.set_dirs),
        ),
        (
            "reset_step_clock".into(),
            "resets".into(),
            Some(mine_total.resets),
            Some(total.resets),
        ),
        (
            "step command bytes".into(),
            "step_cmd_bytes".into(),
            Some(mine.wire_bytes),
            Some(theirs.step_cmd_bytes),
        ),
        (
            "steps".into(),
            "steps".into(),
            Some(mine.steps),
            Some(total.steps),
        ),
    ];
    let mut matched = Vec::new();
    for ((stepper, pin), m) in against.steppers.iter().zip(&mine.per_stepper) {
        let t = pin.and_then(|p| theirs.by_step_pin(p));
        if let Some(t) = t {
            matched.push(t.step_pin);
        }
        rows.push((
            format!("{stepper} steps"),
            format!("steps.{stepper}"),
            Some(m.steps),
            t.map(|t| t.steps),
        ));
        rows.push((
            format!("{stepper} queue_step"),
            format!("queue_steps.{stepper}"),
            Some(m.queue_steps),
            t.map(|t| t.queue_steps),
        ));
    }
    for (oid, t) in &theirs.steppers {
        if !matched.contains(&t.step_pin) {
            let label = match t.step_pin {
                Some(p) => format!("oid {oid} (step pin {p})"),
                None => format!("oid {oid}"),
            };
            rows.push((
                format!("{label} steps"),
                format!("steps.oid{oid}"),
                None,
                Some(t.steps),
            ));
        }
    }
    if json {
        let f = &mut report.figures;
        f.insert("compare_bytes".into(), theirs.bytes as f64);
        f.insert("compare_messages".into(), theirs.messages as f64);
        for (_, key, m, t) in &rows {
            if let Some(m) = m {
                f.insert(key.clone(), *m as f64);
            }
            if let Some(t) = t {
                f.insert(format!("compare_{key}"), *t as f64);
            }
        }
        return Ok(());
    }
    let w = |e| BenchError::file("(standard output)", e);
    writeln!(
        out,
        "against {name} ({} bytes, {} messages; its step commands alone pack into {} bytes):",
        theirs.bytes, theirs.messages, theirs.step_cmd_bytes
    )
    .map_err(w)?;
    writeln!(
        out,
        "  {:<28} {:>14} {:>14} {:>8}",
        "", "this run", "that stream", "ratio"
    )
    .map_err(w)?;
    let cell = |v: &Option<u64>| v.map_or_else(|| "-".to_string(), |v| v.to_string());
    for (label, _, m, t) in &rows {
        let ratio = match (m, t) {
            (Some(m), Some(t)) if *t > 0 => format!("{:.3}", *m as f64 / *t as f64),
            _ => "-".into(),
        };
        writeln!(out, "  {label:<28} {:>14} {:>14} {ratio:>8}", cell(m), cell(t)).map_err(w)?;
    }
    Ok(())
}

/// Min, median and max of `walls` (at least one).
pub fn spread(walls: &mut [f64]) -> (f64, f64, f64) {
    walls.sort_by(f64::total_cmp);
    let n = walls.len();
    let median = if n % 2 == 1 {
        walls[n / 2]
    } else {
        (walls[n / 2 - 1] + walls[n / 2]) / 2.0
    };
    (walls[0], median, walls[n - 1])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spread_gives_min_median_max() {
        assert_eq!(spread(&mut [0.3, 0.1, 0.2]), (0.1, 0.2, 0.3));
        assert_eq!(spread(&mut [0.4, 0.1, 0.2, 0.3]), (0.1, 0.25, 0.4));
    }
}
