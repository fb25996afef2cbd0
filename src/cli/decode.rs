//! `cadence decode`: prints a host→MCU wire stream (as written by `print --batch`) one message
//! a line, with names and fields from the data dictionary; with `--check FILE.gcode`, proves
//! its step commands against the G-code's motion instead ([`cadence::wire_check`]).

use std::io::Write;
use std::path::PathBuf;

use cadence::wire_check::{self as check, load_dictionary};
use clap::Args;
use links::proto::{blocks, StreamItem};

/// Arguments of `cadence decode`.
#[derive(Debug, Args)]
pub struct DecodeArgs {
    /// The wire stream to decode.
    pub file: PathBuf,
    /// Data dictionary (zlib-compressed or plain JSON, e.g. Klipper's out/klipper.dict);
    /// default: the Cadence firmware's own.
    #[arg(long)]
    pub dictionary: Option<PathBuf>,
    /// Instead of printing the messages, prove every step of the stream against this G-code's
    /// motion: within the bound before its ideal time, in order, in its direction, none missing.
    #[arg(long, value_name = "FILE.gcode")]
    pub check: Option<PathBuf>,
    /// With --check: the printer config the stream was written with (default: the built-in
    /// simulated printer).
    #[arg(long, requires = "check")]
    pub config: Option<PathBuf>,
    /// With --check: the MCU the stream is for (`print --batch` writes one file per MCU).
    #[arg(long, default_value = "mcu", requires = "check")]
    pub mcu: String,
    /// With --check: the step time bound the stream was compressed with.
    #[arg(long, default_value_t = 25.0, requires = "check")]
    pub max_error_us: f64,
}

pub fn run(args: &DecodeArgs) -> Result<(), String> {
    let dict = load_dictionary(args.dictionary.as_deref())?;
    let data = std::fs::read(&args.file).map_err(|e| format!("{}: {e}", args.file.display()))?;
    if let Some(gcode) = &args.check {
        let spec = check::CheckSpec {
            gcode,
            config: args.config.as_deref(),
            mcu: &args.mcu,
            max_error_us: args.max_error_us,
        };
        return Ok(check::run(&args.file, &data, &dict, &spec, &mut |line| {
            println!("{line}")
        })?);
    }
    let stdout = std::io::stdout();
    let mut out = std::io::BufWriter::new(stdout.lock());
    let mut bad = 0u64;
    for item in blocks(&data) {
        match item {
            StreamItem::Block { pos, seq, payload } => {
                let msgs = dict
                    .decode(payload)
                    .map_err(|e| format!("{}: block at byte {pos} (seq {seq}): {e}", args.file.display()))?;
                for m in msgs {
                    if writeln!(out, "{m}").is_err() {
                        return Ok(()); // reader went away (e.g. `| head`)
                    }
                }
            }
            StreamItem::Bad { pos, len } => {
                bad += 1;
                let _ = writeln!(out, "# invalid block at byte {pos} ({len} bytes skipped)");
            }
            StreamItem::Truncated { pos, left } => {
                return Err(format!(
                    "{}: truncated block at byte {pos} ({left} bytes left)",
                    args.file.display()
                ));
            }
        }
    }
    let _ = out.flush();
    if bad > 0 {
        return Err(format!("{}: {bad} invalid blocks", args.file.display()));
    }
    Ok(())
}
