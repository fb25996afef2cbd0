//! What every `cadence bench` mode shares: the common options ([`Common`]: `--json`,
//! `--hlog`, `--plot`, `--load`, budget, progress) and a [`Session`] that, for one run, holds
//! the report being filled, the interval log being written, the stressor and the progress
//! bar, and at the end stops the load, draws the plot and prints the text or the JSON.

use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::time::{Duration, Instant, SystemTime};

use hdrhistogram::Histogram;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

use crate::error::BenchError;
use crate::hlog::Hlog;
use crate::host::Host;
use crate::load::{Load, LoadKind, LoadTool};
use crate::plot::{render, PlotSeries};
use crate::report::{Report, SeriesReport};
use crate::stats::Percentiles;

/// Options common to every mode.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Common {
    /// Print the report as JSON ([`crate::report`]) instead of text.
    pub json: bool,
    /// Write an HdrHistogram interval log here.
    pub hlog: Option<PathBuf>,
    /// Draw the charts here (`.svg` or `.png`).
    pub plot: Option<PathBuf>,
    /// Run a stressor beside the measurement.
    pub load: Option<LoadKind>,
    pub load_tool: LoadTool,
    /// The budget drawn in plots and judged in the verdict: `None` takes the mode's default,
    /// `Some(0)` none.
    pub budget_ns: Option<u64>,
    /// Show a progress bar on runs over a few seconds when stderr is a terminal.
    pub progress: bool,
    /// A saved `--json` report of the same mode to compare this run with (`baseline`).
    pub compare: Option<PathBuf>,
}

impl Default for Common {
    fn default() -> Self {
        Common {
            json: false,
            hlog: None,
            plot: None,
            load: None,
            load_tool: LoadTool::Auto,
            budget_ns: None,
            progress: true,
            compare: None,
        }
    }
}

/// Runs shorter than this get no progress bar.
const PROGRESS_FROM: Duration = Duration::from_secs(3);

/// One run of a mode: report, interval log, stressor, progress bar.
#[derive(Debug)]
pub struct Session {
    pub report: Report,
    common: Common,
    hlog: Option<Hlog>,
    base_mono_ns: u64,
    started: Instant,
    load: Option<Load>,
    progress: Option<ProgressBar>,
    /// The saved report of `--compare`.
    saved: Option<(PathBuf, Report)>,
}

impl Session {
    /// Starts a run of `mode` expected to take about `expected`: reads the host, opens the
    /// interval log, writes the header and `describe` (the run's settings in words) to `out`
    /// (text mode), then starts the load and the progress bar (nothing is written to `out`
    /// while the bar shows). `default_budget_ns` is the mode's budget when the options give
    /// none.
    pub fn start(
        mode: &str,
        describe: &str,
        common: &Common,
        default_budget_ns: Option<u64>,
        expected: Duration,
        out: &mut dyn Write,
    ) -> Result<Session, BenchError> {
        let mut report = Report::new(mode, Host::read());
        report.budget_ns = match common.budget_ns {
            Some(0) => None,
            Some(b) => Some(b),
            None => default_budget_ns,
        };
        if let Some(p) = &common.plot {
            crate::plot::check_path(p)?;
        }
        // Read before measuring, so a bad file fails at once.
        let saved = match &common.compare {
            Some(p) => {
                let r = Report::read(p)?;
                if r.mode != mode {
                    return Err(BenchError::Options(format!(
                        "--compare {}: a report of bench {}, not of bench {mode}",
                        p.display(),
                        r.mode
                    )));
                }
                Some((p.clone(), r))
            }
            None => None,
        };
        let hlog = match &common.hlog {
            Some(p) => Some(Hlog::create(
                p,
                &format!("cadence bench {mode}"),
                SystemTime::now(),
            )?),
            None => None,
        };
        let base_mono_ns = crate::wakeup::mono_ns()?;
        if !common.json {
            for line in report.host.header() {
                writeln!(out, "{line}").map_err(stdout_err)?;
            }
            writeln!(out, "{describe}").map_err(stdout_err)?;
            out.flush().map_err(stdout_err)?;
        }
        let load = match common.load {
            Some(kind) => {
                let load = Load::start(kind, common.load_tool, expected)?;
                report.load = Some(load.info());
                if !common.json {
                    let info = load.info();
                    writeln!(out, "load: {} ({})", info.kind, info.tool).map_err(stdout_err)?;
                    out.flush().map_err(stdout_err)?;
                }
                Some(load)
            }
            None => None,
        };
        let progress = (common.progress && expected >= PROGRESS_FROM && std::io::stderr().is_terminal())
            .then(|| {
                let bar = ProgressBar::with_draw_target(
                    Some(expected.as_millis() as u64),
                    ProgressDrawTarget::stderr(),
                );
                if let Ok(style) =
                    ProgressStyle::with_template("{msg} [{bar:40}] {elapsed}/{duration} ({eta} left)")
                {
                    bar.set_style(style.progress_chars("=> "));
                }
                bar.set_message(format!("bench {mode}"));
                bar
            });
        Ok(Session {
            report,
            common: common.clone(),
            hlog,
            base_mono_ns,
            started: Instant::now(),
            load,
            progress,
            saved,
        })
    }

    /// Writes one interval (CLOCK_MONOTONIC ns bounds) to the interval log, if any.
    pub fn interval(
        &mut self,
        tag: &str,
        start_ns: u64,
        end_ns: u64,
        hist: &Histogram<u64>,
    ) -> Result<(), BenchError> {
        if let Some(log) = &mut self.hlog {
            let start = Duration::from_nanos(start_ns.saturating_sub(self.base_mono_ns));
            log.write(
                tag,
                hist,
                start,
                Duration::from_nanos(end_ns.saturating_sub(start_ns)),
            )?;
        }
        Ok(())
    }

    /// Moves the progress bar to `done` of the expected time.
    pub fn progress(&self, done: Duration) {
        if let Some(bar) = &self.progress {
            bar.set_position(done.as_millis() as u64);
        }
    }

    /// Sets the report's `baseline` (with `--compare`) from its figures and series now, for a
    /// mode that removes figures from the report before [`Session::finish`].
    pub fn take_baseline(&mut self) {
        if let Some((path, saved)) = self.saved.take() {
            self.report.baseline = Some(crate::report::Baseline {
                file: path.display().to_string(),
                ratios: self.report.ratios_to(&saved),
            });
        }
    }

    /// Adds a latency series to the report.
    pub fn series(&mut self, name: &str, hist: &Histogram<u64>) {
        self.report.series.push(series(name, hist));
    }

    /// Ends the run: stops the load and the bar, closes the log, draws `plot` (title and series)
    /// when asked, and writes the report (text or JSON) to `out`.
    pub fn finish(
        mut self,
        title: &str,
        plot: &[PlotSeries<'_>],
        out: &mut dyn Write,
    ) -> Result<Report, BenchError> {
        self.report.wall_s = self.started.elapsed().as_secs_f64();
        if let Some(load) = self.load.take() {
            self.report.load = Some(load.stop());
        }
        if let Some(bar) = self.progress.take() {
            bar.finish_and_clear();
        }
        if let Some(log) = self.hlog.take() {
            log.finish()?;
        }
        if let Some(path) = &self.common.plot {
            render(path, title, plot, self.report.budget_ns)?;
        }
        self.take_baseline();
        if self.common.json {
            let text = self
                .report
                .to_json()
                .map_err(|e| BenchError::Histogram(e.to_string()))?;
            writeln!(out, "{text}").map_err(stdout_err)?;
        } else {
            for line in self.report.text_body() {
                writeln!(out, "{line}").map_err(stdout_err)?;
            }
            if let Some(p) = &self.common.hlog {
                writeln!(out, "interval log: {}", p.display()).map_err(stdout_err)?;
            }
            if let Some(p) = &self.common.plot {
                writeln!(out, "plot: {}", p.display()).map_err(stdout_err)?;
            }
        }
        Ok(self.report)
    }
}

/// A report series of `hist` (ns).
pub fn series(name: &str, hist: &Histogram<u64>) -> SeriesReport {
    SeriesReport {
        name: name.into(),
        unit: "ns".into(),
        percentiles: Percentiles::of(hist),
    }
}

fn stdout_err(e: std::io::Error) -> BenchError {
    BenchError::file("(standard output)", e)
}
