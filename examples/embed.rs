//! Embedding Cadence in a Rust program: open the built-in simulated printer (its MCU is the
//! firmware's Linux-process target, started as a child process on a pty), home it, stream a few
//! moves from code, read the status and the lead-margin histogram, and shut down cleanly.
//!
//! Run it with `cargo run --example embed` (the simulated MCU `cadence-mcu` must be built:
//! `cargo build --workspace`). For a real printer, open
//! `PrinterSource::ConfigFile("printer.cfg".into())` instead.

use std::error::Error;
use std::process::ExitCode;

use cadence::{Event, Printer, PrinterOptions, PrinterSource, PrinterState};

/// Counts each thread's heap allocations, so the summary can show that the planner and IO stage
/// threads allocate nothing after warm-up (optional for an embedder).
#[global_allocator]
static ALLOC: rt_core::alloc_count::CountingAlloc = rt_core::alloc_count::CountingAlloc;

fn main() -> ExitCode {
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("embed: error: {e}");
            ExitCode::FAILURE
        }
    }
}

fn run() -> Result<(), Box<dyn Error>> {
    // Real-time threads where the OS allows them (otherwise it says once which guarantee is off).
    let options = PrinterOptions::default();
    let mut printer = Printer::open(PrinterSource::Simulated, options)?;
    let events = printer.events().ok_or("events already taken")?;

    // Homing with real motion: endstops and trsync on the simulated MCU.
    let homing = printer.home([true, true, true])?;
    print!("{homing}");

    // A square, one command at a time, then wait until the MCU executed it.
    printer.send_line("G90")?;
    printer.send_line("G1 Z5 F600")?;
    for (x, y) in [
        (20.0, 20.0),
        (60.0, 20.0),
        (60.0, 60.0),
        (20.0, 60.0),
        (20.0, 20.0),
    ] {
        printer.send_line(&format!("G1 X{x} Y{y} F6000"))?;
    }
    printer.wait_moves()?;

    let status = printer.status();
    let [x, y, z, _] = status.position;
    println!(
        "status: {:?}, toolhead X{x:.3} Y{y:.3} Z{z:.3}, homed {:?}, print time {:.3} s",
        status.state, status.homed, status.print_time
    );
    for (mcu, link) in &status.mcus {
        println!(
            "mcu '{mcu}': {} bytes written, {} retransmitted, srtt {:.3} ms",
            link.queue.bytes_write,
            link.queue.bytes_retransmit,
            link.queue.srtt * 1e3
        );
    }
    let latency = printer.latency();
    let lead = latency.lead_margin;
    println!(
        "lead margin: min {:.1} ms, p50 {:.1} ms over {} step messages ({} late)",
        latency.lead_ms(lead.min),
        latency.lead_ms(lead.p50),
        lead.count,
        lead.negative
    );

    // Another thread may stop the printer at any time: `printer.handle().stop()` (or
    // `emergency_stop()`). Here the session simply ends: what was sent is executed, every
    // stepper's position is read back from the MCU and compared with the host's.
    let report = printer.close()?;
    for line in report.summary.report_lines(&report.link_stats) {
        println!("{line}");
    }
    for event in events.try_iter() {
        match event {
            Event::State(PrinterState::Shutdown { reason }) => println!("event: shut down ({reason})"),
            Event::State(state) => println!("event: {state:?}"),
            Event::Homed(report) => println!("event: homed {} axes", report.axes.len()),
            Event::Response(text) => println!("event: {text}"),
            Event::Warning(text) => println!("event: warning: {text}"),
        }
    }
    Ok(())
}
