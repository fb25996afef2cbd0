//! The thermal hardware as the host drives it: each heater (`[extruder]`, `[heater_bed]`,
//! `[heater_generic]`) with its sensor, control and `[verify_heater]` check, each ADC
//! `[temperature_sensor]` (and each `[temperature_fan]`'s sensor), and the fans (`[fan]`,
//! `[heater_fan]`, `[controller_fan]`, `[fan_generic]`, `[temperature_fan]`), resolved from printer.cfg
//! (sensor types looked up, `[thermistor]` definitions included), with their MCU objects and
//! Klipper's configuration commands for them (`config_digital_out` + `set_digital_out_pwm_cycle`
//! for PWM outputs, `config_analog_in` for sensors).
//!
//! Object ids: on each MCU the thermal objects follow the steppers, endstops, enable pins and
//! the trsync, in this order: each heater's PWM output then its ADC
//! input, each sensor's ADC input, each fan's output.

use links::dict::{Cmd, Dictionary};
use sysconfig::printer::{
    FanOptions, HeaterControl, HeaterSection, PinRef, PrinterConfig, SensorSection, SensorSource,
    SpiSensorSection, ThermistorSection, MULTI_PIN_CHIP,
};

use super::mcu_sensor::{McuSensor, McuSensorError, ADC_TEMPERATURE};
use super::thermistor::{Element, Sensor, SensorError, SteinhartHart};
use super::verify::VerifyConfig;

/// Klipper's longest time a heater PWM value may stay in force without a refresh (s): the
/// MCU's `max_duration` of every heater output.
pub const MAX_HEAT_TIME: f64 = 3.0;
/// The longest `max_duration` (s of MCU time) a time-scaled simulated MCU gets: see
/// [`Thermal::max_heat_time`].
pub const SIM_MAX_HEAT_TIME: f64 = 30.0;
/// ADC readings summed per report (Klipper's thermistor oversampling).
pub const SAMPLE_COUNT: u8 = 8;
/// Seconds between the readings of one report.
pub const SAMPLE_TIME: f64 = 0.001;
/// Seconds between reports.
pub const REPORT_TIME: f64 = 0.300;
/// Consecutive out-of-range reports after which the MCU shuts itself down.
pub const RANGE_CHECK_COUNT: u8 = 4;

impl SimKind {
    /// Its thermal constants (as `cadence-mcu --heater PIN=PIN,hotend|bed` simulates them).
    pub fn model(self) -> firmware::sim::heater::ThermalModel {
        match self {
            SimKind::Hotend => firmware::sim::heater::ThermalModel::HOTEND,
            SimKind::Bed => firmware::sim::heater::ThermalModel::BED,
        }
    }
}

/// The simulated thermal model a heater gets on the simulated printer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SimKind {
    /// A 40 W hotend.
    Hotend,
    /// A 150 W bed.
    Bed,
}

/// One heater.
#[derive(Debug, Clone)]
pub struct HeaterOut {
    /// `extruder`, `heater_bed`, or the NAME of `[heater_generic NAME]`.
    pub name: String,
    /// The MCU of its heater pin (its sensor's is `sensor_pin.mcu`, the same or another).
    pub mcu: String,
    pub heater_pin: PinRef,
    pub sensor_pin: PinRef,
    pub sensor: Sensor,
    pub max_power: f64,
    pub pwm_cycle_time: f64,
    pub smooth_time: f64,
    pub control: HeaterControl,
    pub min_temp: f64,
    pub max_temp: f64,
    /// `[extruder]`'s `min_extrude_temp`.
    pub min_extrude_temp: Option<f64>,
    pub verify: VerifyConfig,
    pub sim: SimKind,
    /// The `[adc_scaled]` chip (index in [`Thermal::scaled`]) its sensor pin is read through.
    pub sensor_scale: Option<usize>,
    /// An SPI temperature chip in place of the ADC (`sensor_pin` its chip select).
    pub spi: Option<SpiSensorSection>,
}

/// One ADC `[temperature_sensor NAME]`, or the sensor of `[temperature_fan NAME]`.
#[derive(Debug, Clone)]
pub struct SensorOut {
    pub name: String,
    /// The index (in [`Thermal::fans`]) of the temperature fan it belongs to.
    pub fan: Option<usize>,
    /// `gcode_id`: reported by M105 under it.
    pub gcode_id: Option<String>,
    pub mcu: String,
    pub pin: PinRef,
    /// The conversion; for the MCU's own sensor ([`SensorOut::internal`]) a placeholder until
    /// the MCU's type is known: use [`SensorOut::sensor_on`].
    pub sensor: Sensor,
    /// `temperature_mcu`: the MCU's own sensor, calibrated for the MCU's type.
    pub internal: Option<McuSensor>,
    /// The `[adc_scaled]` chip (index in [`Thermal::scaled`]) its pin is read through.
    pub scale: Option<usize>,
    /// An SPI temperature chip in place of the ADC (`pin` its chip select).
    pub spi: Option<SpiSensorSection>,
    pub smooth_time: f64,
    pub min_temp: f64,
    pub max_temp: f64,
}

/// What drives a fan.
#[derive(Debug, Clone, PartialEq)]
pub enum FanRole {
    /// `[fan]`: M106/M107.
    Part,
    /// `[heater_fan NAME]`: on at `fan_speed` while any of `heaters` is above `heater_temp`
    /// or has a target.
    Heater {
        heaters: Vec<String>,
        heater_temp: f64,
        fan_speed: f64,
    },
    /// `[controller_fan NAME]`: `fan_speed` while a stepper is enabled (a print runs) or one of
    /// `heaters` has a target, then `idle_speed` for `idle_timeout` seconds, then off.
    Controller {
        heaters: Vec<String>,
        fan_speed: f64,
        idle_speed: f64,
        idle_timeout: f64,
    },
    /// `[fan_generic NAME]`: SET_FAN_SPEED.
    Generic,
    /// `[temperature_fan NAME]`: cools sensor `sensor` (index in [`Thermal::sensors`]) to its
    /// target with its control (more speed when hotter), between `min_speed` and `max_speed`.
    Temperature {
        sensor: usize,
        control: HeaterControl,
        target_temp: f64,
        min_speed: f64,
        max_speed: f64,
        min_temp: f64,
        max_temp: f64,
    },
}

impl FanRole {
    /// Klipper's status object kind of the fan (`fan`, `heater_fan`, …).
    pub fn kind(&self) -> &'static str {
        match self {
            FanRole::Part => "fan",
            FanRole::Heater { .. } => "heater_fan",
            FanRole::Controller { .. } => "controller_fan",
            FanRole::Generic => "fan_generic",
            FanRole::Temperature { .. } => "temperature_fan",
        }
    }
}

/// One fan.
#[derive(Debug, Clone)]
pub struct FanOut {
    /// `fan` or the NAME of `[heater_fan NAME]`.
    pub name: String,
    pub mcu: String,
    pub opts: FanOptions,
    pub role: FanRole,
}

/// One `[adc_scaled NAME]`: the reference inputs of MCU `mcu`'s ADC.
#[derive(Debug, Clone)]
pub struct ScaledOut {
    pub name: String,
    pub mcu: String,
    pub vref_pin: PinRef,
    pub vssa_pin: PinRef,
    pub smooth_time: f64,
}

/// An output driven through `[multi_pin]`: its first pin is the output's own; the others get
/// the same commands.
#[derive(Debug, Clone, PartialEq)]
pub enum MultiOutput {
    /// Heater `i`'s PWM.
    Heater(usize),
    /// Fan `i`'s output.
    Fan(usize),
}

/// Every thermal object of the printer.
#[derive(Debug, Clone, Default)]
pub struct Thermal {
    /// The further pins of outputs named `multi_pin:NAME`.
    pub multi_outputs: Vec<(MultiOutput, Vec<PinRef>)>,
    /// `[adc_scaled]` chips.
    pub scaled: Vec<ScaledOut>,
    pub heaters: Vec<HeaterOut>,
    pub sensors: Vec<SensorOut>,
    pub fans: Vec<FanOut>,
    /// MCU seconds per wall second of a simulated printer (`[simulator] time_scale`, or the
    /// run's `--time-scale` written there); 0 or 1 = real time.
    pub sim_time_scale: f64,
}

/// Why the thermal sections describe nothing the host can drive; each names the section.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ThermalError {
    #[error("[{section}] sensor_type: {source}")]
    Sensor {
        section: String,
        #[source]
        source: SensorError,
    },
    #[error("[{section}] {what}")]
    Invalid { section: String, what: String },
}

/// Why an MCU's heater, sensor and fan objects cannot be configured.
#[derive(Debug, thiserror::Error)]
pub enum ObjectsError {
    /// The firmware lacks a command the objects need.
    #[error("the MCU has no {0} in its dictionary: it cannot drive heaters, sensors or fans")]
    MissingCommand(&'static str),
    /// A pin the MCU does not have.
    #[error(transparent)]
    Pin(#[from] crate::hardware::PinError),
    /// A command does not encode.
    #[error(transparent)]
    Dictionary(#[from] links::dict::DictError),
    /// A hardware-PWM fan on a `[multi_pin]` group.
    #[error("[{0}] hardware_pwm: a multi_pin group is driven with software PWM (set hardware_pwm: False)")]
    MultiPinHardwarePwm(String),
    /// `temperature_mcu` on an MCU it cannot be calibrated for.
    #[error("[temperature_sensor {section}] {source}")]
    McuSensor {
        section: String,
        #[source]
        source: McuSensorError,
    },
}

/// The object of one MCU's thermal list.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ThermalObject {
    /// Heater `i`'s PWM output.
    HeaterPwm(usize),
    /// Heater `i`'s ADC input.
    HeaterAdc(usize),
    /// Sensor `i`'s ADC input.
    SensorAdc(usize),
    /// Fan `i`'s output.
    Fan(usize),
    /// Further pin `j` of [`Thermal::multi_outputs`] entry `k`.
    MultiPwm(usize, usize),
    /// Fan `i`'s tachometer (a pulse counter on its `tachometer_pin`).
    Tach(usize),
    /// `[adc_scaled]` chip `i`'s `vref_pin` input.
    ScaledVref(usize),
    /// `[adc_scaled]` chip `i`'s `vssa_pin` input.
    ScaledVssa(usize),
    /// The SPI device of heater `i`'s SPI temperature chip (whose reader is its
    /// [`ThermalObject::HeaterAdc`]).
    HeaterSpi(usize),
    /// The SPI device of sensor `i`'s SPI temperature chip (whose reader is its
    /// [`ThermalObject::SensorAdc`]).
    SensorSpi(usize),
}

fn sensor_of(
    section: &str,
    sensor_type: &str,
    pullup: f64,
    inline: f64,
    thermistors: &[(String, ThermistorSection)],
) -> Result<Sensor, ThermalError> {
    let bad = |source| ThermalError::Sensor {
        section: section.to_string(),
        source,
    };
    if let Some((_, t)) = thermistors.iter().find(|(n, _)| n == sensor_type) {
        let sh = match *t {
            ThermistorSection::Beta { t1, r1, beta } => SteinhartHart::from_beta(t1, r1, beta),
            ThermistorSection::Points([a, b, c]) => SteinhartHart::from_points(a, b, c),
        }
        .map_err(bad)?;
        return Ok(Sensor {
            element: Element::Thermistor(sh),
            pullup,
            inline,
        });
    }
    Sensor::named(sensor_type, pullup, inline).map_err(bad)
}

/// A sensor read through an MCU's ADC: its MCU, pin, conversion and (for the MCU's own
/// sensor) calibration; `None` for the host's own sensor.
type AdcSensor = (String, PinRef, Sensor, Option<McuSensor>);

fn adc_sensor(
    section: &str,
    s: &SensorSection,
    thermistors: &[(String, ThermistorSection)],
) -> Result<Option<AdcSensor>, ThermalError> {
    Ok(match &s.source {
        SensorSource::Adc {
            sensor_pin,
            pullup_resistor,
            inline_resistor,
        } => {
            let sensor = sensor_of(
                section,
                &s.sensor_type,
                *pullup_resistor,
                *inline_resistor,
                thermistors,
            )?;
            Some((sensor_pin.mcu.clone(), sensor_pin.clone(), sensor, None))
        }
        SensorSource::Mcu {
            sensor_mcu,
            point1,
            point2,
        } => {
            let pin = PinRef {
                mcu: sensor_mcu.clone(),
                pin: ADC_TEMPERATURE.to_string(),
                invert: false,
                pullup: false,
                pulldown: false,
            };
            let placeholder = PLACEHOLDER;
            let internal = McuSensor {
                point1: *point1,
                point2: *point2,
            };
            Some((sensor_mcu.clone(), pin, placeholder, Some(internal)))
        }
        SensorSource::Spi(spi) => Some((
            spi.bus.cs_pin.mcu.clone(),
            spi.bus.cs_pin.clone(),
            PLACEHOLDER,
            None,
        )),
        SensorSource::Host { .. } => None,
    })
}

/// The SPI chip of sensor `s`, if it is one.
fn spi_of(s: &SensorSection) -> Option<SpiSensorSection> {
    match &s.source {
        SensorSource::Spi(spi) => Some(spi.as_ref().clone()),
        _ => None,
    }
}

/// The ADC conversion of a sensor that has none (an SPI chip converts its own readings; the
/// MCU's own sensor's is known once the MCU's type is).
const PLACEHOLDER: Sensor = Sensor {
    element: Element::Linear {
        base: 0.0,
        slope: 1.0,
    },
    pullup: 0.0,
    inline: 0.0,
};

/// `pin` as MCU outputs: `multi_pin:NAME` is the first pin of `[multi_pin NAME]` (inverted
/// when the reference is) and the further pins; any other pin is itself.
fn multi_pin(
    cfg: &PrinterConfig,
    section: &str,
    pin: &PinRef,
) -> Result<(PinRef, Vec<PinRef>), ThermalError> {
    if pin.mcu != MULTI_PIN_CHIP {
        return Ok((pin.clone(), Vec::new()));
    }
    let group = cfg
        .thermal
        .multi_pins
        .iter()
        .find(|g| g.name == pin.pin)
        .map(|g| &g.pins)
        .filter(|p| !p.is_empty())
        .ok_or_else(|| ThermalError::Invalid {
            section: section.to_string(),
            what: format!("there is no [multi_pin {}] section", pin.pin),
        })?;
    let pins: Vec<PinRef> = group
        .iter()
        .map(|p| PinRef {
            invert: p.invert != pin.invert,
            ..p.clone()
        })
        .collect();
    Ok((pins[0].clone(), pins[1..].to_vec()))
}

/// `pin` as its MCU reads it: `NAME:PIN` of `[adc_scaled NAME]` is PIN of the chip's MCU,
/// read through chip `NAME` (its index in `scaled`).
fn resolve_scaled(scaled: &[ScaledOut], pin: &PinRef) -> (PinRef, Option<usize>) {
    match scaled.iter().position(|c| c.name == pin.mcu) {
        Some(k) => (
            PinRef {
                mcu: scaled[k].mcu.clone(),
                ..pin.clone()
            },
            Some(k),
        ),
        None => (pin.clone(), None),
    }
}

impl SensorOut {
    /// The sensor's conversion on an MCU whose dictionary names its type `mcu_type`.
    pub fn sensor_on(&self, mcu_type: &str) -> Result<Sensor, McuSensorError> {
        match &self.internal {
            Some(m) => m.sensor(mcu_type),
            None => Ok(self.sensor),
        }
    }
}

impl Thermal {
    /// The longest time (s of MCU time) a heater's PWM value stays in force without a refresh:
    /// the `max_duration` of every heater output. Klipper's 3 s on a real board. A simulated MCU
    /// running N times faster than the wall clock gets the same 3 s of wall time, at most
    /// [`SIM_MAX_HEAT_TIME`] of its own: the host's heater loop lives in wall time, and a 3 s
    /// window of MCU time would be 60 ms of wall time at 50×, less than this VM's pauses (a
    /// simulated heater whose host is gone still turns itself off, 0.6 s of wall time later).
    pub fn max_heat_time(&self) -> f64 {
        (MAX_HEAT_TIME * self.sim_time_scale.max(1.0)).min(SIM_MAX_HEAT_TIME)
    }

    /// The thermal objects of `cfg`.
    pub fn from_config(cfg: &PrinterConfig) -> Result<Thermal, ThermalError> {
        let mut out = Thermal::default();
        if cfg.mcus.iter().any(|m| m.is_simulated()) {
            out.sim_time_scale = cfg.simulator.time_scale;
        }
        out.scaled = cfg
            .thermal
            .adc_scaled
            .iter()
            .map(|a| ScaledOut {
                name: a.name.clone(),
                mcu: a.vref_pin.mcu.clone(),
                vref_pin: a.vref_pin.clone(),
                vssa_pin: a.vssa_pin.clone(),
                smooth_time: a.smooth_time,
            })
            .collect();
        out.add_heaters(cfg)?;
        out.add_sensors(cfg)?;
        out.add_fans(cfg)?;
        out.add_temperature_fans(cfg)?;
        out.expand_multi_fans(cfg)?;
        out.check_fans()?;
        Ok(out)
    }

    /// The extruder's, the bed's and every `[heater_generic]`, each with its
    /// `[verify_heater]` (every one of which must name a heater).
    fn add_heaters(&mut self, cfg: &PrinterConfig) -> Result<(), ThermalError> {
        let th = &cfg.thermal;
        let sections: Vec<(&HeaterSection, bool)> = cfg
            .extruders()
            .map(|e| (&e.heater, true))
            .chain(cfg.heater_bed.iter().map(|h| (h, false)))
            .chain(th.heater_generic.iter().map(|h| (h, false)))
            .collect();
        for (h, extruder) in sections {
            let section = if extruder || h.name == "heater_bed" {
                h.name.clone()
            } else {
                format!("heater_generic {}", h.name)
            };
            let (heater_pin, more) = multi_pin(cfg, &section, &h.heater_pin)?;
            if !more.is_empty() {
                self.multi_outputs
                    .push((MultiOutput::Heater(self.heaters.len()), more));
            }
            let (sensor_pin, sensor_scale) = resolve_scaled(&self.scaled, &h.sensor_pin);
            let sensor = match h.spi {
                Some(_) => PLACEHOLDER,
                None => sensor_of(
                    &section,
                    &h.sensor_type,
                    h.pullup_resistor,
                    h.inline_resistor,
                    &th.thermistors,
                )?,
            };
            let verify = th
                .verify_heater
                .iter()
                .find(|(n, _)| *n == h.name)
                .map(|(_, v)| VerifyConfig {
                    max_error: v.max_error,
                    check_gain_time: v.check_gain_time,
                    hysteresis: v.hysteresis,
                    heating_gain: v.heating_gain,
                })
                .unwrap_or_else(|| VerifyConfig::defaults_for(&h.name));
            self.heaters.push(HeaterOut {
                name: h.name.clone(),
                mcu: heater_pin.mcu.clone(),
                heater_pin,
                sensor_pin,
                sensor,
                max_power: h.max_power,
                pwm_cycle_time: h.pwm_cycle_time,
                smooth_time: h.smooth_time,
                control: h.control,
                min_temp: h.min_temp,
                max_temp: h.max_temp,
                min_extrude_temp: extruder.then_some(h.min_extrude_temp),
                verify,
                sim: if extruder { SimKind::Hotend } else { SimKind::Bed },
                sensor_scale,
                spi: h.spi.clone(),
            });
        }
        for (name, _) in &th.verify_heater {
            if !self.heaters.iter().any(|h| &h.name == name) {
                return Err(ThermalError::Invalid {
                    section: format!("verify_heater {name}"),
                    what: format!("there is no heater '{name}'"),
                });
            }
        }
        Ok(())
    }

    /// The `[temperature_sensor]`s read through an MCU's ADC (thermistors and the like, and
    /// the MCU's own sensor).
    fn add_sensors(&mut self, cfg: &PrinterConfig) -> Result<(), ThermalError> {
        let th = &cfg.thermal;
        for s in &th.temperature_sensors {
            let section = format!("temperature_sensor {}", s.name);
            let Some((_, pin, sensor, internal)) = adc_sensor(&section, &s.sensor, &th.thermistors)? else {
                // temperature_host is read from the host's own sysfs, no MCU object.
                continue;
            };
            let (pin, scale) = resolve_scaled(&self.scaled, &pin);
            self.sensors.push(SensorOut {
                name: s.name.clone(),
                fan: None,
                gcode_id: s.gcode_id.clone(),
                mcu: pin.mcu.clone(),
                pin,
                sensor,
                internal,
                scale,
                spi: spi_of(&s.sensor),
                smooth_time: s.sensor.smooth_time,
                min_temp: s.min_temp,
                max_temp: s.max_temp,
            });
        }
        Ok(())
    }

    /// `[fan]`, `[heater_fan]`s, `[controller_fan]`s (their heaters must exist) and
    /// `[fan_generic]`s.
    fn add_fans(&mut self, cfg: &PrinterConfig) -> Result<(), ThermalError> {
        let th = &cfg.thermal;
        if let Some(f) = &th.fan {
            self.fans.push(FanOut {
                name: "fan".to_string(),
                mcu: f.pin.mcu.clone(),
                opts: f.clone(),
                role: FanRole::Part,
            });
        }
        for f in &th.heater_fans {
            for h in &f.heaters {
                if !self.heaters.iter().any(|x| &x.name == h) {
                    return Err(ThermalError::Invalid {
                        section: format!("heater_fan {}", f.name),
                        what: format!("heater: there is no heater '{h}'"),
                    });
                }
            }
            self.fans.push(FanOut {
                name: f.name.clone(),
                mcu: f.fan.pin.mcu.clone(),
                opts: f.fan.clone(),
                role: FanRole::Heater {
                    heaters: f.heaters.clone(),
                    heater_temp: f.heater_temp,
                    fan_speed: f.fan_speed,
                },
            });
        }
        for f in &th.controller_fans {
            for h in &f.heaters {
                if !self.heaters.iter().any(|x| &x.name == h) {
                    return Err(ThermalError::Invalid {
                        section: format!("controller_fan {}", f.name),
                        what: format!("heater: there is no heater '{h}'"),
                    });
                }
            }
            self.fans.push(FanOut {
                name: f.name.clone(),
                mcu: f.fan.pin.mcu.clone(),
                opts: f.fan.clone(),
                role: FanRole::Controller {
                    heaters: f.heaters.clone(),
                    fan_speed: f.fan_speed,
                    idle_speed: f.idle_speed,
                    idle_timeout: f64::from(f.idle_timeout),
                },
            });
        }
        for (name, opts) in &th.fan_generic {
            self.fans.push(FanOut {
                name: name.clone(),
                mcu: opts.pin.mcu.clone(),
                opts: opts.clone(),
                role: FanRole::Generic,
            });
        }
        Ok(())
    }

    /// `[temperature_fan]`s: a sensor and the fan it drives.
    fn add_temperature_fans(&mut self, cfg: &PrinterConfig) -> Result<(), ThermalError> {
        let th = &cfg.thermal;
        for f in &th.temperature_fans {
            let section = format!("temperature_fan {}", f.name);
            let Some((_, pin, sensor, internal)) = adc_sensor(&section, &f.sensor, &th.thermistors)? else {
                return Err(ThermalError::Invalid {
                    section,
                    what: "sensor_type: only sensors on an MCU can drive a temperature fan".to_string(),
                });
            };
            let (pin, scale) = resolve_scaled(&self.scaled, &pin);
            self.sensors.push(SensorOut {
                name: f.name.clone(),
                fan: Some(self.fans.len()),
                gcode_id: f.gcode_id.clone(),
                mcu: pin.mcu.clone(),
                pin,
                sensor,
                internal,
                scale,
                spi: spi_of(&f.sensor),
                smooth_time: f.sensor.smooth_time,
                min_temp: f.min_temp,
                max_temp: f.max_temp,
            });
            self.fans.push(FanOut {
                name: f.name.clone(),
                mcu: f.fan.pin.mcu.clone(),
                opts: f.fan.clone(),
                role: FanRole::Temperature {
                    sensor: self.sensors.len() - 1,
                    control: f.control,
                    target_temp: f.target_temp,
                    min_speed: f.min_speed,
                    max_speed: f.max_speed,
                    min_temp: f.min_temp,
                    max_temp: f.max_temp,
                },
            });
        }
        Ok(())
    }

    /// Fans whose pin is `multi_pin:NAME`: the group's first pin is theirs, the others follow.
    fn expand_multi_fans(&mut self, cfg: &PrinterConfig) -> Result<(), ThermalError> {
        for i in 0..self.fans.len() {
            let f = &self.fans[i];
            let (pin, more) = multi_pin(cfg, &f.name, &f.opts.pin)?;
            if more.is_empty() && pin == f.opts.pin {
                continue;
            }
            let f = &mut self.fans[i];
            f.mcu = pin.mcu.clone();
            f.opts.pin = pin;
            if !more.is_empty() {
                self.multi_outputs.push((MultiOutput::Fan(i), more));
            }
        }
        Ok(())
    }

    /// Refuses the fan options the MCUs cannot serve.
    fn check_fans(&self) -> Result<(), ThermalError> {
        for f in &self.fans {
            if f.opts.enable_pin.is_some() {
                return Err(ThermalError::Invalid {
                    section: f.name.clone(),
                    what: "enable_pin: is not supported by Cadence yet (fan enable pins)".to_string(),
                });
            }
        }
        Ok(())
    }

    /// The heater called `name`.
    pub fn heater(&self, name: &str) -> Option<usize> {
        self.heaters.iter().position(|h| h.name == name)
    }

    /// The `[temperature_sensor]` or `[temperature_fan]` sensor called `name`
    /// (`temperature_sensor chamber`, `temperature_fan exhaust`, or the bare name).
    pub fn sensor(&self, name: &str) -> Option<usize> {
        self.sensors.iter().position(|s| {
            let kind = if s.fan.is_some() {
                "temperature_fan "
            } else {
                "temperature_sensor "
            };
            s.name == name || name.strip_prefix(kind) == Some(s.name.as_str())
        })
    }

    /// The fan called `name` with the role kind `kind` (`fan_generic`, `temperature_fan`).
    pub fn fan(&self, kind: &str, name: &str) -> Option<usize> {
        self.fans
            .iter()
            .position(|f| f.role.kind() == kind && f.name == name)
    }

    /// The thermal objects on MCU `mcu`, in oid order.
    pub fn objects_on(&self, mcu: &str) -> Vec<ThermalObject> {
        let mut v = Vec::new();
        // A heater's output and sensor, each on its own MCU (usually the same, then the
        // sensor's oid follows the output's).
        for (i, h) in self.heaters.iter().enumerate() {
            if h.mcu == mcu {
                v.push(ThermalObject::HeaterPwm(i));
            }
            if h.sensor_pin.mcu == mcu {
                v.push(ThermalObject::HeaterAdc(i));
            }
        }
        v.extend(
            self.sensors
                .iter()
                .enumerate()
                .filter(|(_, s)| s.mcu == mcu)
                .map(|(i, _)| ThermalObject::SensorAdc(i)),
        );
        v.extend(
            self.fans
                .iter()
                .enumerate()
                .filter(|(_, f)| f.mcu == mcu)
                .map(|(i, _)| ThermalObject::Fan(i)),
        );
        for (k, (_, pins)) in self.multi_outputs.iter().enumerate() {
            v.extend(
                (0..pins.len())
                    .filter(|&j| pins[j].mcu == mcu)
                    .map(|j| ThermalObject::MultiPwm(k, j)),
            );
        }
        v.extend(
            self.fans
                .iter()
                .enumerate()
                .filter(|(_, f)| f.opts.tachometer_pin.as_ref().is_some_and(|p| p.mcu == mcu))
                .map(|(i, _)| ThermalObject::Tach(i)),
        );
        for (i, _) in self.scaled.iter().enumerate().filter(|(_, c)| c.mcu == mcu) {
            v.push(ThermalObject::ScaledVref(i));
            v.push(ThermalObject::ScaledVssa(i));
        }
        v.extend(
            self.heaters
                .iter()
                .enumerate()
                .filter(|(_, h)| h.sensor_pin.mcu == mcu && h.spi.is_some())
                .map(|(i, _)| ThermalObject::HeaterSpi(i)),
        );
        v.extend(
            self.sensors
                .iter()
                .enumerate()
                .filter(|(_, s)| s.mcu == mcu && s.spi.is_some())
                .map(|(i, _)| ThermalObject::SensorSpi(i)),
        );
        v
    }

    /// `cadence-mcu` arguments giving the simulated MCU `mcu` a spinning fan behind each fan
    /// output with a tachometer on it (`--fan OUT_PIN=TACH_PIN,PPR`).
    pub fn sim_fan_args(&self, mcu: &str) -> Vec<String> {
        self.fans
            .iter()
            .filter(|f| f.mcu == mcu)
            .filter_map(|f| {
                let t = f.opts.tachometer_pin.as_ref().filter(|t| t.mcu == mcu)?;
                Some([
                    "--fan".to_string(),
                    format!("{}={},{}", f.opts.pin.pin, t.pin, f.opts.tachometer_ppr),
                ])
            })
            .flatten()
            .collect()
    }

    /// `cadence-mcu` arguments giving the simulated MCU `mcu` the ADC references of its
    /// `[adc_scaled]` chips (`--adc-ref VREF_PIN=VSSA_PIN`).
    pub fn sim_adc_ref_args(&self, mcu: &str) -> Vec<String> {
        self.scaled
            .iter()
            .filter(|c| c.mcu == mcu)
            .flat_map(|c| {
                [
                    "--adc-ref".to_string(),
                    format!("{}={}", c.vref_pin.pin, c.vssa_pin.pin),
                ]
            })
            .collect()
    }

    /// `cadence-mcu` arguments giving the simulated MCU `mcu` a thermal model per heater
    /// (`--heater [!]HEATER_PIN=SENSOR_PIN,hotend|bed`, `!` for an inverted heater pin), and to each heater's and each ADC
    /// sensor's input the response of the sensor configured (`--sensor-curve`), so that the
    /// host reads the simulated temperature back.
    pub fn sim_args(&self, mcu: &str) -> Vec<String> {
        let mut args = Vec::new();
        for (i, h) in self.heaters.iter().enumerate() {
            let kind = match h.sim {
                SimKind::Hotend => "hotend",
                SimKind::Bed => "bed",
            };
            let low = if h.heater_pin.invert { "!" } else { "" };
            let local = h.sensor_pin.mcu == h.mcu;
            // A sensor on another MCU reads the heater's temperature through the world, which
            // the heater's MCU publishes under this name.
            let name = format!("heat{i}");
            if h.mcu == mcu {
                args.push("--heater".to_string());
                let sensor = if local { h.sensor_pin.pin.as_str() } else { NO_PIN };
                args.push(format!("{low}{}={sensor},{kind}", h.heater_pin.pin));
                if !local {
                    args.extend([
                        "--heater-export".to_string(),
                        format!("{}={name}", h.heater_pin.pin),
                    ]);
                }
            }
            if h.sensor_pin.mcu == mcu {
                if !local {
                    args.extend([
                        "--remote-sensor".to_string(),
                        format!("{}={name}", h.sensor_pin.pin),
                    ]);
                }
                match &h.spi {
                    Some(spi) => args.extend(spi_sensor_args(spi)),
                    None => args.extend(sensor_curve_args(&h.sensor_pin, &h.sensor)),
                }
            }
        }
        // A `temperature_mcu` sensor reads the simulated chip's own die (its ADC_TEMPERATURE
        // channel is not a pin the simulator takes a curve for).
        for s in self
            .sensors
            .iter()
            .filter(|s| s.mcu == mcu && s.pin.pin != ADC_TEMPERATURE)
        {
            match &s.spi {
                Some(spi) => args.extend(spi_sensor_args(spi)),
                None => args.extend(sensor_curve_args(&s.pin, &s.sensor)),
            }
        }
        args
    }

    /// The configuration commands of MCU `mcu`'s thermal objects, oids from `oid0`.
    pub fn config_commands(
        &self,
        dict: &Dictionary,
        mcu: &str,
        oid0: usize,
    ) -> Result<Vec<Cmd>, ObjectsError> {
        let objects = self.objects_on(mcu);
        if objects.is_empty() {
            return Ok(Vec::new());
        }
        for needed in [
            "config_digital_out",
            "set_digital_out_pwm_cycle",
            "config_analog_in",
        ] {
            if dict.command(needed).is_err() {
                return Err(ObjectsError::MissingCommand(needed));
            }
        }
        let clock_freq = dict.clock_freq()?;
        let mut cmds = Vec::new();
        for (k, obj) in objects.iter().enumerate() {
            let oid = (oid0 + k) as i64;
            let pin_of = |p: &PinRef, what: &str| pin_number(dict, p, what);
            let mut pwm =
                |pin: &PinRef, what: &str, cycle: f64, max_duration: f64| -> Result<(), ObjectsError> {
                    cmds.extend(soft_pwm(dict, clock_freq, oid, pin, what, cycle, max_duration)?);
                    Ok(())
                };
            match *obj {
                ThermalObject::HeaterPwm(i) => {
                    let h = &self.heaters[i];
                    pwm(
                        &h.heater_pin,
                        &format!("[{}] heater_pin", h.name),
                        h.pwm_cycle_time,
                        self.max_heat_time(),
                    )?;
                }
                ThermalObject::Fan(i) if self.fans[i].opts.hardware_pwm => {
                    cmds.push(self.hardware_pwm_fan(dict, clock_freq, oid, i)?);
                }
                ThermalObject::Fan(i) => {
                    let f = &self.fans[i];
                    pwm(&f.opts.pin, &format!("[{}] pin", f.name), f.opts.cycle_time, 0.0)?;
                }
                ThermalObject::HeaterAdc(i) => {
                    let h = &self.heaters[i];
                    let what = format!("[{}]", h.name);
                    if let Some(spi) = &h.spi {
                        let spi_oid = oid_of(&objects, oid0, ThermalObject::HeaterSpi(i));
                        cmds.extend(spi_reader_commands(dict, clock_freq, oid, spi_oid, spi, &what)?);
                        continue;
                    }
                    let pin = pin_of(&h.sensor_pin, &format!("{what} sensor_pin"))?;
                    cmds.push(dict.encode("config_analog_in", &[oid, pin])?);
                }
                // Configured with their readers.
                ThermalObject::HeaterSpi(_) | ThermalObject::SensorSpi(_) => {}
                ThermalObject::MultiPwm(k, j) => {
                    let (cycle, max_duration, what) = self.multi_pwm_settings(k)?;
                    pwm(&self.multi_outputs[k].1[j], &what, cycle, max_duration)?;
                }
                ThermalObject::Tach(i) => {
                    let f = &self.fans[i];
                    if dict.command("config_counter").is_err() {
                        return Err(ObjectsError::MissingCommand("config_counter"));
                    }
                    if let Some(t) = &f.opts.tachometer_pin {
                        let pin = pin_of(t, &format!("[{}] tachometer_pin", f.name))?;
                        cmds.push(dict.encode("config_counter", &[oid, pin, i64::from(t.pullup)])?);
                    }
                }
                ThermalObject::ScaledVref(i) | ThermalObject::ScaledVssa(i) => {
                    let c = &self.scaled[i];
                    let (pin, option) = match *obj {
                        ThermalObject::ScaledVref(_) => (&c.vref_pin, "vref_pin"),
                        _ => (&c.vssa_pin, "vssa_pin"),
                    };
                    let pin = pin_of(pin, &format!("[adc_scaled {}] {option}", c.name))?;
                    cmds.push(dict.encode("config_analog_in", &[oid, pin])?);
                }
                ThermalObject::SensorAdc(i) => {
                    let s = &self.sensors[i];
                    if let Some(spi) = &s.spi {
                        let spi_oid = oid_of(&objects, oid0, ThermalObject::SensorSpi(i));
                        let what = format!("[temperature_sensor {}]", s.name);
                        cmds.extend(spi_reader_commands(dict, clock_freq, oid, spi_oid, spi, &what)?);
                        continue;
                    }
                    let mcu_type = dict.config_str("MCU").unwrap_or_default();
                    s.sensor_on(&mcu_type).map_err(|source| ObjectsError::McuSensor {
                        section: s.name.clone(),
                        source,
                    })?;
                    let pin = pin_of(&s.pin, &format!("[temperature_sensor {}] sensor_pin", s.name))?;
                    cmds.push(dict.encode("config_analog_in", &[oid, pin])?);
                }
            }
        }
        Ok(cmds)
    }

    /// Klipper's hardware PWM for fan `i` (the chip's PWM unit, duty in 0..=PWM_MAX).
    fn hardware_pwm_fan(
        &self,
        dict: &Dictionary,
        clock_freq: f64,
        oid: i64,
        i: usize,
    ) -> Result<Cmd, ObjectsError> {
        let f = &self.fans[i];
        if dict.command("config_pwm_out").is_err() {
            return Err(ObjectsError::MissingCommand("config_pwm_out"));
        }
        let pwm_max = dict.config_f64("PWM_MAX")?.round() as i64;
        let off = if f.opts.pin.invert { pwm_max } else { 0 };
        let pin = pin_number(dict, &f.opts.pin, &format!("[{}] pin", f.name))?;
        let cycle_ticks = (f.opts.cycle_time * clock_freq).round().max(1.0) as i64;
        Ok(dict.encode("config_pwm_out", &[oid, pin, cycle_ticks, off, off, 0])?)
    }

    /// The PWM cycle, maximum duration and option name of `[multi_pin]` output `k`'s pins (a
    /// heater's or a software-PWM fan's).
    fn multi_pwm_settings(&self, k: usize) -> Result<(f64, f64, String), ObjectsError> {
        match self.multi_outputs[k].0 {
            MultiOutput::Heater(i) => Ok((
                self.heaters[i].pwm_cycle_time,
                self.max_heat_time(),
                format!("[{}] heater_pin", self.heaters[i].name),
            )),
            MultiOutput::Fan(i) if self.fans[i].opts.hardware_pwm => {
                Err(ObjectsError::MultiPinHardwarePwm(self.fans[i].name.clone()))
            }
            MultiOutput::Fan(i) => Ok((
                self.fans[i].opts.cycle_time,
                0.0,
                format!("[{}] pin", self.fans[i].name),
            )),
        }
    }
}

/// The oid of `obj` in `objects` (numbered from `oid0`).
fn oid_of(objects: &[ThermalObject], oid0: usize, obj: ThermalObject) -> i64 {
    (oid0 + objects.iter().position(|&o| o == obj).unwrap_or(0)) as i64
}

/// An SPI temperature chip's commands: its SPI device `spi_oid` (chip select `sensor_pin`,
/// the chip's SPI mode, its start-up configuration written with `spi_send`), then its reader
/// `oid` (`config_thermocouple`). `what` names the section in errors.
fn spi_reader_commands(
    dict: &Dictionary,
    clock_freq: f64,
    oid: i64,
    spi_oid: i64,
    spi: &SpiSensorSection,
    what: &str,
) -> Result<Vec<Cmd>, ObjectsError> {
    for needed in ["config_spi", "config_thermocouple"] {
        if dict.command(needed).is_err() {
            return Err(ObjectsError::MissingCommand(needed));
        }
    }
    let pin = |p: &PinRef, option: &str| pin_number(dict, p, &format!("{what} {option}"));
    let software = match &spi.bus.software {
        Some([sclk, mosi, miso]) => Some((
            pin(miso, "spi_software_miso_pin")?,
            pin(mosi, "spi_software_mosi_pin")?,
            pin(sclk, "spi_software_sclk_pin")?,
        )),
        None => None,
    };
    let pins = crate::spi_device::SpiPins {
        cs: pin(&spi.bus.cs_pin, "sensor_pin")?,
        software,
    };
    let mode = i64::from(spi.chip.spi_mode());
    let mut cmds = crate::spi_device::config_commands(
        dict,
        clock_freq,
        spi_oid,
        pins,
        spi.bus.bus.as_deref(),
        mode,
        spi.bus.speed,
    )?
    .to_vec();
    if let Some(bytes) = super::spi_sensor::init_bytes(spi) {
        use links::proto::format::Value;
        cmds.push(dict.encode_values("spi_send", &[Value::Int(spi_oid), Value::Bytes(&bytes)])?);
    }
    let chip = dict.enumeration("thermocouple_type", spi.chip.name())?;
    cmds.push(dict.encode("config_thermocouple", &[oid, spi_oid, chip])?);
    Ok(cmds)
}

/// The MCU's number for `p` (`what` names the option in the error).
fn pin_number(dict: &Dictionary, p: &PinRef, what: &str) -> Result<i64, crate::hardware::PinError> {
    dict.pin(&p.pin)
        .map(i64::from)
        .map_err(|source| crate::hardware::PinError {
            what: what.to_string(),
            source,
        })
}

/// A software-PWM output's configuration: off (inverted pins are active low) from the start
/// and on an MCU shutdown, turned off by the MCU itself after `max_duration` without an update
/// (0: never), at `cycle` seconds per period.
fn soft_pwm(
    dict: &Dictionary,
    clock_freq: f64,
    oid: i64,
    pin: &PinRef,
    what: &str,
    cycle: f64,
    max_duration: f64,
) -> Result<[Cmd; 2], ObjectsError> {
    let off = i64::from(pin.invert);
    let pin = pin_number(dict, pin, what)?;
    let max_ticks = (max_duration * clock_freq).round() as i64;
    let cycle_ticks = (cycle * clock_freq).round().max(1.0) as i64;
    Ok([
        dict.encode("config_digital_out", &[oid, pin, off, off, max_ticks])?,
        dict.encode("set_digital_out_pwm_cycle", &[oid, cycle_ticks])?,
    ])
}

/// The simulated sensor's table: from well below any `min_temp` to beyond the simulated
/// hotend's full-power temperature, every [`SIM_CURVE_STEP`] °C.
const SIM_CURVE_RANGE: (f64, f64) = (-40.0, 450.0);
/// See [`SIM_CURVE_RANGE`]: 2 °C keeps the linear interpolation of an NTC divider's response
/// within a few hundredths of a degree where printers print.
const SIM_CURVE_STEP: f64 = 2.0;

/// `--sensor-curve PIN=T:F/…`: sensor `sensor`'s response on input `pin`, as a table (none if
/// the table cannot be made, the simulator then reads its default thermistor).
fn sensor_curve_args(pin: &PinRef, sensor: &Sensor) -> Vec<String> {
    let (from, to) = SIM_CURVE_RANGE;
    match firmware::sim::sensor_curve::SensorCurve::sample(from, to, SIM_CURVE_STEP, |t| sensor.adc(t)) {
        Ok(curve) => vec![
            "--sensor-curve".to_string(),
            format!("{}={}", pin.pin, curve.to_arg()),
        ],
        Err(_) => Vec::new(),
    }
}

/// The simulated heater's sensor pin when its sensor is on another MCU: a pin number no
/// configured object uses.
const NO_PIN: &str = "255";

/// `--spi-sensor CS_PIN=CHIP,RTD_NOMINAL,RTD_REFERENCE`: the simulated chip behind `spi`.
fn spi_sensor_args(spi: &SpiSensorSection) -> [String; 2] {
    [
        "--spi-sensor".to_string(),
        format!(
            "{}={},{},{}",
            spi.bus.cs_pin.pin,
            spi.chip.name(),
            spi.rtd_nominal_r,
            spi.rtd_reference_r
        ),
    ]
}

/// `query_analog_in`'s range check of a sensor: the sums of [`SAMPLE_COUNT`] readings (of an
/// ADC whose largest reading is `adc_max`) between `min_temp` and `max_temp`, as (min, max).
pub fn adc_range(sensor: &Sensor, min_temp: f64, max_temp: f64, adc_max: f64) -> (u16, u16) {
    let full = adc_max * f64::from(SAMPLE_COUNT);
    let a = sensor.adc(min_temp);
    let b = sensor.adc(max_temp);
    let sum = |x: f64| (x * full).clamp(0.0, f64::from(u16::MAX)) as u16;
    (sum(a.min(b)), sum(a.max(b)).max(sum(a.min(b))))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn thermal(text: &str) -> Result<Thermal, String> {
        let cfg =
            sysconfig::parse_str(text, std::path::Path::new("printer.cfg")).map_err(|e| e.to_string())?;
        Thermal::from_config(&cfg).map_err(|e| e.to_string())
    }

    const BASE: &str = include_str!("../../examples/simulated-cartesian.cfg");

    #[test]
    fn the_simulated_printer_has_a_hotend_a_bed_and_a_fan() {
        let t = thermal(BASE).unwrap();
        let names: Vec<&str> = t.heaters.iter().map(|h| h.name.as_str()).collect();
        assert_eq!(names, ["extruder", "heater_bed"]);
        assert_eq!(
            t.heaters[0].min_extrude_temp,
            Some(0.0),
            "the examples extrude cold"
        );
        assert_eq!(t.heaters[1].verify.check_gain_time, 60.0);
        assert!(t.fans.iter().any(|f| f.role == FanRole::Part));
        let objs = t.objects_on("mcu");
        assert_eq!(
            objs[..4],
            [
                ThermalObject::HeaterPwm(0),
                ThermalObject::HeaterAdc(0),
                ThermalObject::HeaterPwm(1),
                ThermalObject::HeaterAdc(1)
            ]
        );
    }

    #[test]
    fn bad_sensor_types_and_references_name_the_section() {
        let text = BASE.replace(
            "sensor_type: Generic 3950\nsensor_pin: PF0",
            "sensor_type: Bogus 9\nsensor_pin: PF0",
        );
        let e = thermal(&text).unwrap_err();
        assert!(
            e.starts_with("[extruder] sensor_type:") && e.contains("Bogus 9"),
            "{e}"
        );
        let e = thermal(&format!("{BASE}\n[verify_heater chamber]\n")).unwrap_err();
        assert_eq!(e, "[verify_heater chamber] there is no heater 'chamber'");
        // A custom [thermistor] is a sensor_type.
        let text = format!(
            "{}\n[thermistor my_ntc]\ntemperature1: 25\nresistance1: 100000\nbeta: 3950\n",
            BASE.replace(
                "sensor_type: Generic 3950\nsensor_pin: PF0",
                "sensor_type: my_ntc\nsensor_pin: PF0"
            )
        );
        let t = thermal(&text).unwrap();
        assert!((t.heaters[0].sensor.temperature(t.heaters[0].sensor.adc(200.0)) - 200.0).abs() < 1e-6);
    }

    #[test]
    fn range_check_brackets_the_allowed_temperatures() {
        let s = Sensor::named("Generic 3950", 4700.0, 0.0).unwrap();
        let (lo, hi) = adc_range(&s, 0.0, 250.0, 4095.0);
        // NTC: hot is a low reading.
        assert!(lo < hi);
        let at = |t: f64| (s.adc(t) * 4095.0 * 8.0) as u16;
        assert!(at(25.0) > lo && at(25.0) < hi && at(240.0) > lo);
        assert!(at(260.0) < lo, "{} {lo}", at(260.0));
        assert!(4095 * 8 > hi as u32, "an open thermistor is out of range");
    }

    #[test]
    fn the_simulated_inputs_get_the_configured_sensors_response() {
        let text = BASE.replace(
            "sensor_type: Generic 3950\nsensor_pin: PF1",
            "sensor_type: PT1000\nsensor_pin: PF1",
        ) + "\n[temperature_sensor chamber]\nsensor_type: PT100 INA826\nsensor_pin: PF3\n";
        let t = thermal(&text).unwrap();
        let args = t.sim_args("mcu");
        let curve = |pin: &str| {
            let at = args
                .iter()
                .position(|a| a.starts_with(&format!("{pin}=")))
                .unwrap_or_else(|| panic!("no curve for {pin} in {args:?}"));
            assert_eq!(args[at - 1], "--sensor-curve");
            firmware::sim::sensor_curve::SensorCurve::parse(&args[at][pin.len() + 1..]).unwrap()
        };
        let bed = &t.heaters[1];
        let chamber = &t.sensors[t.sensor("chamber").unwrap()];
        for temp in [0.0, 25.0, 61.0, 119.5, 300.0] {
            for (pin, sensor) in [("PF1", &bed.sensor), ("PF3", &chamber.sensor)] {
                let read = sensor.temperature(curve(pin).fraction(temp));
                assert!((read - temp).abs() < 0.1, "{pin} at {temp}: {read}");
            }
        }
        assert!(t.sim_args("other").is_empty());
    }
}
