//! What a live print reports at the end ([`Summary`]): lines, moves, print and wall time, each
//! stepper's position read back from its MCU against the host's, histogram and allocation
//! lines, and the MCU links' lead and traffic figures.
//!
//! [`Summary::report_lines`] shows it as a person reads it: a few sentences in plain words
//! first ([`Summary::plain_words`]), then the figures under `Details`, one [`Section`] each
//! (times in ms or µs, written so); a caller adds a block of its own by pushing a [`Section`]
//! before printing. [`Summary::to_json`] gives all of it machine-readably.

use std::path::PathBuf;

use crate::MIN_LEAD_S;

/// What a live print reports at the end.
#[derive(Debug)]
pub struct Summary {
    pub file: PathBuf,
    pub lines: u64,
    pub moves: u64,
    pub print_time: f64,
    pub wall: f64,
    pub queue_steps: u64,
    /// (stepper, steps sent, MCU position, host position, commanded axis position)
    pub rows: Vec<(String, u64, i64, i64, f64)>,
    pub clock_freq: f64,
    /// Each streamed MCU's CLOCK_FREQ (for its lead figures; others use `clock_freq`).
    pub mcu_freqs: Vec<(String, f64)>,
    /// Further report lines (histograms, allocation counts).
    pub extra: Vec<String>,
}

/// One titled block of the details.
#[derive(Debug, Clone, PartialEq)]
pub struct Section {
    pub title: String,
    pub lines: Vec<String>,
}

/// `seconds` as a person says it: `45 s`, `12 m 03 s`, `1 h 03 m`.
pub fn human_duration(seconds: f64) -> String {
    let s = if seconds.is_finite() {
        seconds.max(0.0).round() as u64
    } else {
        0
    };
    match s {
        0..60 => format!("{s} s"),
        60..3600 => format!("{} m {:02} s", s / 60, s % 60),
        _ => format!("{} h {:02} m", s / 3600, s % 3600 / 60),
    }
}

/// `n` with thousands separated by commas.
pub fn grouped(n: u64) -> String {
    let digits = n.to_string();
    let mut out = String::with_capacity(digits.len() + digits.len() / 3);
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    out
}

impl Summary {
    /// Smallest lead of a step message over all MCUs (ms), if any was sent.
    fn min_lead_ms(&self, all_stats: &[(String, links::mcu::LinkStats)]) -> Option<f64> {
        all_stats
            .iter()
            .filter_map(|(name, s)| {
                s.min_lead_margin_ticks
                    .map(|t| t as f64 / self.freq_of(name) * 1e3)
            })
            .reduce(f64::min)
    }

    fn freq_of(&self, mcu: &str) -> f64 {
        self.mcu_freqs
            .iter()
            .find(|(n, _)| n == mcu)
            .map_or(self.clock_freq, |&(_, f)| f)
    }

    /// The short block a printer owner reads: what was printed, whether motion kept safely
    /// ahead of the MCUs, whether the final positions match the MCUs' counts.
    pub fn plain_words(&self, all_stats: &[(String, links::mcu::LinkStats)]) -> Vec<String> {
        let mut out = vec![format!(
            "printed {} moves ({} lines of {}) in {} of print time ({} on the clock)",
            grouped(self.moves),
            grouped(self.lines),
            self.file.display(),
            human_duration(self.print_time),
            human_duration(self.wall)
        )];
        let safe = MIN_LEAD_S * 1e3;
        match self.min_lead_ms(all_stats) {
            Some(ms) if ms >= safe => out.push(format!(
                "all motion was sent at least {ms:.0} ms ahead of the MCUs (the safe minimum is {safe:.0} ms)"
            )),
            Some(ms) => out.push(format!(
                "some motion was sent only {ms:.0} ms ahead of the MCUs: below the safe minimum of {safe:.0} ms"
            )),
            None if !all_stats.is_empty() => out.push("no motion was sent".to_string()),
            None => {}
        }
        if !self.rows.is_empty() {
            let bad: Vec<&str> = self
                .rows
                .iter()
                .filter(|r| r.2 != r.3)
                .map(|r| r.0.as_str())
                .collect();
            let n = self.rows.len();
            if bad.is_empty() {
                out.push(format!(
                    "final position matches the MCU's step count on all {n} stepper{}",
                    if n == 1 { "" } else { "s" }
                ));
            } else {
                out.push(format!(
                    "final position DIFFERS from the MCU's step count on {}",
                    bad.join(", ")
                ));
            }
        }
        out
    }

    /// The details, one section each: steppers, latency and allocation figures, MCU links.
    pub fn sections(&self, all_stats: &[(String, links::mcu::LinkStats)]) -> Vec<Section> {
        let mut steppers = vec![format!(
            "{:<10} {:>10} {:>12} {:>12} {:>12}",
            "stepper", "steps", "mcu count", "host count", "position mm"
        )];
        for (name, steps, mcu_pos, host_pos, mm) in &self.rows {
            let flag = if mcu_pos == host_pos { "" } else { "  MISMATCH" };
            steppers.push(format!(
                "{name:<10} {steps:>10} {mcu_pos:>12} {host_pos:>12} {mm:>12.4}{flag}"
            ));
        }
        let mut out = vec![Section {
            title: "print".to_string(),
            lines: vec![format!(
                "lines {}, moves {}, queue_step commands {}, print time {:.3} s, wall time {:.3} s",
                self.lines, self.moves, self.queue_steps, self.print_time, self.wall
            )],
        }];
        if !self.rows.is_empty() {
            out.push(Section {
                title: "steppers (counts in steps from where each started)".to_string(),
                lines: steppers,
            });
        }
        if !self.extra.is_empty() {
            out.push(Section {
                title: "timing, memory and G-code side effects".to_string(),
                lines: self.extra.iter().map(|l| micro_sign(l)).collect(),
            });
        }
        let mut links = Vec::new();
        for (name, stats) in all_stats {
            let freq = self.freq_of(name);
            if let Some(margin) = stats.min_lead_margin_ticks {
                links.push(format!(
                    "mcu '{name}': min lead margin {:.1} ms over {} clocked messages (required {:.0} ms)",
                    margin as f64 / freq * 1e3,
                    stats.clocked_msgs,
                    MIN_LEAD_S * 1e3
                ));
            }
            let q = &stats.queue;
            links.push(format!(
                "mcu '{name}': {} bytes written, {} read, {} retransmitted, {} invalid; round trip \
                 (srtt) {:.3} ms, clock fit residual {:.1} µs",
                q.bytes_write,
                q.bytes_read,
                q.bytes_retransmit,
                q.bytes_invalid,
                q.srtt * 1e3,
                stats.clock_residual_us
            ));
        }
        if !links.is_empty() {
            out.push(Section {
                title: "MCU links".to_string(),
                lines: links,
            });
        }
        out
    }

    /// The report's lines, as `cadence print` shows them; `all_stats` are the MCU links'.
    pub fn report_lines(&self, all_stats: &[(String, links::mcu::LinkStats)]) -> Vec<String> {
        render(&self.plain_words(all_stats), &self.sections(all_stats))
    }

    /// The whole summary machine-readably (`cadence print --json`).
    pub fn to_json(&self, all_stats: &[(String, links::mcu::LinkStats)]) -> serde_json::Value {
        let steppers: Vec<serde_json::Value> = self
            .rows
            .iter()
            .map(|(name, steps, mcu, host, mm)| {
                serde_json::json!({
                    "name": name, "steps": steps, "mcu_count": mcu, "host_count": host,
                    "position_mm": mm, "matches": mcu == host,
                })
            })
            .collect();
        let links: Vec<serde_json::Value> = all_stats
            .iter()
            .map(|(name, s)| {
                let freq = self.freq_of(name);
                serde_json::json!({
                    "mcu": name,
                    "min_lead_ms": s.min_lead_margin_ticks.map(|t| t as f64 / freq * 1e3),
                    "clocked_messages": s.clocked_msgs,
                    "bytes_written": s.queue.bytes_write,
                    "bytes_read": s.queue.bytes_read,
                    "bytes_retransmitted": s.queue.bytes_retransmit,
                    "bytes_invalid": s.queue.bytes_invalid,
                    "srtt_ms": s.queue.srtt * 1e3,
                    "clock_residual_us": s.clock_residual_us,
                })
            })
            .collect();
        serde_json::json!({
            "file": self.file.display().to_string(),
            "lines": self.lines,
            "moves": self.moves,
            "queue_steps": self.queue_steps,
            "print_time_s": self.print_time,
            "wall_s": self.wall,
            "min_lead_ms": self.min_lead_ms(all_stats),
            "required_lead_ms": MIN_LEAD_S * 1e3,
            "steppers": steppers,
            "mcu_links": links,
            "summary": self.plain_words(all_stats),
            "details": self.extra,
        })
    }
}

/// `line` with microseconds written one way: a number followed by `us` becomes `µs`.
pub fn micro_sign(line: &str) -> String {
    let b = line.as_bytes();
    let mut out = String::with_capacity(line.len() + 8);
    let mut last = 0;
    let mut i = 0;
    while let Some(k) = line[i..].find("us") {
        let at = i + k;
        let before = line[..at].trim_end_matches(' ');
        let number_before = before.ends_with(|c: char| c.is_ascii_digit());
        let word_start = at == 0 || !b[at - 1].is_ascii_alphabetic();
        let word_end = b.get(at + 2).is_none_or(|c| !c.is_ascii_alphanumeric());
        if number_before && word_start && word_end {
            out.push_str(&line[last..at]);
            out.push_str("µs");
            last = at + 2;
        }
        i = at + 2;
    }
    out.push_str(&line[last..]);
    out
}

/// The plain sentences, then `Details:` with each section under its title.
pub fn render(plain: &[String], sections: &[Section]) -> Vec<String> {
    let mut out: Vec<String> = plain.iter().map(|l| format!("  {l}")).collect();
    out.push(String::new());
    out.push("Details:".to_string());
    for s in sections {
        out.push(format!("  {}:", s.title));
        out.extend(s.lines.iter().map(|l| format!("    {l}")));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn summary(rows: Vec<(String, u64, i64, i64, f64)>) -> Summary {
        Summary {
            file: PathBuf::from("benchy.gcode"),
            lines: 123_456,
            moves: 60_069,
            print_time: 3780.0,
            wall: 80.0,
            queue_steps: 9,
            rows,
            clock_freq: 50e6,
            mcu_freqs: vec![("mcu".to_string(), 50e6)],
            extra: vec!["hand-off planner→io: p50 12 us".to_string()],
        }
    }

    fn stats(min_lead_ms: f64) -> Vec<(String, links::mcu::LinkStats)> {
        let s = links::mcu::LinkStats {
            min_lead_margin_ticks: Some((min_lead_ms * 50e3) as i64),
            clocked_msgs: 10,
            ..Default::default()
        };
        vec![("mcu".to_string(), s)]
    }

    #[test]
    fn microseconds_are_written_one_way() {
        assert_eq!(micro_sign("stop 42..208 us after"), "stop 42..208 µs after");
        assert_eq!(micro_sign("12us, used by us"), "12µs, used by us");
        assert_eq!(micro_sign("max 3 µs"), "max 3 µs");
    }

    #[test]
    fn durations_and_numbers_read_as_words() {
        assert_eq!(human_duration(45.4), "45 s");
        assert_eq!(human_duration(723.0), "12 m 03 s");
        assert_eq!(human_duration(3780.0), "1 h 03 m");
        assert_eq!(human_duration(f64::NAN), "0 s");
        assert_eq!(grouped(60_069), "60,069");
        assert_eq!(grouped(999), "999");
        assert_eq!(grouped(1_000_000), "1,000,000");
    }

    #[test]
    fn plain_words_first_then_details() {
        let rows = vec![
            ("stepper_x".to_string(), 10, -960, -960, 10.0),
            ("stepper_y".to_string(), 10, 5, 5, 1.0),
        ];
        let lines = summary(rows).report_lines(&stats(125.4));
        assert_eq!(
            lines[0],
            "  printed 60,069 moves (123,456 lines of benchy.gcode) in 1 h 03 m of print time (1 m 20 s on the clock)"
        );
        assert_eq!(
            lines[1],
            "  all motion was sent at least 125 ms ahead of the MCUs (the safe minimum is 100 ms)"
        );
        assert_eq!(
            lines[2],
            "  final position matches the MCU's step count on all 2 steppers"
        );
        let details = lines.iter().position(|l| l == "Details:").unwrap();
        assert_eq!(details, 4);
        assert!(lines.iter().any(|l| l.contains("p50 12 µs")), "{lines:?}");
        assert!(
            !lines.iter().any(|l| l.contains(" us")),
            "one spelling of µs: {lines:?}"
        );
    }

    #[test]
    fn a_low_lead_and_a_mismatch_are_said_plainly() {
        let rows = vec![("stepper_z".to_string(), 10, 4, 5, 1.0)];
        let s = summary(rows);
        let words = s.plain_words(&stats(42.0));
        assert!(words[1].contains("only 42 ms ahead") && words[1].contains("below the safe minimum"));
        assert_eq!(
            words[2],
            "final position DIFFERS from the MCU's step count on stepper_z"
        );
        let json = s.to_json(&stats(42.0));
        assert_eq!(json["moves"], 60_069);
        assert_eq!(json["steppers"][0]["matches"], false);
        assert!((json["min_lead_ms"].as_f64().unwrap() - 42.0).abs() < 1e-6);
    }
}
