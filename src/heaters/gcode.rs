//! The heater and fan G-code the planner does not see, with Klipper's names and parameters:
//! `SET_HEATER_TEMPERATURE HEATER= TARGET=`, `TEMPERATURE_WAIT SENSOR= MINIMUM= MAXIMUM=`,
//! `TURN_OFF_HEATERS`, `M105`, `M112`, `PID_CALIBRATE HEATER= TARGET= [WRITE_FILE=1]`,
//! `SAVE_CONFIG`, `SET_FAN_SPEED FAN= SPEED=`, `SET_TEMPERATURE_FAN_TARGET TEMPERATURE_FAN=
//! [TARGET=] [MIN_SPEED=] [MAX_SPEED=]`; and the commands the planner parses itself (M104/M109/M140/M190,
//! M106/M107) as [`HeatCmd`]s. Pure: parsing only, nothing here touches a heater.

use std::borrow::Cow;

use planner::gcode::{Command, OtherParams};
use planner::machine::Applied;

/// A heater or fan command.
#[derive(Debug, Clone, PartialEq)]
pub enum HeatCmd {
    /// Set `heater`'s target (°C, 0 = off); `wait` until it settles (M109/M190).
    Set {
        /// `extruder`, `heater_bed` (no allocation for M104/M140), or as written.
        heater: Cow<'static, str>,
        target: f64,
        wait: bool,
    },
    /// Wait until `sensor` (a heater or temperature sensor) is within `min..=max`.
    Wait {
        sensor: String,
        min: Option<f64>,
        max: Option<f64>,
    },
    /// Every heater's target to 0.
    TurnOffAll,
    /// M105: the temperature report.
    Report,
    /// M112: emergency stop (every MCU shut down, every heater off).
    EmergencyStop,
    /// The part fan's speed (0..=1).
    Fan { speed: f64 },
    /// PID_CALIBRATE: the relay test on `heater` at `target`; `write_file`: its samples to
    /// `/tmp/heattest.txt`.
    PidCalibrate {
        heater: String,
        target: f64,
        write_file: bool,
    },
    /// SAVE_CONFIG: the pending calibration results into printer.cfg.
    SaveConfig,
    /// SET_FAN_SPEED: a `[fan_generic]`'s speed (0..=1).
    FanSpeed { fan: String, speed: f64 },
    /// SET_TEMPERATURE_FAN_TARGET: a `[temperature_fan]`'s target (`None`: its configured
    /// one) and speed range.
    TemperatureFanTarget {
        fan: String,
        target: Option<f64>,
        min_speed: Option<f64>,
        max_speed: Option<f64>,
    },
}

/// A malformed heater command; each names the command or its missing parameter.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum HeatCmdError {
    /// A parameter that does not parse.
    #[error("{name}: {source}")]
    Param {
        name: String,
        #[source]
        source: planner::gcode::GcodeErrorKind,
    },
    /// A required parameter is missing (`raw`: the command as written).
    #[error("Error on '{raw}': missing {key}")]
    Missing { raw: String, key: String },
    /// TEMPERATURE_WAIT without either bound.
    #[error("Error on 'TEMPERATURE_WAIT': missing MINIMUM or MAXIMUM.")]
    NoBounds,
}

/// The heater command of an extended/M command line the planner does not know, `None` for any
/// other command; a malformed one is an error naming the parameter.
pub fn parse(cmd: &Command) -> Option<Result<HeatCmd, HeatCmdError>> {
    let Command::Other { name, raw } = cmd else {
        return None;
    };
    let name = name.as_str();
    if !matches!(
        name,
        "SET_HEATER_TEMPERATURE"
            | "TEMPERATURE_WAIT"
            | "TURN_OFF_HEATERS"
            | "M105"
            | "M112"
            | "PID_CALIBRATE"
            | "SAVE_CONFIG"
            | "SET_FAN_SPEED"
            | "SET_TEMPERATURE_FAN_TARGET"
    ) {
        return None;
    }
    Some(parse_named(name, raw.as_str()))
}

fn parse_named(name: &str, raw: &str) -> Result<HeatCmd, HeatCmdError> {
    let param = |source| HeatCmdError::Param {
        name: name.to_string(),
        source,
    };
    let missing = |key: &str| HeatCmdError::Missing {
        raw: raw.trim().to_string(),
        key: key.to_string(),
    };
    let p = OtherParams::parse(raw).map_err(param)?;
    let num = |k: &str| p.float(k).map_err(param);
    let text =
        |k: &str| -> Result<String, HeatCmdError> { p.get(k).map(str::to_string).ok_or_else(|| missing(k)) };
    Ok(match name {
        "SET_HEATER_TEMPERATURE" => HeatCmd::Set {
            heater: Cow::Owned(text("HEATER")?),
            target: num("TARGET")?.unwrap_or(0.0),
            wait: false,
        },
        "TEMPERATURE_WAIT" => {
            let (min, max) = (num("MINIMUM")?, num("MAXIMUM")?);
            if min.is_none() && max.is_none() {
                return Err(HeatCmdError::NoBounds);
            }
            HeatCmd::Wait {
                sensor: text("SENSOR")?,
                min,
                max,
            }
        }
        "TURN_OFF_HEATERS" => HeatCmd::TurnOffAll,
        "PID_CALIBRATE" => HeatCmd::PidCalibrate {
            heater: text("HEATER")?,
            target: num("TARGET")?.ok_or_else(|| missing("TARGET"))?,
            write_file: num("WRITE_FILE")?.is_some_and(|v| v != 0.0),
        },
        "SAVE_CONFIG" => HeatCmd::SaveConfig,
        "SET_FAN_SPEED" => HeatCmd::FanSpeed {
            fan: text("FAN")?,
            speed: num("SPEED")?.unwrap_or(0.0),
        },
        "SET_TEMPERATURE_FAN_TARGET" => HeatCmd::TemperatureFanTarget {
            fan: text("TEMPERATURE_FAN")?,
            target: num("TARGET")?,
            min_speed: num("MIN_SPEED")?,
            max_speed: num("MAX_SPEED")?,
        },
        "M112" => HeatCmd::EmergencyStop,
        _ => HeatCmd::Report,
    })
}

/// The heater command of what the planner applied (M104/M109/M140/M190, M106/M107).
pub fn of_applied(applied: &Applied) -> Option<HeatCmd> {
    match *applied {
        Applied::Heater { heater, target, wait } => Some(HeatCmd::Set {
            heater: Cow::Borrowed(heater.name()),
            target,
            wait,
        }),
        Applied::Fan { speed } => Some(HeatCmd::Fan { speed }),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use planner::gcode::parse_line;

    fn cmd(text: &str) -> Option<Result<HeatCmd, HeatCmdError>> {
        parse(&parse_line(1, text.as_bytes()).unwrap().unwrap())
    }

    #[test]
    fn klippers_commands() {
        assert_eq!(
            cmd("SET_HEATER_TEMPERATURE HEATER=heater_bed TARGET=60"),
            Some(Ok(HeatCmd::Set {
                heater: "heater_bed".into(),
                target: 60.0,
                wait: false
            }))
        );
        assert_eq!(
            cmd("TEMPERATURE_WAIT SENSOR=extruder MINIMUM=200"),
            Some(Ok(HeatCmd::Wait {
                sensor: "extruder".into(),
                min: Some(200.0),
                max: None
            }))
        );
        assert_eq!(cmd("TURN_OFF_HEATERS"), Some(Ok(HeatCmd::TurnOffAll)));
        assert_eq!(cmd("M105"), Some(Ok(HeatCmd::Report)));
        assert_eq!(cmd("M112"), Some(Ok(HeatCmd::EmergencyStop)));
        assert_eq!(
            cmd("PID_CALIBRATE HEATER=extruder TARGET=210 WRITE_FILE=1"),
            Some(Ok(HeatCmd::PidCalibrate {
                heater: "extruder".into(),
                target: 210.0,
                write_file: true
            }))
        );
        assert_eq!(cmd("SAVE_CONFIG"), Some(Ok(HeatCmd::SaveConfig)));
        assert_eq!(
            cmd("SET_FAN_SPEED FAN=aux SPEED=0.5"),
            Some(Ok(HeatCmd::FanSpeed {
                fan: "aux".into(),
                speed: 0.5
            }))
        );
        assert_eq!(
            cmd("SET_TEMPERATURE_FAN_TARGET TEMPERATURE_FAN=exhaust TARGET=40 MAX_SPEED=0.8"),
            Some(Ok(HeatCmd::TemperatureFanTarget {
                fan: "exhaust".into(),
                target: Some(40.0),
                min_speed: None,
                max_speed: Some(0.8)
            }))
        );
        assert!(cmd("SET_FAN_SPEED SPEED=1").unwrap().is_err());
        assert_eq!(cmd("G1 X1"), None);
        assert_eq!(cmd("SET_VELOCITY_LIMIT ACCEL=1"), None);
    }

    #[test]
    fn bad_parameters_are_errors() {
        assert!(cmd("TEMPERATURE_WAIT SENSOR=extruder").unwrap().is_err());
        let e = cmd("PID_CALIBRATE HEATER=extruder").unwrap().unwrap_err();
        assert!(
            matches!(&e, HeatCmdError::Missing { key, .. } if key == "TARGET"),
            "{e:?}"
        );
        assert!(e.to_string().contains("missing TARGET"), "{e}");
        let e = cmd("SET_HEATER_TEMPERATURE TARGET=60").unwrap().unwrap_err();
        assert!(e.to_string().contains("missing HEATER"), "{e}");
        assert!(cmd("SET_HEATER_TEMPERATURE HEATER=extruder TARGET=abc")
            .unwrap()
            .is_err());
    }
}
