//! What `cadence print` shows while a live print runs: on a terminal one line redrawn in place
//! (indicatif); otherwise (stderr redirected, or `--log-file`) a plain line every
//! [`PLAIN_PERIOD`]. Both say how far the file is read, the print time done and an estimate of
//! what is left, the planned Z, and a health mark: the smallest lead of a step message so far
//! against the 100 ms the MCUs need, and the MCU links' state:
//!
//! `████▌      42 % · line 27,015 · 26 m 40 s printed, ~36 m 50 s left · layer 65 · Z 12.90 · ✓ lead ≥ 1353 ms`
//!
//! The estimate of the remaining print time extrapolates the planner's own print time: the
//! moves planned so far took `planned` seconds of print time for the share of the file read,
//! so the whole file takes about `planned / share`.

use std::io::IsTerminal;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use cadence::job::Progress;
use cadence::summary::human_duration;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

use cadence::gcode_source::ReadPosition;

/// On a time-scaled simulator, a lead below this many times the 100 ms minimum means the
/// simulation is falling behind (the buffer of planned motion is nearly spent).
const FALLING_BEHIND: f64 = 1.5;

/// Period of the plain progress lines.
pub const PLAIN_PERIOD: Duration = Duration::from_secs(10);

/// The progress display of one print.
pub struct Display {
    pos: Arc<ReadPosition>,
    file_bytes: u64,
    out: Out,
    /// The falling-behind warning was printed.
    warned: std::sync::atomic::AtomicBool,
}

enum Out {
    Bar(ProgressBar),
    Plain(Mutex<Option<Instant>>),
}

/// What one progress report says, in words.
#[derive(Debug, Clone, PartialEq)]
pub struct Line {
    pub percent: f64,
    pub line: u64,
    pub text: String,
    /// The health mark is not "ok".
    pub warn: bool,
}

impl Display {
    /// A bar on a terminal (unless `plain`), plain lines otherwise.
    pub fn new(pos: Arc<ReadPosition>, file_bytes: u64, plain: bool) -> Display {
        let out = if !plain && std::io::stderr().is_terminal() {
            let bar = ProgressBar::with_draw_target(Some(1000), ProgressDrawTarget::stderr_with_hz(4));
            let style = ProgressStyle::with_template("{bar:16.cyan/blue} {wide_msg}")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("█▌ ");
            bar.set_style(style);
            Out::Bar(bar)
        } else {
            Out::Plain(Mutex::new(None))
        };
        Display {
            pos,
            file_bytes,
            out,
            warned: std::sync::atomic::AtomicBool::new(false),
        }
    }

    /// Shows `p`.
    pub fn update(&self, p: &Progress) {
        let line = describe(
            p,
            self.pos.bytes.load(Ordering::Relaxed),
            self.file_bytes,
            self.pos.lines.load(Ordering::Relaxed),
            self.pos.layers.load(Ordering::Relaxed),
        );
        if let Some(text) = falling_behind(p) {
            if !self.warned.swap(true, Ordering::Relaxed) {
                match &self.out {
                    Out::Bar(bar) => bar.println(&text),
                    Out::Plain(_) => eprintln!("{text}"),
                }
            }
        }
        match &self.out {
            Out::Bar(bar) => {
                bar.set_position((line.percent * 10.0) as u64);
                bar.set_message(line.text);
            }
            Out::Plain(last) => {
                let Ok(mut last) = last.lock() else { return };
                let due = last.is_none_or(|t| t.elapsed() >= PLAIN_PERIOD);
                if due && p.planned > 0.0 {
                    *last = Some(Instant::now());
                    eprintln!("cadence: progress: {}", line.text);
                }
            }
        }
    }

    /// Removes the bar (before the summary or an error is printed).
    pub fn finish(&self) {
        if let Out::Bar(bar) = &self.out {
            bar.finish_and_clear();
        }
    }
}

/// The warning, once, that a time-scaled simulation is falling behind (its lead is nearly spent:
/// the simulated MCU will shut down with `Timer too close` if it goes on), with a lower scale to
/// try; `None` while it keeps up.
pub fn falling_behind(p: &Progress) -> Option<String> {
    let ms = p.min_lead_ms?;
    if p.time_scale <= 1.0 || ms >= FALLING_BEHIND * cadence::MIN_LEAD_S * 1e3 {
        return None;
    }
    let lower = (p.time_scale / 2.5).floor().max(1.0);
    Some(format!(
        "cadence: warning: the simulation is falling behind at --time-scale {}: step commands reached \
         the simulated MCU only {ms:.0} ms ahead (it needs 100 ms; the host or the simulator did not \
         get the CPU in time, load average {}); if it stops with 'Timer too close', try --time-scale {lower}",
        p.time_scale,
        load_average()
    ))
}

/// The 1-minute load average, as /proc says it (`?` where it cannot be read).
pub fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|l| l.split_whitespace().next().map(str::to_string))
        .unwrap_or_else(|| "?".to_string())
}

/// The words of one progress report: `bytes` of `file_bytes` read, `lines` lines, `layers`
/// slicer layers begun (not shown when the file has no layer comments).
pub fn describe(p: &Progress, bytes: u64, file_bytes: u64, lines: u64, layers: u64) -> Line {
    let share = if file_bytes == 0 {
        1.0
    } else {
        (bytes as f64 / file_bytes as f64).clamp(0.0, 1.0)
    };
    let percent = share * 100.0;
    let mut text = format!("{percent:.0} % · line {lines}");
    if p.planned > 0.0 && share > 0.0 {
        let total = p.planned / share;
        let left = (total - p.print_time).max(0.0);
        text.push_str(&format!(
            " · {} printed, ~{} left",
            human_duration(p.print_time),
            human_duration(left)
        ));
    } else {
        text.push_str(" · starting");
    }
    if layers > 0 {
        text.push_str(&format!(" · layer {layers}"));
    }
    text.push_str(&format!(" · Z {:.2}", p.position[2]));
    let down: Vec<String> = p
        .mcus
        .iter()
        .filter_map(|(name, why)| why.as_ref().map(|w| format!("mcu '{name}' down: {w}")))
        .collect();
    let (mark, warn) = if !down.is_empty() {
        (format!("✗ {}", down.join("; ")), true)
    } else {
        match p.min_lead_ms {
            Some(ms) if ms < cadence::MIN_LEAD_S * 1e3 => {
                (format!("⚠ lead only {ms:.0} ms (< 100 ms)"), true)
            }
            Some(ms) if p.time_scale > 1.0 && ms < FALLING_BEHIND * cadence::MIN_LEAD_S * 1e3 => (
                format!("⚠ falling behind at {}×: lead {ms:.0} ms", p.time_scale),
                true,
            ),
            Some(ms) => (format!("✓ lead ≥ {ms:.0} ms"), false),
            None => ("✓ link up".to_string(), false),
        }
    };
    text.push_str(" · ");
    text.push_str(&mark);
    Line {
        percent,
        line: lines,
        text,
        warn,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn progress(print_time: f64, planned: f64, lead: Option<f64>) -> Progress {
        Progress {
            print_time,
            planned,
            position: [0.0, 0.0, 1.2, 0.0],
            min_lead_ms: lead,
            mcus: vec![("mcu".to_string(), None)],
            time_scale: 1.0,
        }
    }

    #[test]
    fn estimates_what_is_left_from_the_share_planned() {
        // A quarter of the file planned 100 s of print time: about 400 s in all, 330 s left.
        let l = describe(&progress(70.0, 100.0, Some(180.0)), 250, 1000, 12, 6);
        assert_eq!(l.percent, 25.0);
        assert_eq!(l.line, 12);
        assert_eq!(
            l.text,
            "25 % · line 12 · 1 m 10 s printed, ~5 m 30 s left · layer 6 · Z 1.20 · ✓ lead ≥ 180 ms"
        );
        assert!(!l.warn);
    }

    #[test]
    fn health_mark_warns_on_low_lead_and_a_dead_link() {
        let l = describe(&progress(1.0, 2.0, Some(60.0)), 1, 10, 1, 0);
        assert!(l.warn && l.text.contains("lead only 60 ms"), "{}", l.text);
        let mut p = progress(1.0, 2.0, Some(300.0));
        p.mcus[0].1 = Some("Timer too close".to_string());
        let l = describe(&p, 1, 10, 1, 0);
        assert!(
            l.warn && l.text.contains("mcu 'mcu' down: Timer too close"),
            "{}",
            l.text
        );
        let l = describe(&progress(0.0, 0.0, None), 0, 10, 0, 0);
        assert!(l.text.contains("starting") && !l.warn, "{}", l.text);
    }

    #[test]
    fn a_time_scaled_simulation_running_out_of_lead_is_named() {
        let mut p = progress(1.0, 2.0, Some(120.0));
        assert!(!describe(&p, 1, 10, 1, 0).warn, "at 1x 120 ms is fine");
        assert_eq!(falling_behind(&p), None);
        p.time_scale = 50.0;
        let l = describe(&p, 1, 10, 1, 0);
        assert!(
            l.warn && l.text.ends_with("⚠ falling behind at 50×: lead 120 ms"),
            "{}",
            l.text
        );
        let w = falling_behind(&p).unwrap();
        assert!(
            w.contains("falling behind at --time-scale 50: step commands reached the simulated MCU only 120 ms ahead")
                && w.ends_with("try --time-scale 20"),
            "{w}"
        );
        p.min_lead_ms = Some(281.0);
        assert_eq!(falling_behind(&p), None, "the usual lead at 50×");
    }
}
