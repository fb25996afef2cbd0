//! What a live print reports at the end ([`Summary`]): lines, moves, print and wall time, each
//! stepper's position read back from its MCU against the host's, histogram and allocation
//! lines, and the MCU links' lead and traffic figures.

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

impl Summary {
    /// The report's lines, as `cadence print` shows them; `all_stats` are the MCU links'.
    pub fn report_lines(&self, all_stats: &[(String, links::mcu::LinkStats)]) -> Vec<String> {
        let mut out = Vec::new();
        out.push(format!("print: {}", self.file.display()));
        out.push(format!(
            "  lines {}, moves {}, queue_step {}, print time {:.3} s, wall {:.3} s",
            self.lines, self.moves, self.queue_steps, self.print_time, self.wall
        ));
        out.push(format!(
            "  {:<10} {:>10} {:>12} {:>12} {:>12}",
            "stepper", "steps", "mcu pos", "host pos", "position mm"
        ));
        for (name, steps, mcu_pos, host_pos, mm) in &self.rows {
            let flag = if mcu_pos == host_pos { "" } else { "  MISMATCH" };
            out.push(format!(
                "  {name:<10} {steps:>10} {mcu_pos:>12} {host_pos:>12} {mm:>12.4}{flag}"
            ));
        }
        for line in &self.extra {
            out.push(format!("  {line}"));
        }
        for (name, stats) in all_stats {
            let freq = self
                .mcu_freqs
                .iter()
                .find(|(n, _)| n == name)
                .map_or(self.clock_freq, |&(_, f)| f);
            if let Some(margin) = stats.min_lead_margin_ticks {
                out.push(format!(
                    "  mcu '{name}': min lead margin {:.1} ms over {} clocked messages (required {:.0} ms)",
                    margin as f64 / freq * 1e3,
                    stats.clocked_msgs,
                    MIN_LEAD_S * 1e3
                ));
            }
            let q = &stats.queue;
            out.push(format!(
                "  mcu '{name}': {} bytes written, {} read, {} retransmitted, {} invalid; srtt {:.3} ms, \
                 clock residual {:.1} us",
                q.bytes_write,
                q.bytes_read,
                q.bytes_retransmit,
                q.bytes_invalid,
                q.srtt * 1e3,
                stats.clock_residual_us
            ));
        }
        out
    }
}
