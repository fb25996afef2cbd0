//! Typed readers of the thermal sections beyond `[extruder]`/`[heater_bed]`: `[heater_generic]`,
//! `[verify_heater]`, `[thermistor]`, `[temperature_sensor]`, and the fans (`[fan]`,
//! `[heater_fan]`, `[controller_fan]`, `[fan_generic]`, `[temperature_fan]`), with Klipper's
//! options, defaults and bounds.
//!
//! The load reads every one of them ([`DRIVEN`]): the host drives them all.

use super::error::{ConfigError, ValueProblem};
use super::heater::{read_heater_options, HeaterSection, ABSOLUTE_ZERO_C};
use super::pins::{PinKind, PinRef, PinRegistry, Share};
use super::reader::{Bounds, Reader, SectionReader};
use super::HeaterControl;

/// Where a sensor's temperature comes from.
#[derive(Debug, Clone, PartialEq)]
pub enum SensorSource {
    /// An ADC pin (thermistors, RTDs, amplifiers) with its divider.
    Adc {
        /// The pin.
        sensor_pin: PinRef,
        /// `pullup_resistor` (Ω, default 4700).
        pullup_resistor: f64,
        /// `inline_resistor` (Ω, default 0).
        inline_resistor: f64,
    },
    /// `temperature_mcu`: the MCU's own sensor, read through its `ADC_TEMPERATURE` channel.
    Mcu {
        /// `sensor_mcu` (default `mcu`).
        sensor_mcu: String,
        /// `sensor_temperature1` (°C) and `sensor_adc1` (0..1): with it the calibration's line
        /// goes through this point (Klipper keeps the MCU family's slope).
        point1: Option<(f64, f64)>,
        /// `sensor_temperature2` and `sensor_adc2` (only with the first): the slope through
        /// both points.
        point2: Option<(f64, f64)>,
    },
    /// An SPI temperature chip (MAX6675, MAX31855, MAX31856, MAX31865).
    Spi(Box<super::spi_sensor::SpiSensorSection>),
    /// `temperature_host`: the host's own temperature from `sensor_path`.
    Host {
        /// Default `/sys/class/thermal/thermal_zone0/temp`.
        sensor_path: String,
    },
}

/// A sensor as `[temperature_sensor]` and `[temperature_fan]` take it.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorSection {
    /// `sensor_type` as written.
    pub sensor_type: String,
    /// Where readings come from.
    pub source: SensorSource,
    /// `smooth_time` (s, default 1).
    pub smooth_time: f64,
}

/// `[temperature_sensor NAME]`.
#[derive(Debug, Clone, PartialEq)]
pub struct TemperatureSensorSection {
    /// NAME.
    pub name: String,
    /// The sensor.
    pub sensor: SensorSection,
    /// `min_temp` (°C, default absolute zero).
    pub min_temp: f64,
    /// `max_temp` (°C, default 99999999.9).
    pub max_temp: f64,
    /// `gcode_id` for M105.
    pub gcode_id: Option<String>,
}

/// `[verify_heater HEATER]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VerifyHeaterSection {
    /// `max_error` (default 120).
    pub max_error: f64,
    /// `check_gain_time` (s, default 20; 60 for `heater_bed`).
    pub check_gain_time: f64,
    /// `hysteresis` (°C, default 5).
    pub hysteresis: f64,
    /// `heating_gain` (°C, default 2).
    pub heating_gain: f64,
}

impl VerifyHeaterSection {
    /// Klipper's defaults for heater `name`.
    pub fn defaults_for(name: &str) -> VerifyHeaterSection {
        VerifyHeaterSection {
            max_error: 120.0,
            check_gain_time: if name == "heater_bed" { 60.0 } else { 20.0 },
            hysteresis: 5.0,
            heating_gain: 2.0,
        }
    }
}

/// `[thermistor NAME]`: a custom thermistor usable as `sensor_type: NAME`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ThermistorSection {
    /// `temperature1`, `resistance1`, `beta`.
    Beta {
        /// °C.
        t1: f64,
        /// Ω.
        r1: f64,
        /// β.
        beta: f64,
    },
    /// Three (°C, Ω) points.
    Points([(f64, f64); 3]),
}

/// The options every fan has (`[fan]` and the named fans).
#[derive(Debug, Clone, PartialEq)]
pub struct FanOptions {
    /// `pin`.
    pub pin: PinRef,
    /// `max_power` (0, 1], default 1.
    pub max_power: f64,
    /// `kick_start_time` (s, default 0.1).
    pub kick_start_time: f64,
    /// `off_below` [0, 1], default 0.
    pub off_below: f64,
    /// `cycle_time` (s, default 0.010).
    pub cycle_time: f64,
    /// `hardware_pwm` (default false).
    pub hardware_pwm: bool,
    /// `shutdown_speed` [0, 1] (default 0; 1 for `[heater_fan]`).
    pub shutdown_speed: f64,
    /// `enable_pin`.
    pub enable_pin: Option<PinRef>,
    /// `tachometer_pin`.
    pub tachometer_pin: Option<PinRef>,
    /// `tachometer_ppr` (default 2).
    pub tachometer_ppr: u32,
    /// `tachometer_poll_interval` (s, default 0.0015).
    pub tachometer_poll_interval: f64,
}

/// `[heater_fan NAME]`.
#[derive(Debug, Clone, PartialEq)]
pub struct HeaterFanSection {
    /// NAME.
    pub name: String,
    /// Fan options.
    pub fan: FanOptions,
    /// `heater` (default `extruder`).
    pub heaters: Vec<String>,
    /// `heater_temp` (°C, default 50).
    pub heater_temp: f64,
    /// `fan_speed` [0, 1], default 1.
    pub fan_speed: f64,
}

/// `[controller_fan NAME]`.
#[derive(Debug, Clone, PartialEq)]
pub struct ControllerFanSection {
    /// NAME.
    pub name: String,
    /// Fan options.
    pub fan: FanOptions,
    /// `fan_speed` [0, 1], default 1.
    pub fan_speed: f64,
    /// `idle_speed` [0, 1], default `fan_speed`.
    pub idle_speed: f64,
    /// `idle_timeout` (s, default 30).
    pub idle_timeout: u32,
    /// `heater` (default `extruder`).
    pub heaters: Vec<String>,
    /// `stepper` (empty: every stepper).
    pub steppers: Vec<String>,
}

/// `[temperature_fan NAME]`.
#[derive(Debug, Clone, PartialEq)]
pub struct TemperatureFanSection {
    /// NAME.
    pub name: String,
    /// Fan options.
    pub fan: FanOptions,
    /// The sensor.
    pub sensor: SensorSection,
    /// `min_temp` (°C).
    pub min_temp: f64,
    /// `max_temp` (°C).
    pub max_temp: f64,
    /// `control` (watermark or pid, as heaters).
    pub control: HeaterControl,
    /// `target_temp` (°C, default 40, within min..max).
    pub target_temp: f64,
    /// `max_speed` (0, 1], default 1.
    pub max_speed: f64,
    /// `min_speed` [0, 1], default 0.3.
    pub min_speed: f64,
    /// `gcode_id`.
    pub gcode_id: Option<String>,
}

/// Every thermal section of a config.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ThermalSections {
    /// `[heater_generic NAME]`.
    pub heater_generic: Vec<HeaterSection>,
    /// `[verify_heater HEATER]`, by heater name.
    pub verify_heater: Vec<(String, VerifyHeaterSection)>,
    /// `[thermistor NAME]`, by name.
    pub thermistors: Vec<(String, ThermistorSection)>,
    /// `[temperature_sensor NAME]`.
    pub temperature_sensors: Vec<TemperatureSensorSection>,
    /// `[fan]`.
    pub fan: Option<FanOptions>,
    /// `[heater_fan NAME]`.
    pub heater_fans: Vec<HeaterFanSection>,
    /// `[controller_fan NAME]`.
    pub controller_fans: Vec<ControllerFanSection>,
    /// `[fan_generic NAME]`, by name.
    pub fan_generic: Vec<(String, FanOptions)>,
    /// `[temperature_fan NAME]`.
    pub temperature_fans: Vec<TemperatureFanSection>,
    /// `[adc_scaled NAME]` (read before the sections naming its pins).
    pub adc_scaled: Vec<super::adc_scaled::AdcScaledSection>,
    /// `[multi_pin NAME]` (read before the sections naming its group).
    pub multi_pins: Vec<super::multi_pin::MultiPinSection>,
}

const UNIT: Bounds = Bounds::ANY.min(0.0).max(1.0);

fn arg_name(s: &SectionReader<'_>) -> String {
    s.arg().unwrap_or_default().to_string()
}

fn list(s: &SectionReader<'_>, option: &str, default: &[&str]) -> Vec<String> {
    match s.value(option) {
        Some(v) => v
            .text
            .split(',')
            .map(str::trim)
            .filter(|x| !x.is_empty())
            .map(String::from)
            .collect(),
        None => default.iter().map(|x| x.to_string()).collect(),
    }
}

fn read_sensor(s: &SectionReader<'_>, pins: &mut PinRegistry) -> Result<SensorSection, ConfigError> {
    let sensor_type = s.string("sensor_type")?;
    let source = match sensor_type.as_str() {
        "temperature_host" => SensorSource::Host {
            sensor_path: s
                .value("sensor_path")
                .map(|v| v.text.clone())
                .unwrap_or_else(|| "/sys/class/thermal/thermal_zone0/temp".into()),
        },
        "temperature_mcu" => read_mcu_sensor(s, pins)?,
        t => match super::spi_sensor::SpiChip::of(t) {
            Some(chip) => SensorSource::Spi(Box::new(super::spi_sensor::read_spi_sensor(s, pins, chip)?)),
            None => {
                super::heater::refuse_unsupported_sensor(s, &sensor_type)?;
                SensorSource::Adc {
                    sensor_pin: s.pin("sensor_pin", PinKind::Analog, pins, Share::Exclusive)?,
                    pullup_resistor: s.float_or("pullup_resistor", 4700.0, Bounds::ANY.above(0.0))?,
                    inline_resistor: s.float_or("inline_resistor", 0.0, Bounds::ANY.min(0.0))?,
                }
            }
        },
    };
    Ok(SensorSection {
        sensor_type,
        source,
        smooth_time: s.float_or("smooth_time", 1.0, Bounds::ANY.above(0.0))?,
    })
}

/// `sensor_type: temperature_mcu`'s options (Klipper's: `sensor_mcu`, and an optional
/// calibration by one or two points).
fn read_mcu_sensor(s: &SectionReader<'_>, pins: &PinRegistry) -> Result<SensorSource, ConfigError> {
    let sensor_mcu = s
        .value("sensor_mcu")
        .map_or_else(|| "mcu".to_string(), |v| v.text.clone());
    if let Some(v) = s.value("sensor_mcu") {
        if !pins.has_mcu(&sensor_mcu) {
            return Err(s.bad(
                "sensor_mcu",
                v,
                ValueProblem::Invalid(format!("there is no [mcu {sensor_mcu}] section")),
            ));
        }
    }
    let adc = Bounds::ANY.min(0.0).max(1.0);
    let temp = Bounds::ANY.min(ABSOLUTE_ZERO_C);
    let mut point1 = None;
    let mut point2 = None;
    if let Some(t1) = s.opt_float("sensor_temperature1", temp)? {
        point1 = Some((t1, s.float("sensor_adc1", adc)?));
        if let Some(t2) = s.opt_float("sensor_temperature2", temp)? {
            point2 = Some((t2, s.float("sensor_adc2", adc)?));
        }
    }
    Ok(SensorSource::Mcu {
        sensor_mcu,
        point1,
        point2,
    })
}

fn read_fan(
    s: &SectionReader<'_>,
    pins: &mut PinRegistry,
    default_shutdown_speed: f64,
) -> Result<FanOptions, ConfigError> {
    let max_power = s.float_or("max_power", 1.0, Bounds::ANY.above(0.0).max(1.0))?;
    Ok(FanOptions {
        pin: s.pin("pin", PinKind::Output, pins, Share::Exclusive)?,
        max_power,
        kick_start_time: s.float_or("kick_start_time", 0.1, Bounds::ANY.min(0.0))?,
        off_below: s.float_or("off_below", 0.0, UNIT)?,
        cycle_time: s.float_or("cycle_time", 0.010, Bounds::ANY.above(0.0))?,
        hardware_pwm: s.opt_bool("hardware_pwm")?.unwrap_or(false),
        shutdown_speed: s.float_or("shutdown_speed", default_shutdown_speed, UNIT)?,
        enable_pin: s.opt_pin("enable_pin", PinKind::Output, pins, Share::Exclusive)?,
        tachometer_pin: s.opt_pin("tachometer_pin", PinKind::Input, pins, Share::Exclusive)?,
        tachometer_ppr: s.int("tachometer_ppr", Some(2), 1..=i64::from(u32::MAX))?,
        tachometer_poll_interval: s.float_or("tachometer_poll_interval", 0.0015, Bounds::ANY.above(0.0))?,
    })
}

fn read_control(s: &SectionReader<'_>, max_delta_default: f64) -> Result<HeaterControl, ConfigError> {
    #[derive(Clone, Copy)]
    enum Kind {
        Watermark,
        Pid,
    }
    let kinds = [("watermark", Kind::Watermark), ("pid", Kind::Pid)];
    Ok(match s.choice("control", &kinds, None)? {
        Kind::Watermark => HeaterControl::Watermark {
            max_delta: s.float_or("max_delta", max_delta_default, Bounds::ANY.above(0.0))?,
        },
        Kind::Pid => HeaterControl::Pid {
            kp: s.float("pid_kp", Bounds::ANY)?,
            ki: s.float("pid_ki", Bounds::ANY)?,
            kd: s.float("pid_kd", Bounds::ANY)?,
        },
    })
}

fn gcode_id(s: &SectionReader<'_>) -> Option<String> {
    s.value("gcode_id").map(|v| v.text.clone())
}

fn read_thermistor(s: &SectionReader<'_>) -> Result<ThermistorSection, ConfigError> {
    let t1 = s.float("temperature1", Bounds::ANY.min(ABSOLUTE_ZERO_C))?;
    let r1 = s.float("resistance1", Bounds::ANY.min(0.0))?;
    if let Some(beta) = s.opt_float("beta", Bounds::ANY.above(0.0))? {
        return Ok(ThermistorSection::Beta { t1, r1, beta });
    }
    let t2 = s.float("temperature2", Bounds::ANY.min(ABSOLUTE_ZERO_C))?;
    let r2 = s.float("resistance2", Bounds::ANY.min(0.0))?;
    let t3 = s.float("temperature3", Bounds::ANY.min(ABSOLUTE_ZERO_C))?;
    let r3 = s.float("resistance3", Bounds::ANY.min(0.0))?;
    Ok(ThermistorSection::Points([(t1, r1), (t2, r2), (t3, r3)]))
}

/// The thermal section kinds the host drives (the load reads them; sections.rs lists them read).
pub const DRIVEN: &[&str] = &[
    "controller_fan",
    "fan",
    "fan_generic",
    "heater_fan",
    "heater_generic",
    "temperature_fan",
    "temperature_sensor",
    "thermistor",
    "verify_heater",
];

/// Reads the thermal sections of `reader` (marking them read): those the host drives, and
/// with `all` also `[controller_fan]`, `[fan_generic]` and `[temperature_fan]`.
pub(crate) fn read_thermal(
    reader: &Reader<'_>,
    pins: &mut PinRegistry,
    all: bool,
) -> Result<ThermalSections, ConfigError> {
    let mut out = ThermalSections::default();
    for s in reader.sections_with_arg("thermistor") {
        out.thermistors.push((arg_name(&s), read_thermistor(&s)?));
    }
    for s in reader.sections_with_arg("heater_generic") {
        let mut h = read_heater_options(&s, pins, false)?;
        h.name = arg_name(&s);
        out.heater_generic.push(h);
    }
    for s in reader.sections_with_arg("verify_heater") {
        let name = arg_name(&s);
        let d = VerifyHeaterSection::defaults_for(&name);
        out.verify_heater.push((
            name,
            VerifyHeaterSection {
                max_error: s.float_or("max_error", d.max_error, Bounds::ANY.min(0.0))?,
                check_gain_time: s.float_or("check_gain_time", d.check_gain_time, Bounds::ANY.min(1.0))?,
                hysteresis: s.float_or("hysteresis", d.hysteresis, Bounds::ANY.min(0.0))?,
                heating_gain: s.float_or("heating_gain", d.heating_gain, Bounds::ANY.above(0.0))?,
            },
        ));
    }
    for s in reader.sections_with_arg("temperature_sensor") {
        let sensor = read_sensor(&s, pins)?;
        let min_temp = s.float_or("min_temp", ABSOLUTE_ZERO_C, Bounds::ANY.min(ABSOLUTE_ZERO_C))?;
        out.temperature_sensors.push(TemperatureSensorSection {
            name: arg_name(&s),
            sensor,
            min_temp,
            max_temp: s.float_or("max_temp", 99_999_999.9, Bounds::ANY.above(min_temp))?,
            gcode_id: gcode_id(&s),
        });
    }
    if let Some(s) = reader.section("fan") {
        out.fan = Some(read_fan(&s, pins, 0.0)?);
    }
    for s in reader.sections_with_arg("heater_fan") {
        let fan = read_fan(&s, pins, 1.0)?;
        out.heater_fans.push(HeaterFanSection {
            name: arg_name(&s),
            fan,
            heaters: list(&s, "heater", &["extruder"]),
            heater_temp: s.float_or("heater_temp", 50.0, Bounds::ANY)?,
            fan_speed: s.float_or("fan_speed", 1.0, UNIT)?,
        });
    }
    if !all {
        return Ok(out);
    }
    for s in reader.sections_with_arg("controller_fan") {
        let fan = read_fan(&s, pins, 0.0)?;
        let fan_speed = s.float_or("fan_speed", 1.0, UNIT)?;
        out.controller_fans.push(ControllerFanSection {
            name: arg_name(&s),
            fan,
            fan_speed,
            idle_speed: s.float_or("idle_speed", fan_speed, UNIT)?,
            idle_timeout: s.int("idle_timeout", Some(30), 0..=i64::from(u32::MAX))?,
            heaters: list(&s, "heater", &["extruder"]),
            steppers: list(&s, "stepper", &[]),
        });
    }
    for s in reader.sections_with_arg("fan_generic") {
        out.fan_generic.push((arg_name(&s), read_fan(&s, pins, 0.0)?));
    }
    for s in reader.sections_with_arg("temperature_fan") {
        let fan = read_fan(&s, pins, 0.0)?;
        let sensor = read_sensor(&s, pins)?;
        let min_temp = s.float("min_temp", Bounds::ANY.min(ABSOLUTE_ZERO_C))?;
        let max_temp = s.float("max_temp", Bounds::ANY.above(min_temp))?;
        let max_speed = s.float_or("max_speed", 1.0, Bounds::ANY.above(0.0).max(1.0))?;
        out.temperature_fans.push(TemperatureFanSection {
            name: arg_name(&s),
            fan,
            sensor,
            min_temp,
            max_temp,
            control: read_control(&s, 2.0)?,
            target_temp: s.float_or("target_temp", 40.0, Bounds::ANY.min(min_temp).max(max_temp))?,
            max_speed,
            min_speed: s.float_or("min_speed", 0.3, Bounds::ANY.min(0.0).max(1.0))?,
            gcode_id: gcode_id(&s),
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ini;
    use std::path::Path;

    fn read(text: &str) -> Result<ThermalSections, String> {
        let file = ini::parse_str(text, Path::new("printer.cfg")).map_err(|e| e.to_string())?;
        let reader = Reader::new(&file);
        let t = read_thermal(&reader, &mut PinRegistry::new(vec!["mcu".into()]), true)
            .map_err(|e| e.to_string())?;
        reader.finish(|_| false).map_err(|e| e.to_string())?;
        Ok(t)
    }

    #[test]
    fn fans_with_klippers_defaults() {
        let t = read(
            "[fan]\npin: PH6\n\
             [heater_fan hotend_fan]\npin: PH4\nheater: extruder, heater_generic chamber\nheater_temp: 45\n\
             [controller_fan board]\npin: PH3\nidle_speed: 0.4\nstepper: stepper_x, stepper_y\n\
             [fan_generic aux]\npin: PH2\nmax_power: 0.6\nkick_start_time: 0.5\noff_below: 0.1\nhardware_pwm: true\ncycle_time: 0.002\n\
             [temperature_fan exhaust]\npin: PH1\nsensor_type: Generic 3950\nsensor_pin: PK7\nmin_temp: 0\nmax_temp: 80\ncontrol: watermark\ntarget_temp: 35\n",
        )
        .unwrap_or_else(|e| panic!("{e}"));
        let fan = t.fan.unwrap();
        assert_eq!(
            (
                fan.max_power,
                fan.kick_start_time,
                fan.off_below,
                fan.cycle_time,
                fan.hardware_pwm,
                fan.shutdown_speed
            ),
            (1.0, 0.1, 0.0, 0.010, false, 0.0)
        );
        assert_eq!(
            (fan.tachometer_ppr, fan.tachometer_poll_interval, fan.enable_pin),
            (2, 0.0015, None)
        );
        let hf = &t.heater_fans[0];
        assert_eq!(hf.name, "hotend_fan");
        assert_eq!(hf.heaters, ["extruder", "heater_generic chamber"]);
        assert_eq!(
            (hf.heater_temp, hf.fan_speed, hf.fan.shutdown_speed),
            (45.0, 1.0, 1.0)
        );
        let cf = &t.controller_fans[0];
        assert_eq!((cf.fan_speed, cf.idle_speed, cf.idle_timeout), (1.0, 0.4, 30));
        assert_eq!(
            (cf.heaters.clone(), cf.steppers.clone()),
            (
                vec!["extruder".to_string()],
                vec!["stepper_x".to_string(), "stepper_y".to_string()]
            )
        );
        let (name, g) = &t.fan_generic[0];
        assert_eq!(
            (
                name.as_str(),
                g.max_power,
                g.kick_start_time,
                g.off_below,
                g.hardware_pwm,
                g.cycle_time
            ),
            ("aux", 0.6, 0.5, 0.1, true, 0.002)
        );
        let tf = &t.temperature_fans[0];
        assert_eq!((tf.target_temp, tf.max_speed, tf.min_speed), (35.0, 1.0, 0.3));
        assert_eq!(tf.control, HeaterControl::Watermark { max_delta: 2.0 });
        assert_eq!(tf.sensor.sensor_type, "Generic 3950");
    }

    #[test]
    fn sensors_thermistors_generic_heaters_and_verify() {
        let t = read(
            "[thermistor my_ntc]\ntemperature1: 25\nresistance1: 100000\nbeta: 3950\n\
             [thermistor three]\ntemperature1: 25\nresistance1: 100000\ntemperature2: 150\nresistance2: 1641.9\ntemperature3: 250\nresistance3: 226.15\n\
             [temperature_sensor raspberry_pi]\nsensor_type: temperature_host\nmax_temp: 100\n\
             [temperature_sensor chamber]\nsensor_type: my_ntc\nsensor_pin: PK5\npullup_resistor: 2200\ngcode_id: C\n\
             [heater_generic chamber_heater]\nheater_pin: PH5\nsensor_type: PT1000\nsensor_pin: PK6\ncontrol: watermark\nmin_temp: 0\nmax_temp: 70\n\
             [verify_heater heater_bed]\n\
             [verify_heater extruder]\nmax_error: 200\nhysteresis: 8\n",
        )
        .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            t.thermistors[0],
            (
                "my_ntc".into(),
                ThermistorSection::Beta {
                    t1: 25.0,
                    r1: 100_000.0,
                    beta: 3950.0
                }
            )
        );
        assert_eq!(
            t.thermistors[1].1,
            ThermistorSection::Points([(25.0, 100_000.0), (150.0, 1641.9), (250.0, 226.15)])
        );
        let pi = &t.temperature_sensors[0];
        assert_eq!(
            pi.sensor.source,
            SensorSource::Host {
                sensor_path: "/sys/class/thermal/thermal_zone0/temp".into()
            }
        );
        assert_eq!((pi.min_temp, pi.max_temp), (ABSOLUTE_ZERO_C, 100.0));
        let chamber = &t.temperature_sensors[1];
        assert!(matches!(
            chamber.sensor.source,
            SensorSource::Adc {
                pullup_resistor: 2200.0,
                ..
            }
        ));
        assert_eq!(chamber.gcode_id.as_deref(), Some("C"));
        let g = &t.heater_generic[0];
        assert_eq!(
            (g.name.as_str(), g.max_temp, g.sensor_type.as_str()),
            ("chamber_heater", 70.0, "PT1000")
        );
        assert_eq!(
            t.verify_heater[0],
            (
                "heater_bed".into(),
                VerifyHeaterSection::defaults_for("heater_bed")
            )
        );
        assert_eq!(t.verify_heater[0].1.check_gain_time, 60.0);
        let v = t.verify_heater[1].1;
        assert_eq!(
            (v.max_error, v.check_gain_time, v.hysteresis, v.heating_gain),
            (200.0, 20.0, 8.0, 2.0)
        );
    }

    #[test]
    fn the_mcus_own_sensor() {
        let t = read(
            "[temperature_sensor board]\nsensor_type: temperature_mcu\nmax_temp: 100\n\
             [temperature_fan cpu]\npin: PH1\nsensor_type: temperature_mcu\nsensor_mcu: mcu\n\
             sensor_temperature1: 30\nsensor_adc1: 0.4\nsensor_temperature2: 110\nsensor_adc2: 0.5\n\
             min_temp: 0\nmax_temp: 90\ncontrol: watermark\n",
        )
        .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            t.temperature_sensors[0].sensor.source,
            SensorSource::Mcu {
                sensor_mcu: "mcu".into(),
                point1: None,
                point2: None
            }
        );
        assert_eq!(
            t.temperature_fans[0].sensor.source,
            SensorSource::Mcu {
                sensor_mcu: "mcu".into(),
                point1: Some((30.0, 0.4)),
                point2: Some((110.0, 0.5))
            }
        );
    }

    #[test]
    fn errors_name_file_line_section_and_option() {
        let cases = [
            ("[fan]\npin: PH6\nmax_power: 0\n", "printer.cfg:3: [fan] max_power: must be above 0, got 0"),
            ("[fan]\npin: PH6\nshutdown_speed: 2\n", "printer.cfg:3: [fan] shutdown_speed: must have maximum of 1, got 2"),
            ("[fan]\n", "printer.cfg:1: Option 'pin' in section 'fan' must be specified"),
            ("[fan]\npin: PH6\nspeed: 1\n", "printer.cfg:3: Option 'speed' is not valid in section 'fan'"),
            (
                "[heater_fan h]\npin: PH6\nfan_speed: 1.5\n",
                "printer.cfg:3: [heater_fan h] fan_speed: must have maximum of 1, got 1.5",
            ),
            (
                "[verify_heater extruder]\ncheck_gain_time: 0.5\n",
                "printer.cfg:2: [verify_heater extruder] check_gain_time: must have minimum of 1, got 0.5",
            ),
            (
                "[thermistor t]\ntemperature1: 25\nresistance1: 100000\n",
                "printer.cfg:1: Option 'temperature2' in section 'thermistor t' must be specified",
            ),
            (
                "[temperature_fan f]\npin: PH1\nsensor_type: Generic 3950\nsensor_pin: PK7\nmin_temp: 0\nmax_temp: 80\ncontrol: watermark\ntarget_temp: 90\n",
                "printer.cfg:8: [temperature_fan f] target_temp: must have maximum of 80, got 90",
            ),
            (
                "[temperature_sensor m]\nsensor_type: temperature_mcu\nsensor_mcu: ebb\n",
                "printer.cfg:3: [temperature_sensor m] sensor_mcu: there is no [mcu ebb] section",
            ),
            (
                "[temperature_sensor m]\nsensor_type: temperature_mcu\nsensor_temperature1: 25\nsensor_adc1: 1.5\n",
                "printer.cfg:4: [temperature_sensor m] sensor_adc1: must have maximum of 1, got 1.5",
            ),
            (
                "[temperature_sensor m]\nsensor_type: temperature_mcu\nsensor_temperature1: 25\n",
                "printer.cfg:1: Option 'sensor_adc1' in section 'temperature_sensor m' must be specified",
            ),
            (
                "[fan]\npin: PH6\n[fan_generic a]\npin: PH6\n",
                "printer.cfg:4: [fan_generic a] pin: pin 'PH6' is also used by [fan] pin",
            ),
            (
                "[heater_generic c]\nheater_pin: PH5\nsensor_type: PT1000\nsensor_pin: PK6\ncontrol: watermark\nmin_temp: 0\nmax_temp: 70\nmin_extrude_temp: 50\n",
                "printer.cfg:8: Option 'min_extrude_temp' is not valid in section 'heater_generic c'",
            ),
        ];
        for (text, want) in cases {
            assert_eq!(read(text).map(|_| ()), Err(want.to_string()), "{text}");
        }
    }
}
