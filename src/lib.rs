//! Cadence, the running printer as a library: open a printer from its printer.cfg (or the
//! built-in simulated one), connect and configure its MCUs and feed it G-code; the `cadence`
//! CLI, the tests and embedding programs all go through it.
//!
//! Layers (each module imports only from those above it in this list or from the crates below):
//! - the printer's description: [`hardware`] (printer.cfg → steppers, endstops, probe);
//! - the MCUs: [`sim_mcu`] (simulated MCU processes), [`mcus`] (links, identify, configure);
//! - the step stream: [`step_stream`] (step commands → per-MCU encoded messages and sinks);
//! - the G-code loop: [`gcode_feed`], [`accessories`]; [`gcode_source`] (a G-code file read with
//!   progress counts and a stop at a line boundary);
//! - the pipeline threads: [`planner_thread`], [`io_stage`], [`telemetry`], with
//!   [`latency`], [`realtime`] and [`logging`];
//! - homing and probing: [`homing`]; [`home_cycles`] (`cadence home`: cycles with latency
//!   figures);
//! - whole prints: [`live`] (threads in this process), [`io_process`] (the IO stage in
//!   another process), [`batch`] (wire files), [`job`] (what `cadence print` runs);
//! - the API: [`printer`] ([`printer::Printer`], its handle, events and status in [`events`]);
//! - the service: [`service`] (`cadence serve`: the printer kept up for front ends, Klipper's
//!   API socket);
//! - [`heaters`]: the heater logic (sensors, PID/watermark, verify_heater, PID calibration),
//!   pure and clock-free, its MCU objects and the heater thread of a live print (used by
//!   [`hardware`], [`mcus`], [`gcode_feed`], [`live`] and [`events`]);
//! - [`host_check`]: is this host fit for hard timing (PREEMPT_RT, SCHED_FIFO, limits,
//!   isolated CPUs, wake-up latency)?
//! - [`wire_check`]: a batch wire stream proved against its G-code.
//!
//! Guarantees kept here: every step command reaches its MCU at least [`MIN_LEAD_S`] before
//! its first step or the print stops before sending it; the planner and IO stage threads do
//! not allocate after warm-up; threads are pinned and SCHED_FIFO where the OS allows it, and
//! run anyway (reported once) where it does not.

/// `From<$inner>` for the error enum `$outer` through its boxed variant `$variant`: large
/// errors are boxed inside the enums that carry them, so every `Result` stays small.
macro_rules! from_boxed {
    ($outer:ty, $variant:ident, $inner:ty) => {
        impl From<$inner> for $outer {
            fn from(e: $inner) -> Self {
                Self::$variant(Box::new(e))
            }
        }
    };
}

pub mod accessories;
pub mod allocsites;
pub mod batch;
pub mod events;
pub mod gcode_feed;
pub mod gcode_source;
pub mod hardware;
pub mod heaters;
pub mod home_cycles;
pub mod homing;
pub use rt_core::host_check;
pub mod io_process;
pub mod io_stage;
pub mod job;
pub mod latency;
pub mod live;
pub mod logging;
pub mod mcu_dictionary;
pub mod mcus;
pub mod planner_thread;
pub mod printer;
pub mod realtime;
pub mod service;
pub mod sim_mcu;
pub mod spi_device;
pub mod step_stream;
pub mod summary;
pub mod telemetry;
pub mod tmc;
pub mod wire_check;

/// Lead every step command must have at the MCU, in print seconds (Klipper's "Timer too
/// close" limit is what it protects against).
pub const MIN_LEAD_S: f64 = 0.100;

pub use events::{Event, PrinterState, Status};
pub use printer::{Printer, PrinterError, PrinterHandle, PrinterOptions, PrinterSource};
