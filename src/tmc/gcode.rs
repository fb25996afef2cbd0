//! `SET_TMC_CURRENT`, `SET_TMC_FIELD`, `DUMP_TMC` and `INIT_TMC` (Klipper's TMC commands, each
//! with `STEPPER=`), run on a live print once the moves before them are done.
//!
//! - `SET_TMC_CURRENT STEPPER=s [CURRENT=a] [HOLDCURRENT=a]`: the current registers recomputed
//!   and written; answers `Run Current: 0.80A Hold Current: 0.50A` (the currents the bits give).
//! - `SET_TMC_FIELD STEPPER=s FIELD=f VALUE=v|VELOCITY=mm/s`: the field set and its register
//!   written (a velocity as TSTEP units).
//! - `DUMP_TMC STEPPER=s [REGISTER=r]`: the write-only registers as last written, then every
//!   readable register read from the driver (`REG:        value field=v …`).
//! - `INIT_TMC STEPPER=s`: every register written again.

use super::io::TmcIo;
use super::{TmcError, TmcOut};
use crate::mcus::Mcus;
use sysconfig::printer::tmc::{current, FieldSet};

/// The commands this module runs.
pub const COMMANDS: [&str; 4] = ["SET_TMC_CURRENT", "SET_TMC_FIELD", "DUMP_TMC", "INIT_TMC"];

/// True for a command name this module runs.
pub fn is_tmc_command(name: &str) -> bool {
    COMMANDS.contains(&name)
}

/// `NAME KEY=VALUE …` → upper-cased keys and their values.
fn params(raw: &str) -> Vec<(String, String)> {
    raw.split_whitespace()
        .skip(1)
        .filter_map(|w| w.split_once('='))
        .map(|(k, v)| (k.to_ascii_uppercase(), v.to_string()))
        .collect()
}

/// The driver and its bus link of `STEPPER=`.
pub fn io_for<'a>(mcus: &'a Mcus, drivers: &'a [TmcOut], stepper: &str) -> Result<TmcIo<'a>, TmcError> {
    let drv = drivers
        .iter()
        .find(|d| d.cfg.stepper == stepper)
        .ok_or_else(|| TmcError::UnknownStepper {
            stepper: stepper.to_string(),
        })?;
    let conn = mcus.get(drv.mcu()).ok_or_else(|| TmcError::NotConnected {
        mcu: drv.mcu().to_string(),
        section: drv.cfg.section_name(),
    })?;
    let oid = usize::from(conn.tmc_oid0) + drv.bus;
    let mux = super::mux_selection(drivers, drv)
        .into_iter()
        .map(|(offset, level)| u8::try_from(usize::from(conn.tmc_oid0) + offset).map(|o| (o, level)))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|_| TmcError::TooManyObjects)?;
    Ok(TmcIo {
        link: &conn.link,
        oid: u8::try_from(oid).map_err(|_| TmcError::TooManyObjects)?,
        drv,
        mux,
    })
}

/// Runs `raw` (a command of [`COMMANDS`]); its answer lines go to `out`.
pub fn run(
    mcus: &Mcus,
    drivers: &[TmcOut],
    name: &str,
    raw: &str,
    out: &mut Vec<String>,
) -> Result<(), TmcError> {
    let ps = params(raw);
    let get = |key: &str| ps.iter().rev().find(|(k, _)| k == key).map(|(_, v)| v.as_str());
    let missing = |key: &'static str| TmcError::Missing {
        raw: raw.to_string(),
        key,
    };
    let unparsable = |value: &str, what: &'static str| TmcError::Unparsable {
        raw: raw.to_string(),
        value: value.to_string(),
        what,
    };
    let stepper = get("STEPPER").ok_or_else(|| missing("STEPPER"))?;
    let io = io_for(mcus, drivers, stepper)?;
    let float = |key: &str| -> Result<Option<f64>, TmcError> {
        get(key)
            .map(|v| {
                v.parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| unparsable(v, "a float"))
            })
            .transpose()
    };
    match name {
        "SET_TMC_CURRENT" => set_current(&io, float("CURRENT")?, float("HOLDCURRENT")?, raw, out),
        "SET_TMC_FIELD" => {
            let field = get("FIELD").ok_or_else(|| missing("FIELD"))?.to_ascii_lowercase();
            let value = match get("VALUE") {
                Some(v) => Some(v.parse::<i64>().map_err(|_| unparsable(v, "an integer"))?),
                None => None,
            };
            let velocity = float("VELOCITY")?;
            let value = match (value, velocity) {
                (Some(v), None) => v,
                (None, Some(v)) if v >= 0.0 => i64::from(io.drv.cfg.tstep(v)),
                (None, Some(_)) => return Err(TmcError::NegativeVelocity { raw: raw.to_string() }),
                _ => return Err(TmcError::ValueOrVelocity),
            };
            let (reg, val) = io.drv.lock().fields.set(&field, value)?;
            io.write(reg, val)
        }
        "DUMP_TMC" => dump(&io, get("REGISTER"), out),
        _ => io.init(),
    }
}

fn set_current(
    io: &TmcIo<'_>,
    run: Option<f64>,
    hold: Option<f64>,
    raw: &str,
    out: &mut Vec<String>,
) -> Result<(), TmcError> {
    let cfg = &io.drv.cfg;
    let max = cfg.model.max_current();
    for (key, v) in [("CURRENT", run), ("HOLDCURRENT", hold)] {
        if let Some(value) = v.filter(|&v| v <= 0.0 || v > max) {
            return Err(TmcError::Current {
                raw: raw.to_string(),
                key,
                max,
                value,
            });
        }
    }
    if run.is_some() || hold.is_some() {
        let (prev_run, _) = current::current(&io.drv.lock().fields, cfg.sense_resistor);
        let run = run.unwrap_or(prev_run);
        let changed = {
            let mut st = io.drv.lock();
            let hold = hold.unwrap_or(st.req_hold_current);
            st.req_hold_current = hold;
            st.req_run_current = run;
            current::set_current(&mut st.fields, cfg.sense_resistor, run, hold)
        };
        for (reg, value) in changed {
            io.write(reg, value)?;
        }
    }
    let (run, hold) = current::current(&io.drv.lock().fields, cfg.sense_resistor);
    out.push(format!("Run Current: {run:.2}A Hold Current: {hold:.2}A"));
    Ok(())
}

fn dump(io: &TmcIo<'_>, register: Option<&str>, out: &mut Vec<String>) -> Result<(), TmcError> {
    let model = io.drv.cfg.model;
    let readable = model.readable();
    let written = io.drv.lock().fields.registers().to_vec();
    let show = |reg: &str, v: u32| FieldSet::pretty(model, dump_name(model, reg, v), v);
    if let Some(reg) = register {
        let reg = reg.to_ascii_uppercase();
        if readable.contains(&reg.as_str()) {
            out.push(show(&reg, io.read(&reg)?));
        } else if let Some(&(r, v)) = written.iter().find(|(r, _)| *r == reg) {
            out.push(show(r, v));
        } else {
            return Err(TmcError::UnknownRegister { reg });
        }
        return Ok(());
    }
    out.push("========== Write-only registers ==========".to_string());
    for (reg, v) in written.iter().filter(|(r, _)| !readable.contains(r)) {
        out.push(show(reg, *v));
    }
    out.push("========== Queried registers ==========".to_string());
    for reg in readable {
        out.push(show(reg, io.read(reg)?));
    }
    Ok(())
}

/// The field table a register's value is shown with: the TMC2208's IOIN has two layouts,
/// told apart by its `sel_a` bit.
fn dump_name(model: sysconfig::printer::TmcModel, reg: &str, v: u32) -> &str {
    match (model, reg) {
        (sysconfig::printer::TmcModel::Tmc2208, "IOIN") if v & (1 << 8) != 0 => "IOIN@TMC220x",
        (sysconfig::printer::TmcModel::Tmc2208, "IOIN") => "IOIN@TMC222x",
        _ => reg,
    }
}
