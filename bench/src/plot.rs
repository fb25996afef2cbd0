//! `--plot FILE.svg|FILE.png`: two charts of the run's latency series, drawn with plotters.
//!
//! - Top: the latency histogram, log-scaled on both axes (logarithmic bins 12 % wide, so a
//!   decade holds the same number of bins at any latency).
//! - Bottom: the percentile distribution as HdrHistogram's plotter draws it: the x axis is
//!   `1/(1−q)` on a log scale, labelled 90 %, 99 %, 99.9 % ..., the y axis latency (log).
//!
//! The budget (when the mode has one) is a red line on both. Text is laid out with a TrueType
//! font from the system (DejaVu Sans, Debian's fonts-dejavu-core, or whatever `fc-match`
//! names), registered once for plotters' `sans-serif` family.

use std::path::Path;
use std::sync::OnceLock;

use hdrhistogram::Histogram;
use plotters::coord::Shift;
use plotters::prelude::*;

use crate::error::BenchError;

/// One line on the charts.
#[derive(Debug, Clone, Copy)]
pub struct PlotSeries<'a> {
    pub name: &'a str,
    pub hist: &'a Histogram<u64>,
}

/// Width of a logarithmic histogram bin (each is this many times the previous one's end).
const BIN_RATIO: f64 = 1.12;
const SIZE: (u32, u32) = (1100, 1000);
/// The histogram's count axis starts here (below 1 sample: where empty bins are drawn).
const FLOOR: f64 = 0.8;
/// Series colours (no red: red is the budget).
const COLOURS: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(23, 190, 207),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
];

fn colour(i: usize) -> RGBAColor {
    COLOURS[i % COLOURS.len()].to_rgba()
}

/// An axis label in µs: "50 µs", "1.5 ms", "20 ms".
fn axis_us(v: f64) -> String {
    let trim = |x: f64| {
        let s = format!("{x:.2}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    };
    if v >= 1000.0 {
        format!("{} ms", trim(v / 1000.0))
    } else {
        format!("{} µs", trim(v))
    }
}
const FONT_PATHS: [&str; 4] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
];

fn font_file() -> Option<Vec<u8>> {
    for p in FONT_PATHS {
        if let Ok(b) = std::fs::read(p) {
            return Some(b);
        }
    }
    let out = std::process::Command::new("fc-match")
        .args(["-f", "%{file}", "sans-serif:style=Regular"])
        .output()
        .ok()?;
    std::fs::read(String::from_utf8_lossy(&out.stdout).trim()).ok()
}

/// Registers the font once per process.
fn ensure_font() -> Result<(), String> {
    static DONE: OnceLock<Result<(), String>> = OnceLock::new();
    DONE.get_or_init(|| {
        let bytes = font_file().ok_or_else(|| {
            format!(
                "no TrueType font found (tried {} and fc-match); install fonts-dejavu-core",
                FONT_PATHS.join(", ")
            )
        })?;
        // plotters keeps fonts for the life of the process; this is done once.
        let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
        plotters::style::register_font("sans-serif", FontStyle::Normal, bytes)
            .map_err(|_| "the system font could not be parsed".to_string())
    })
    .clone()
}

/// Checks before a run that `path` can be drawn: a `.svg` or `.png` name and a font.
pub fn check_path(path: &Path) -> Result<(), BenchError> {
    let err = |reason: String| BenchError::Plot {
        path: path.to_path_buf(),
        reason,
    };
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    if ext != "svg" && ext != "png" {
        return Err(err("expected a file name ending in .svg or .png".into()));
    }
    ensure_font().map_err(err)
}

/// Draws both charts of `series` into `path` (`.svg` or `.png`) under `title`.
pub fn render(
    path: &Path,
    title: &str,
    series: &[PlotSeries<'_>],
    budget_ns: Option<u64>,
) -> Result<(), BenchError> {
    let err = |reason: String| BenchError::Plot {
        path: path.to_path_buf(),
        reason,
    };
    ensure_font().map_err(err)?;
    if series.iter().all(|s| s.hist.is_empty()) {
        return Err(err("no samples to plot".into()));
    }
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    match ext.as_str() {
        "svg" => draw(
            SVGBackend::new(path, SIZE).into_drawing_area(),
            title,
            series,
            budget_ns,
        )
        .map_err(err),
        "png" => draw(
            BitMapBackend::new(path, SIZE).into_drawing_area(),
            title,
            series,
            budget_ns,
        )
        .map_err(err),
        _ => Err(err("expected a file name ending in .svg or .png".into())),
    }
}

fn us(ns: u64) -> f64 {
    ns as f64 / 1e3
}

/// `1 − 1/x` as a percentage label: 1 → "0%", 10 → "90%", 1000 → "99.9%".
pub fn percentile_label(x: f64) -> String {
    let pct = (1.0 - 1.0 / x.max(1.0)) * 100.0;
    let s = format!("{pct:.6}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    format!("{s}%")
}

fn draw<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    title: &str,
    series: &[PlotSeries<'_>],
    budget_ns: Option<u64>,
) -> Result<(), String>
where
    DB::ErrorType: 'static,
{
    let e = |x: DrawingAreaErrorKind<DB::ErrorType>| x.to_string();
    root.fill(&WHITE).map_err(e)?;
    let root = root.titled(title, ("sans-serif", 22)).map_err(e)?;
    let (top, bottom) = root.split_vertically(SIZE.1 / 2 - 20);
    let present: Vec<&PlotSeries<'_>> = series.iter().filter(|s| !s.hist.is_empty()).collect();
    let lo_ns = present.iter().map(|s| s.hist.min()).min().unwrap_or(1).max(50);
    let hi_ns = present
        .iter()
        .map(|s| s.hist.max())
        .max()
        .unwrap_or(1)
        .max(budget_ns.unwrap_or(0))
        .max(lo_ns * 10);
    let (lo, hi) = (us(lo_ns) / 1.5, us(hi_ns) * 1.5);
    let budget = budget_ns.map(us);

    // Histogram: log bins; an empty bin is drawn on the axis (a log scale has no 0).
    let bins: Vec<Vec<(f64, f64)>> = present
        .iter()
        .map(|s| {
            s.hist
                .iter_log(1, BIN_RATIO)
                .map(|v| (us(v.value_iterated_to()), v.count_since_last_iteration() as f64))
                .filter(|&(x, _)| x >= lo && x <= hi)
                .map(|(x, n)| (x, n.max(FLOOR)))
                .collect()
        })
        .collect();
    let top_count = bins.iter().flatten().map(|p| p.1).fold(1.0, f64::max) * 2.0;
    let mut chart = ChartBuilder::on(&top)
        .caption("latency histogram", ("sans-serif", 18))
        .margin(12)
        .margin_right(40)
        .x_label_area_size(45)
        .y_label_area_size(70)
        .build_cartesian_2d((lo..hi).log_scale(), (FLOOR..top_count).log_scale())
        .map_err(e)?;
    chart
        .configure_mesh()
        .x_desc("latency")
        .y_desc("samples per bin (bins 12 % wide)")
        .y_label_formatter(&|y| format!("{y:.0}"))
        .x_label_formatter(&|x| axis_us(*x))
        .draw()
        .map_err(e)?;
    let names: Vec<&str> = present.iter().map(|s| s.name).collect();
    let budget_line = budget.map(|b| [(b, FLOOR), (b, top_count)]);
    draw_lines(
        &mut chart,
        &names,
        &bins,
        budget_line,
        SeriesLabelPosition::UpperRight,
    )
    .map_err(e)?;

    // Percentile distribution.
    let count = present.iter().map(|s| s.hist.len()).max().unwrap_or(1) as f64;
    let x_max = 10f64.powf(count.log10().ceil().max(1.0));
    let curves: Vec<Vec<(f64, f64)>> = present
        .iter()
        .map(|s| {
            s.hist
                .iter_quantiles(5)
                .map(|v| {
                    let q = v.quantile_iterated_to();
                    (
                        (1.0 / (1.0 - q).max(1.0 / x_max)).min(x_max),
                        us(v.value_iterated_to()),
                    )
                })
                .collect()
        })
        .collect();
    let mut chart = ChartBuilder::on(&bottom)
        .caption("percentile distribution", ("sans-serif", 18))
        .margin(12)
        .margin_right(40)
        .x_label_area_size(45)
        .y_label_area_size(70)
        .build_cartesian_2d((1.0..x_max).log_scale(), (lo..hi).log_scale())
        .map_err(e)?;
    chart
        .configure_mesh()
        .x_desc("percentile")
        .y_desc("latency")
        .y_label_formatter(&|y| axis_us(*y))
        .x_label_formatter(&|x| percentile_label(*x))
        .draw()
        .map_err(e)?;
    let budget_line = budget.map(|b| [(1.0, b), (x_max, b)]);
    draw_lines(
        &mut chart,
        &names,
        &curves,
        budget_line,
        SeriesLabelPosition::UpperLeft,
    )
    .map_err(e)?;
    root.present().map_err(e)
}

/// A log-log chart's lines: one per series (its colour and name in the legend), the budget as a
/// red line through `budget` (its two ends; its value in µs is the one that is not the same at
/// both ends), and the legend box at `legend`.
fn draw_lines<'a, DB: DrawingBackend + 'a>(
    chart: &mut ChartContext<'a, DB, Cartesian2d<LogCoord<f64>, LogCoord<f64>>>,
    names: &[&str],
    curves: &[Vec<(f64, f64)>],
    budget: Option<[(f64, f64); 2]>,
    legend: SeriesLabelPosition,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>>
where
    DB::ErrorType: 'static,
{
    for (i, (name, pts)) in names.iter().zip(curves).enumerate() {
        let color = colour(i);
        chart
            .draw_series(LineSeries::new(pts.iter().copied(), color.stroke_width(2)))?
            .label(*name)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
    }
    if let Some(ends) = budget {
        // The budget line is vertical on the histogram (x = budget) and horizontal on the
        // percentile chart (y = budget): its value is the coordinate both ends share.
        let value = if ends[0].0 == ends[1].0 {
            ends[0].0
        } else {
            ends[0].1
        };
        chart
            .draw_series(LineSeries::new(ends, RED.stroke_width(2)))?
            .label(format!("budget {}", rt_core::hist::fmt_ns(value * 1e3)))
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RED.stroke_width(2)));
    }
    chart
        .configure_series_labels()
        .position(legend)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stats::new_hist;

    fn sample(scale: u64) -> Histogram<u64> {
        let mut h = new_hist().unwrap();
        for i in 1..=2000u64 {
            h.record(scale * (1000 + (i * i) % 50_000)).unwrap();
        }
        h
    }

    #[test]
    fn axis_labels_in_time_units() {
        assert_eq!(axis_us(10.0), "10 µs");
        assert_eq!(axis_us(2.5), "2.5 µs");
        assert_eq!(axis_us(1000.0), "1 ms");
        assert_eq!(axis_us(25000.0), "25 ms");
    }

    #[test]
    fn labels_read_as_percentiles() {
        assert_eq!(percentile_label(1.0), "0%");
        assert_eq!(percentile_label(10.0), "90%");
        assert_eq!(percentile_label(1000.0), "99.9%");
        assert_eq!(percentile_label(1e5), "99.999%");
    }

    #[test]
    fn svg_has_axes_series_and_budget() {
        let dir = std::env::temp_dir().join(format!("cadence-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("p.svg");
        let (a, b) = (sample(1), sample(3));
        let series = [
            PlotSeries {
                name: "cpu0",
                hist: &a,
            },
            PlotSeries {
                name: "cpu1",
                hist: &b,
            },
        ];
        render(&path, "wakeup test", &series, Some(25_000_000)).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        let doc = roxmltree::Document::parse(&text).unwrap();
        assert_eq!(doc.root_element().tag_name().name(), "svg");
        let texts: Vec<String> = doc
            .descendants()
            .filter(|n| n.has_tag_name("text"))
            .filter_map(|n| n.text().map(str::to_string))
            .collect();
        for want in [
            "latency",
            "percentile",
            "1 ms",
            "latency histogram",
            "percentile distribution",
            "cpu0",
            "cpu1",
            "budget 25.00 ms",
            "99.9%",
        ] {
            assert!(
                texts.iter().any(|t| t.contains(want)),
                "{want:?} not in {texts:?}"
            );
        }
        let lines = doc.descendants().filter(|n| n.has_tag_name("polyline")).count();
        // Two series and the budget on each chart.
        assert!(lines >= 6, "{lines} polylines");
        let png = dir.join("p.png");
        render(&png, "wakeup test", &series, None).unwrap();
        assert!(std::fs::read(&png).unwrap().starts_with(b"\x89PNG"));
        assert!(render(&dir.join("p.jpg"), "x", &series, None).is_err());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
