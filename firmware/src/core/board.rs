//! The board: everything the core asks of the hardware (or of the simulator).
//!
//! The core calls these from `receive` and `run_timers`; none may block. On a real MCU
//! `step` toggles the step pin (and the direction pin when it changed) and `write` queues bytes
//! for the UART; the Linux-process target records steps in its trace and writes to its pty.

use super::stepper::StepperConfig;
use rt_core::WireClock;

/// Hardware hooks of the firmware core.
pub trait Board {
    /// Take one step on stepper `oid` in direction `dir` (true = position +1). `clock` is the
    /// step's scheduled time; the board may be running a little after it.
    fn step(&mut self, oid: u8, dir: bool, clock: WireClock);

    /// Send bytes (whole message blocks) to the host.
    fn write(&mut self, bytes: &[u8]);

    /// `config_stepper` configured `oid` (set the pins up).
    fn config_stepper(&mut self, _oid: u8, _config: &StepperConfig) {}

    /// A `queue_step` arrived at `now`; its first step is due at `first_clock`.
    fn queue_step_received(&mut self, _oid: u8, _first_clock: WireClock, _now: WireClock) {}

    /// The MCU shut down at `clock` for `reason` (`static_string_id` is its dictionary id).
    fn shutdown(&mut self, _clock: WireClock, _static_string_id: u16, _reason: &'static str) {}
}
