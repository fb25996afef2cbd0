//! `cadence dictionary`: prints or saves an MCU's data dictionary ([`cadence::mcu_dictionary`])
//! from a simulated MCU, a serial device, a saved file, or the Cadence firmware's own.

use std::path::PathBuf;

use cadence::mcu_dictionary::{self as md, DictSource};
use clap::Args;

/// Arguments of `cadence dictionary`.
#[derive(Debug, Args)]
pub struct DictionaryArgs {
    /// Ask an MCU on this serial device (or pty) through identify.
    #[arg(long, value_name = "DEVICE", conflicts_with_all = ["file", "simulator"])]
    pub serial: Option<String>,
    /// Baud rate for --serial.
    #[arg(long, default_value_t = 250_000, requires = "serial")]
    pub baud: u32,
    /// Read a saved dictionary (plain JSON such as Klipper's out/klipper.dict, or zlib data).
    #[arg(long, value_name = "PATH", conflicts_with = "simulator")]
    pub file: Option<PathBuf>,
    /// Start a simulated MCU and ask it through identify (default without a source: the
    /// Cadence firmware's built-in dictionary, the one batch mode uses).
    #[arg(long)]
    pub simulator: bool,
    /// The simulated MCU's clock (Hz).
    #[arg(long, default_value_t = 50_000_000, requires = "simulator")]
    pub clock_freq: u64,
    /// Print JSON (what --dictionary takes back) instead of the readable table.
    #[arg(long)]
    pub json: bool,
    /// Write the JSON to this file instead of printing.
    #[arg(long, short, value_name = "PATH")]
    pub output: Option<PathBuf>,
}

pub fn run(args: &DictionaryArgs) -> Result<(), String> {
    let source = match (&args.serial, &args.file, args.simulator) {
        (Some(path), _, _) => DictSource::Serial {
            path,
            baud: args.baud,
        },
        (_, Some(p), _) => DictSource::File(p),
        (_, _, true) => DictSource::Simulator {
            clock_freq: args.clock_freq,
        },
        _ => DictSource::Builtin,
    };
    let dict = md::fetch(source)?;
    if let Some(out) = &args.output {
        let json = md::to_json(&dict)?;
        std::fs::write(out, json + "\n").map_err(|e| format!("{}: {e}", out.display()))?;
        eprintln!("cadence: dictionary written to {}", out.display());
        return Ok(());
    }
    let text = if args.json {
        md::to_json(&dict)? + "\n"
    } else {
        md::to_table(&dict)?
    };
    print!("{text}");
    Ok(())
}
