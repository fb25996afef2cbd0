//! The `cadence-mcu` command line (docs/contract.md).

use crate::trace::TraceFormat;
use clap::{Parser, ValueEnum};
use std::path::PathBuf;

/// Largest `--move-count` (the core's move pool capacity).
pub const MAX_MOVE_COUNT: u16 = super::SIM_MOVES as u16;

/// Trace file format on the command line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum TraceFormatArg {
    /// Binary: 24-byte header, 16-byte records.
    Bin,
    /// Text lines.
    Csv,
}

impl From<TraceFormatArg> for TraceFormat {
    fn from(f: TraceFormatArg) -> TraceFormat {
        match f {
            TraceFormatArg::Bin => TraceFormat::Bin,
            TraceFormatArg::Csv => TraceFormat::Csv,
        }
    }
}

/// Simulated Klipper-protocol MCU on a pseudo-terminal.
#[derive(Debug, Clone, Parser)]
#[command(name = "cadence-mcu", version, about)]
pub struct Cli {
    /// Also make a symlink to the pty slave at PATH.
    #[arg(long, value_name = "PATH")]
    pub pty_link: Option<PathBuf>,
    /// MCU clock frequency (the dictionary's CLOCK_FREQ).
    #[arg(long, value_name = "HZ", default_value_t = 50_000_000,
          value_parser = clap::value_parser!(u32).range(1..))]
    pub clock_freq: u32,
    /// MCU seconds per wall-clock second.
    #[arg(long, value_name = "N", default_value_t = 1.0, value_parser = parse_time_scale)]
    pub time_scale: f64,
    /// Write every step, received queue_step and shutdown to FILE.
    #[arg(long, value_name = "FILE")]
    pub trace: Option<PathBuf>,
    /// Trace file format.
    #[arg(long, value_enum, default_value_t = TraceFormatArg::Bin)]
    pub trace_format: TraceFormatArg,
    /// Size of the move queue reported in `config` (move_count).
    #[arg(long, value_name = "N", default_value_t = 16384,
          value_parser = clap::value_parser!(u16).range(1..=MAX_MOVE_COUNT as i64))]
    pub move_count: u16,
}

fn parse_time_scale(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("`{s}` is not a positive number")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(args: &[&str]) -> Result<Cli, clap::Error> {
        Cli::try_parse_from(std::iter::once("cadence-mcu").chain(args.iter().copied()))
    }

    #[test]
    fn defaults() {
        let c = parse(&[]).unwrap();
        assert_eq!(c.clock_freq, 50_000_000);
        assert_eq!(c.time_scale, 1.0);
        assert_eq!(c.move_count, 16384);
        assert_eq!(c.trace_format, TraceFormatArg::Bin);
        assert!(c.trace.is_none() && c.pty_link.is_none());
    }

    #[test]
    fn all_options() {
        let c = parse(&[
            "--pty-link",
            "/tmp/x",
            "--clock-freq",
            "1000000",
            "--time-scale",
            "10",
            "--trace",
            "t.csv",
            "--trace-format",
            "csv",
            "--move-count",
            "500",
        ])
        .unwrap();
        assert_eq!(c.pty_link.as_deref(), Some(std::path::Path::new("/tmp/x")));
        assert_eq!((c.clock_freq, c.time_scale, c.move_count), (1_000_000, 10.0, 500));
        assert_eq!(c.trace_format, TraceFormatArg::Csv);
    }

    #[test]
    fn rejects_bad_values() {
        assert!(parse(&["--time-scale", "0"]).is_err());
        assert!(parse(&["--time-scale", "nan"]).is_err());
        assert!(parse(&["--clock-freq", "0"]).is_err());
        assert!(parse(&["--move-count", "0"]).is_err());
        assert!(parse(&["--move-count", "70000"]).is_err());
        assert!(parse(&["--trace-format", "xml"]).is_err());
    }
}
