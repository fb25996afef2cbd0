//! `cadence`: the host binary. Subcommands:
//! - `print FILE.gcode [--config printer.cfg]`: plan, compress and stream a print to the MCUs
//!   (the built-in simulated printer when no config is given), or with `--batch OUT.bin`
//!   write the exact wire stream to a file without any MCU.
//! - `home [--config printer.cfg] [--axes xyz] [--cycles N]`: G28 with motion on the MCUs,
//!   reporting overshoot and trigger → stop latencies (see `homing`).
//! - `decode OUT.bin`: print a wire stream one message a line.
//! - `service print|install --config printer.cfg`: the systemd unit of `cadence serve`.
//! - `check-config printer.cfg`: every error and warning of a config, the sections read,
//!   ignored and refused.
//! - `dictionary [--simulator | --serial DEV | --file PATH] [--json]`: an MCU's data dictionary.
//! - `doctor [--unit --config printer.cfg]`: host real-time checks, or the systemd unit.
//! - `serve [--config printer.cfg | --simulated] [-a SOCKET]`: the printer service front ends
//!   attach to (Klipper's API socket); `serve --role io [--config printer.cfg] [--instance
//!   NAME]`: the IO stage in its own process (MCU connections), serving one `print
//!   --io-process` / `--io-attach NAME`.
//! - `mcu …` (hidden): the simulated MCU (the firmware's Linux-process target), for when the
//!   separate `cadence-mcu` executable was not built.

//!
//! Each subcommand is a small module of [`cli`] over the `cadence` library; `bench` is in
//! `benchcmd` (the only user of the `bench` crate).

mod benchcmd;
mod cli;

// `benchcmd` reaches the library through these paths.
use cadence::hardware as machine;
use cadence::wire_check as decode;

use cadence::allocsites;
use clap::{Parser, Subcommand};
use cli::{check_config, decode as decode_cmd, dictionary, doctor, home, print, serve, service};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Debug, Parser)]
#[command(
    name = "cadence",
    version,
    about = "Deterministic real-time motion kernel for Klipper-protocol MCUs"
)]
struct Cli {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Debug, Subcommand)]
enum Cmd {
    /// Print a G-code file on the configured printer (default: the built-in simulated printer).
    Print(print::PrintArgs),
    /// Home the printer's axes with real motion (G28), once or in cycles with latency figures.
    Home(home::HomeArgs),
    /// The printer service front ends attach to (Klipper's API socket with `-a`), or with
    /// `--role io` one stage of the live print (the MCU connections) serving a `cadence print
    /// --io-process` or `--io-attach NAME`.
    Serve(serve::ServeArgs),
    /// The systemd unit of `cadence serve` for a printer.cfg: `print` it or `install` it.
    Service(service::ServiceArgs),
    /// Check this host for hard timing (PREEMPT_RT, SCHED_FIFO, limits, CPU isolation, wake-up
    /// latency), or print the systemd unit for the service with `--unit`.
    Doctor(doctor::DoctorArgs),
    /// Decode a wire stream written by `print --batch` into one message per line.
    Decode(decode_cmd::DecodeArgs),
    /// Check a printer.cfg: every error and warning with file:line, the sections read, ignored
    /// and refused, the MCUs' pins against a data dictionary (exit status 1 on errors).
    CheckConfig(check_config::CheckConfigArgs),
    /// Print an MCU's data dictionary (from a simulated MCU, a serial device, a saved file or
    /// the built-in firmware's) as a table or JSON, or save it for --dictionary.
    Dictionary(dictionary::DictionaryArgs),
    /// Benchmarks: `bench wakeup` (wake-up latency, cyclictest-class), `bench handoff`,
    /// `bench plan FILE` (planning + step compression), with --json, --hlog, --plot, --load.
    Bench(benchcmd::BenchArgs),
    /// Run the simulated MCU (same code as the `cadence-mcu` executable).
    #[command(hide = true, disable_help_flag = true)]
    Mcu {
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
}

/// Counts allocations per thread so the real-time loops can prove they allocate nothing.
#[global_allocator]
static ALLOC: rt_core::alloc_count::CountingAlloc = rt_core::alloc_count::CountingAlloc;

fn main() -> ExitCode {
    let cli = Cli::parse();
    allocsites::init();
    let who = match cli.command {
        Cmd::Serve(_) => "cadence serve",
        _ => "cadence",
    };
    let result = match cli.command {
        Cmd::Print(args) => match print::run(&args) {
            Ok(code) => return ExitCode::from(code),
            Err(e) => Err(e),
        },
        Cmd::Decode(args) => decode_cmd::run(&args),
        Cmd::CheckConfig(args) => check_config::run(&args),
        Cmd::Dictionary(args) => dictionary::run(&args),
        Cmd::Doctor(args) => doctor::run(&args),
        Cmd::Serve(args) => serve::run(&args),
        Cmd::Service(args) => service::run(&args),
        Cmd::Bench(args) => benchcmd::run(&args).map_err(String::from),
        Cmd::Home(args) => home::run(&args),
        Cmd::Mcu { args } => {
            let argv = std::iter::once("cadence-mcu".to_string()).chain(args);
            let code = firmware::sim::main_with_args(argv);
            return ExitCode::from(code.clamp(0, 255) as u8);
        }
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("{who}: error: {}", printable(&e));
            ExitCode::FAILURE
        }
    }
}

/// `text` safe for a terminal: control characters other than newlines (as in a G-code line
/// quoted from a binary file) written as `\xNN`.
fn printable(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        if c.is_control() && c != '\n' {
            out.push_str(&format!("\\x{:02x}", c as u32));
        } else {
            out.push(c);
        }
    }
    out
}

/// Paths the CLI takes.
pub type FilePath = PathBuf;

#[cfg(test)]
mod tests {
    #[test]
    fn control_characters_are_escaped() {
        assert_eq!(
            super::printable("bad \u{1b}[2J\x07 line\n2"),
            "bad \\x1b[2J\\x07 line\n2"
        );
    }
}
