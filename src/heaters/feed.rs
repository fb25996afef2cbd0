//! What a heater command does to the running heaters, for the G-code loop: targets checked
//! against the heater's range (Klipper's "Requested temperature (300.0) out of range
//! (0.0:250.0)"), the waits of M109/M190/TEMPERATURE_WAIT as conditions on the heater thread's
//! state, the extrusion check ("Extrude below minimum temp") and the waits' log for the
//! summary.

use super::gcode::HeatCmd;
use super::objects::Thermal;
use super::runtime::HeaterShared;
use std::sync::atomic::Ordering;

/// Why a heater or fan command was refused, in Klipper's words.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum HeatError {
    /// A heater or fan name that is not configured (`param`: `HEATER`, `FAN`, …).
    #[error("The value '{value}' is not valid for {param}")]
    NotValid { value: String, param: &'static str },
    /// A target outside the heater's (or temperature fan's) `min_temp`..`max_temp`.
    #[error("Requested temperature ({target:.1}) out of range ({min:.1}:{max:.1})")]
    OutOfRange { target: f64, min: f64, max: f64 },
    /// `PID_CALIBRATE HEATER=` of an unknown heater.
    #[error("Unknown heater '{0}'")]
    UnknownHeater(String),
    /// A second `PID_CALIBRATE` while one runs.
    #[error("PID_CALIBRATE is already running")]
    CalibrationRunning,
    /// `TEMPERATURE_WAIT SENSOR=` of an unknown heater or sensor.
    #[error("Unknown sensor '{0}'")]
    UnknownSensor(String),
    /// `SET_TEMPERATURE_FAN_TARGET` with `MIN_SPEED` above `MAX_SPEED`.
    #[error("Requested min speed ({min:.1}) is greater than max speed ({max:.1})")]
    MinAboveMax { min: f64, max: f64 },
    /// An extruding move below the extruder's `min_extrude_temp`.
    #[error(
        "Extrude below minimum temp ({heater} at {temp:.1} °C, min_extrude_temp {min:.1}; see the \
         'min_extrude_temp' config option)"
    )]
    ColdExtrude { heater: String, temp: f64, min: f64 },
}

/// A name that is not valid for parameter `param`.
fn not_valid(value: &str, param: &'static str) -> HeatError {
    HeatError::NotValid {
        value: value.to_string(),
        param,
    }
}

/// A wait the G-code holds for.
#[derive(Debug, Clone, PartialEq)]
pub struct Wait {
    /// The heater's index (the sensor's with `sensor`).
    pub heater: usize,
    /// `heater` is a temperature sensor's index (TEMPERATURE_WAIT on a sensor).
    pub sensor: bool,
    /// The command, for the log (`M109`, `TEMPERATURE_WAIT`).
    pub what: &'static str,
    /// Until its control settles at the target (M109/M190) …
    pub settle: bool,
    /// … or its temperature is within these (TEMPERATURE_WAIT).
    pub min: Option<f64>,
    pub max: Option<f64>,
    /// The target waited for.
    pub target: f64,
    /// Until PID_CALIBRATE's relay test ends.
    pub calibrate: bool,
}

impl Wait {
    /// True once the wait is over.
    pub fn done(&self, shared: &HeaterShared) -> bool {
        if self.sensor {
            let t = shared.sensors.get(self.heater).map_or(f64::NAN, |s| s.temp.get());
            return !t.is_nan() && self.min.is_none_or(|m| t >= m) && self.max.is_none_or(|m| t <= m);
        }
        let Some(h) = shared.heaters.get(self.heater) else {
            return true;
        };
        if self.calibrate {
            return !shared.calibrating();
        }
        if self.settle {
            return !h.busy.load(Ordering::Acquire);
        }
        let t = h.temp.get();
        !t.is_nan() && self.min.is_none_or(|m| t >= m) && self.max.is_none_or(|m| t <= m)
    }
}

/// Applies `cmd` to the heaters; returns the wait the G-code must hold for, if any.
pub fn apply(thermal: &Thermal, shared: &HeaterShared, cmd: &HeatCmd) -> Result<Option<Wait>, HeatError> {
    match cmd {
        HeatCmd::Set { heater, target, wait } => set_target(thermal, shared, heater, *target, *wait),
        HeatCmd::PidCalibrate { heater, target, .. } => {
            pid_calibrate(thermal, shared, heater, *target).map(Some)
        }
        HeatCmd::Wait { sensor, min, max } => temperature_wait(thermal, sensor, *min, *max).map(Some),
        HeatCmd::TurnOffAll | HeatCmd::EmergencyStop => {
            shared.turn_off_all();
            Ok(None)
        }
        HeatCmd::Report | HeatCmd::SaveConfig => Ok(None),
        HeatCmd::Fan { speed } => {
            shared.set_fan("fan", *speed);
            Ok(None)
        }
        HeatCmd::FanSpeed { fan, speed } => {
            let i = thermal
                .fan("fan_generic", fan)
                .ok_or_else(|| not_valid(fan, "FAN"))?;
            shared.set_fan_index(i, *speed);
            Ok(None)
        }
        HeatCmd::TemperatureFanTarget {
            fan,
            target,
            min_speed,
            max_speed,
        } => temperature_fan_target(thermal, shared, fan, *target, [*min_speed, *max_speed]).map(|()| None),
    }
}

/// The heater's range check: 0 (off) or `min_temp`..`max_temp`.
fn check_range(target: f64, min: f64, max: f64) -> Result<(), HeatError> {
    match target != 0.0 && (target < min || target > max) {
        true => Err(HeatError::OutOfRange { target, min, max }),
        false => Ok(()),
    }
}

/// M104/M140/M109/M190/SET_HEATER_TEMPERATURE: the target set; M109/M190 wait for it.
fn set_target(
    thermal: &Thermal,
    shared: &HeaterShared,
    heater: &str,
    target: f64,
    wait: bool,
) -> Result<Option<Wait>, HeatError> {
    let i = thermal
        .heater(heater)
        .ok_or_else(|| not_valid(heater, "HEATER"))?;
    let h = &thermal.heaters[i];
    check_range(target, h.min_temp, h.max_temp)?;
    shared.set_target(i, target);
    Ok(wait.then_some(Wait {
        heater: i,
        sensor: false,
        what: if heater == "heater_bed" { "M190" } else { "M109" },
        settle: true,
        min: None,
        max: None,
        target,
        calibrate: false,
    }))
}

/// PID_CALIBRATE: the relay test started; the G-code waits for its end.
fn pid_calibrate(
    thermal: &Thermal,
    shared: &HeaterShared,
    heater: &str,
    target: f64,
) -> Result<Wait, HeatError> {
    let i = thermal
        .heater(heater)
        .ok_or_else(|| HeatError::UnknownHeater(heater.to_string()))?;
    let h = &thermal.heaters[i];
    if target < h.min_temp || target > h.max_temp {
        return Err(HeatError::OutOfRange {
            target,
            min: h.min_temp,
            max: h.max_temp,
        });
    }
    if !shared.start_calibration(i, target) {
        return Err(HeatError::CalibrationRunning);
    }
    Ok(Wait {
        heater: i,
        sensor: false,
        what: "PID_CALIBRATE",
        settle: false,
        min: None,
        max: None,
        target,
        calibrate: true,
    })
}

/// TEMPERATURE_WAIT on a heater or a temperature sensor.
fn temperature_wait(
    thermal: &Thermal,
    sensor: &str,
    min: Option<f64>,
    max: Option<f64>,
) -> Result<Wait, HeatError> {
    let (i, is_sensor) = match (thermal.heater(sensor), thermal.sensor(sensor)) {
        (Some(i), _) => (i, false),
        (None, Some(i)) => (i, true),
        (None, None) => return Err(HeatError::UnknownSensor(sensor.to_string())),
    };
    Ok(Wait {
        heater: i,
        sensor: is_sensor,
        what: "TEMPERATURE_WAIT",
        settle: false,
        min,
        max,
        target: min.or(max).unwrap_or(0.0),
        calibrate: false,
    })
}

/// SET_TEMPERATURE_FAN_TARGET: the fan's target and its speed range (`[min, max]`, each
/// kept when not given).
fn temperature_fan_target(
    thermal: &Thermal,
    shared: &HeaterShared,
    fan: &str,
    target: Option<f64>,
    speeds: [Option<f64>; 2],
) -> Result<(), HeatError> {
    let i = thermal
        .fan("temperature_fan", fan)
        .ok_or_else(|| not_valid(fan, "TEMPERATURE_FAN"))?;
    let super::objects::FanRole::Temperature {
        target_temp,
        min_temp,
        max_temp,
        ..
    } = thermal.fans[i].role
    else {
        return Err(not_valid(fan, "TEMPERATURE_FAN"));
    };
    let cell = &shared.fans[i];
    let target = target.unwrap_or(target_temp);
    check_range(target, min_temp, max_temp)?;
    let min = speeds[0].unwrap_or(cell.min_speed.get());
    let max = speeds[1].unwrap_or(cell.max_speed.get());
    if min > max {
        return Err(HeatError::MinAboveMax { min, max });
    }
    cell.target.set(target);
    cell.min_speed.set(min.clamp(0.0, 1.0));
    cell.max_speed.set(max.clamp(0.0, 1.0));
    Ok(())
}

/// Klipper's refusal of an extruding move while the extruder `extruder` (its heater's name)
/// is below `min_extrude_temp`.
pub fn can_extrude(thermal: &Thermal, shared: &HeaterShared, extruder: &str) -> Result<(), HeatError> {
    for (h, cell) in thermal.heaters.iter().zip(&shared.heaters) {
        let Some(min) = h.min_extrude_temp.filter(|_| h.name == extruder) else {
            continue;
        };
        let t = cell.temp.get();
        if min > 0.0 && (t.is_nan() || t < min) {
            return Err(HeatError::ColdExtrude {
                heater: h.name.clone(),
                temp: if t.is_nan() { 0.0 } else { t },
                min,
            });
        }
    }
    Ok(())
}

/// The waits of a print, for its summary.
#[derive(Debug, Default)]
pub struct HeatLog {
    waits: Vec<String>,
}

impl HeatLog {
    /// A finished wait: MCU seconds of the heater's reports at its start and end, wall seconds.
    pub fn record(&mut self, wait: &Wait, start: Option<f64>, end: Option<f64>, wall_s: f64) {
        let mcu = match (start, end) {
            (Some(a), Some(b)) => format!("{:.1} s", b - a),
            _ => "?".to_string(),
        };
        self.waits.push(format!(
            "{} waited {mcu} of printer time ({wall_s:.1} s wall) for {} °C",
            wait.what, wait.target
        ));
    }

    /// A line for the summary as it is (PID_CALIBRATE's result, SAVE_CONFIG's file).
    pub fn note(&mut self, text: String) {
        self.waits.push(text);
    }

    /// An M105 report (kept for the summary, the latest few).
    pub fn report(&mut self, text: String) {
        if self.waits.iter().filter(|w| w.starts_with("M105")).count() < 8 {
            self.waits.push(format!("M105: {text}"));
        }
    }

    /// The summary's heater lines: each heater's state at the end and the waits.
    pub fn lines(&mut self, shared: Option<&HeaterShared>) -> Vec<String> {
        let Some(shared) = shared else {
            return Vec::new();
        };
        let fmt = |t: f64| {
            if t.is_nan() {
                "no reading".to_string()
            } else {
                format!("{t:.1} °C")
            }
        };
        let mut out = Vec::new();
        for h in &shared.heaters {
            out.push(format!(
                "heater {}: {} (highest {}), target {:.1} °C, power {:.0} %",
                h.name,
                fmt(h.temp.get()),
                fmt(h.max_seen.get()),
                h.target.get(),
                h.power.get() * 100.0
            ));
        }
        for s in shared.sensors.iter().filter(|s| s.kind == "temperature_sensor") {
            out.push(format!(
                "{} {}: {} (lowest {}, highest {})",
                s.kind,
                s.name,
                fmt(s.temp.get()),
                fmt(s.min_seen.get()),
                fmt(s.max_seen.get())
            ));
        }
        for f in &shared.fans {
            let target = match f.sensor.and_then(|i| shared.sensors.get(i)) {
                Some(sensor) => format!(
                    ", sensor {:.1} °C, target {:.1} °C",
                    sensor.temp.get(),
                    f.target.get()
                ),
                None => String::new(),
            };
            let rpm = f.rpm.get();
            let rpm = if rpm.is_nan() {
                String::new()
            } else {
                format!(", {rpm:.0} rpm")
            };
            out.push(format!(
                "{} {}: {:.0} %{target}{rpm}",
                f.kind,
                f.name,
                f.speed.get() * 100.0
            ));
        }
        out.extend(self.waits.drain(..).map(|w| format!("heaters: {w}")));
        if let Some(fault) = shared.fault() {
            out.push(format!("heaters: shut down: {fault}"));
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::borrow::Cow;

    fn setup() -> (Thermal, HeaterShared) {
        let cfg = sysconfig::builtin_simulated().unwrap();
        let t = Thermal::from_config(&cfg).unwrap();
        let s = HeaterShared::new(&t);
        (t, s)
    }

    fn set(heater: &'static str, target: f64, wait: bool) -> HeatCmd {
        HeatCmd::Set {
            heater: Cow::Borrowed(heater),
            target,
            wait,
        }
    }

    #[test]
    fn targets_out_of_range_are_refused_as_klipper_words_it() {
        let (t, s) = setup();
        assert_eq!(
            apply(&t, &s, &set("extruder", 300.0, false)).map_err(|e| e.to_string()),
            Err("Requested temperature (300.0) out of range (0.0:250.0)".to_string())
        );
        assert_eq!(apply(&t, &s, &set("extruder", 210.0, false)), Ok(None));
        assert_eq!(s.heaters[0].target.get(), 210.0);
        let w = apply(&t, &s, &set("heater_bed", 60.0, true)).unwrap().unwrap();
        assert_eq!((w.heater, w.what), (1, "M190"));
        assert!(!w.done(&s), "busy from the moment the target is set");
        assert!(apply(&t, &s, &set("chamber", 60.0, false)).is_err());
        apply(&t, &s, &HeatCmd::TurnOffAll).unwrap();
        assert_eq!(s.heaters[0].target.get(), 0.0);
    }

    #[test]
    fn extrusion_needs_min_extrude_temp() {
        let cfg = sysconfig::parse_str(
            &sysconfig::printer::SIMULATED_PRINTER_CFG
                .replace("min_extrude_temp: 0", "min_extrude_temp: 170"),
            std::path::Path::new("printer.cfg"),
        )
        .unwrap();
        let t = Thermal::from_config(&cfg).unwrap();
        let s = HeaterShared::new(&t);
        let e = can_extrude(&t, &s, "extruder").unwrap_err().to_string();
        assert!(e.starts_with("Extrude below minimum temp"), "{e}");
        s.heaters[0].temp.set(171.0);
        assert_eq!(can_extrude(&t, &s, "extruder"), Ok(()));
        let w = Wait {
            heater: 0,
            sensor: false,
            what: "TEMPERATURE_WAIT",
            settle: false,
            min: Some(170.0),
            max: None,
            target: 170.0,
            calibrate: false,
        };
        assert!(w.done(&s));
    }
}
