//! Sensorless homing: around the homing of an axis whose endstop is a driver's
//! `virtual_endstop`, the driver is switched to report stalls on its DIAG pin, then restored.
//!
//! As Klipper does it: stallGuard4 drivers (TMC2209) need stealthChop (`TPWMTHRS` 0,
//! `en_spreadcycle` 0); stallGuard2 drivers (TMC2130/5160, a TMC2240 without `sg4_thrs`) need
//! spreadCycle (`en_pwm_mode` 0) and the stall routed to the pin (`diag0_stall`/`diag1_stall`
//! 1); a TMC2240 with `sg4_thrs` set uses stallGuard4 in stealthChop (`en_pwm_mode` 1,
//! `TPWMTHRS` 0) with the stall routed; every driver gets
//! `TCOOLTHRS` 0xfffff when it was 0 (stall detection at every speed) and `THIGH` 0. Each
//! changed register is written before the first homing move; afterwards the fields get their
//! earlier values back and their registers are written again, also when homing failed.

use super::io::TmcIo;
use super::TmcError;

/// The fields changed for homing and their earlier values.
#[derive(Debug, Default)]
pub struct Saved {
    fields: Vec<(&'static str, i64)>,
}

/// Sets the homing fields, writes their registers; returns what to restore.
pub fn begin(io: &TmcIo<'_>) -> Result<Saved, TmcError> {
    let mut saved = Saved::default();
    let mut dirty: Vec<&'static str> = Vec::new();
    {
        let mut st = io.drv.lock();
        let model = io.drv.cfg.model;
        let mut changes: Vec<(&'static str, i64)> = Vec::new();
        let sg4 = st.fields.get("sg4_thrs").unwrap_or(0) != 0;
        if model.field("en_pwm_mode").is_none() {
            changes.extend([("tpwmthrs", 0), ("en_spreadcycle", 0)]);
        } else if sg4 {
            // A TMC2240 with `driver_SG4_THRS`: stallGuard4, in stealthChop.
            changes.extend([("en_pwm_mode", 1), ("tpwmthrs", 0)]);
            if let Some(f) = io.drv.cfg.diag_field {
                changes.push((f, 1));
            }
        } else {
            changes.push(("en_pwm_mode", 0));
            if let Some(f) = io.drv.cfg.diag_field {
                changes.push((f, 1));
            }
        }
        if st.fields.get("tcoolthrs") == Some(0) {
            changes.push(("tcoolthrs", 0xfffff));
        }
        if model.field("thigh").is_some() {
            changes.push(("thigh", 0));
        }
        for (field, v) in changes {
            let Some(old) = st.fields.get(field) else {
                continue;
            };
            saved.fields.push((field, old));
            if let Ok((reg, _)) = st.fields.set(field, v) {
                if !dirty.contains(&reg) {
                    dirty.push(reg);
                }
            }
        }
    }
    write_all(io, &dirty)?;
    Ok(saved)
}

/// Gives the fields their earlier values back and writes their registers.
pub fn end(io: &TmcIo<'_>, saved: Saved) -> Result<(), TmcError> {
    let mut dirty: Vec<&'static str> = Vec::new();
    {
        let mut st = io.drv.lock();
        for (field, v) in saved.fields.into_iter().rev() {
            if let Ok((reg, _)) = st.fields.set(field, v) {
                if !dirty.contains(&reg) {
                    dirty.push(reg);
                }
            }
        }
    }
    write_all(io, &dirty)
}

fn write_all(io: &TmcIo<'_>, regs: &[&'static str]) -> Result<(), TmcError> {
    for reg in regs {
        let value = io.drv.lock().fields.register(reg);
        io.write(reg, value)?;
    }
    Ok(())
}
