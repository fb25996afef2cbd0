//! TMC2660 `idle_current_percent`: the driver's current lowered while the printer is idle and
//! raised again before it moves, as Klipper's idle_timeout states drive it.
//!
//! Klipper's printer is "Ready" once its G-code is quiet and the toolhead has been idle for
//! [`READY_TIMEOUT`] past the end of its last move (here: every MCU's last step that long
//! ago; commands without motion do not count), and "Printing" again as soon as motion is
//! planned. On Ready each TMC2660 whose `idle_current_percent` is below 100 gets
//! `run current × percent / 100` (SGCSCONF's `cs`, DRVCONF only when `vsense` changes); on
//! Printing the run current comes back, before the first step of the new motion (the host
//! writes it at once over SPI, and a move starts at least the MCU lead after it is planned).
//! A SET_TMC_CURRENT while Ready writes the new run current at once and the driver stays there
//! until the next Printing → Ready (Klipper's behaviour too). Each driver's flag
//! ([`super::TmcState::idle`]) says whether its idle current is in.

use super::gcode::io_for;
use super::{TmcError, TmcOut};
use crate::mcus::Mcus;
use sysconfig::printer::tmc::current::set_current_2660;
use sysconfig::printer::TmcModel;

/// Quiet print time after the last move's end before the printer is Ready (s).
pub const READY_TIMEOUT: f64 = 0.5;

/// Whether `d` lowers its current while idle.
fn lowers(d: &TmcOut) -> bool {
    d.cfg.model == TmcModel::Tmc2660 && d.cfg.idle_current_percent < 100
}

/// The printer is quiet, its last step `still_s` seconds ago: from [`READY_TIMEOUT`] on, every
/// driver that lowers its current and has not yet gets its idle current. Returns the drivers
/// changed.
pub fn on_quiet(mcus: &Mcus, drivers: &[TmcOut], still_s: f64) -> Result<usize, TmcError> {
    if still_s < READY_TIMEOUT {
        return Ok(0);
    }
    let mut changed = 0;
    for d in drivers.iter().filter(|d| lowers(d) && !d.lock().idle) {
        let current = d.lock().req_run_current * f64::from(d.cfg.idle_current_percent) / 100.0;
        write_current(mcus, drivers, d, current)?;
        d.lock().idle = true;
        changed += 1;
    }
    Ok(changed)
}

/// Motion is about to be planned: every driver in its idle current gets its run current back.
/// Returns the drivers changed.
pub fn on_motion(mcus: &Mcus, drivers: &[TmcOut]) -> Result<usize, TmcError> {
    let mut changed = 0;
    for d in drivers.iter().filter(|d| d.lock().idle) {
        let current = d.lock().req_run_current;
        write_current(mcus, drivers, d, current)?;
        d.lock().idle = false;
        changed += 1;
    }
    Ok(changed)
}

/// Writes `current` (A) to `d`: SGCSCONF, and DRVCONF when `vsense` changes.
fn write_current(mcus: &Mcus, drivers: &[TmcOut], d: &TmcOut, current: f64) -> Result<(), TmcError> {
    let io = io_for(mcus, drivers, &d.cfg.stepper)?;
    let changed = set_current_2660(&mut d.lock().fields, d.cfg.sense_resistor, current);
    for (reg, value) in changed {
        io.write(reg, value)?;
    }
    Ok(())
}
