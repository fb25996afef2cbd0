//! Heater options, shared by `[extruder]` and `[heater_bed]`: the PWM output, the temperature
//! sensor (thermistor-style: an ADC pin with a pull-up resistor), the control algorithm and the
//! allowed temperature range.
//!
//! Sensors are read through an analog `sensor_pin` (with `pullup_resistor` /
//! `inline_resistor`) or are SPI chips ([`super::spi_sensor`]) whose chip select is
//! `sensor_pin`; I2C and 1-wire sensors are refused by name.

use super::error::{ConfigError, ValueProblem};
use super::pins::{PinKind, PinRef, PinRegistry, Share};
use super::reader::{Bounds, SectionReader};
use super::spi_sensor::{read_spi_sensor, SpiChip, SpiSensorSection};

/// Absolute zero in °C: the lowest `min_temp`.
pub const ABSOLUTE_ZERO_C: f64 = -273.15;

/// `control:` and its parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum HeaterControl {
    /// Bang-bang: on below target − max_delta, off above target + max_delta.
    Watermark { max_delta: f64 },
    /// PID with Klipper's gains as written (`pid_Kp`, `pid_Ki`, `pid_Kd`).
    Pid { kp: f64, ki: f64, kd: f64 },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ControlKind {
    Watermark,
    Pid,
}

/// One heater.
#[derive(Debug, Clone, PartialEq)]
pub struct HeaterSection {
    /// The section it came from: `extruder`, `heater_bed`.
    pub name: String,
    pub heater_pin: PinRef,
    /// In (0, 1]; default 1.
    pub max_power: f64,
    /// Seconds, > 0; default 0.1.
    pub pwm_cycle_time: f64,
    /// The sensor's name as written (e.g. `EPCOS 100K B57560G104F`); not checked against a list.
    pub sensor_type: String,
    pub sensor_pin: PinRef,
    /// Ohms, > 0; default 4700.
    pub pullup_resistor: f64,
    /// Ohms, ≥ 0; default 0.
    pub inline_resistor: f64,
    /// Seconds, > 0; default 1.
    pub smooth_time: f64,
    pub control: HeaterControl,
    /// °C, ≥ absolute zero.
    pub min_temp: f64,
    /// °C, > min_temp.
    pub max_temp: f64,
    /// °C in [min_temp, max_temp]; default 170 (meaningful for extruders).
    pub min_extrude_temp: f64,
    /// An SPI temperature chip (`sensor_type: MAX6675` etc.): `sensor_pin` is its chip select.
    pub spi: Option<SpiSensorSection>,
}

pub(crate) fn read_heater(
    s: &SectionReader<'_>,
    pins: &mut PinRegistry,
) -> Result<HeaterSection, ConfigError> {
    read_heater_options(s, pins, true)
}

/// Klipper's sensor types that are not read through an analog pin (the MCU's own sensor,
/// amplifiers on SPI, sensors on I2C or 1-wire), with what they are: Cadence's MCUs do not
/// read them yet.
const UNSUPPORTED_SENSORS: [(&str, &str); 13] = [
    ("temperature_mcu", "the MCU's own sensor"),
    ("BME280", "an I2C sensor"),
    ("BMP280", "an I2C sensor"),
    ("BME680", "an I2C sensor"),
    ("BMP180", "an I2C sensor"),
    ("AHT10", "an I2C sensor"),
    ("AHT20", "an I2C sensor"),
    ("AHT21", "an I2C sensor"),
    ("HTU21D", "an I2C sensor"),
    ("SHT3X", "an I2C sensor"),
    ("LM75", "an I2C sensor"),
    ("SI7013", "an I2C sensor"),
    ("DS18B20", "a 1-wire sensor"),
];

/// A sensor type of [`UNSUPPORTED_SENSORS`] as the error naming it (before its bus options
/// would be reported as unknown options).
pub(crate) fn refuse_unsupported_sensor(s: &SectionReader<'_>, sensor_type: &str) -> Result<(), ConfigError> {
    let Some((name, what)) = UNSUPPORTED_SENSORS.iter().find(|(n, _)| *n == sensor_type) else {
        return Ok(());
    };
    let v = s.required("sensor_type")?;
    Err(s.bad(
        "sensor_type",
        v,
        ValueProblem::Invalid(format!("{name} ({what}) is not supported")),
    ))
}

/// The heater options of section `s`; `min_extrude_temp` only if `with_extrude_temp` (not in
/// `[heater_generic]`, where it stays at its default and may not be written).
pub(crate) fn read_heater_options(
    s: &SectionReader<'_>,
    pins: &mut PinRegistry,
    with_extrude_temp: bool,
) -> Result<HeaterSection, ConfigError> {
    let sensor_type = s.string("sensor_type")?;
    refuse_unsupported_sensor(s, &sensor_type)?;
    let spi = match SpiChip::of(&sensor_type) {
        Some(chip) => Some(read_spi_sensor(s, pins, chip)?),
        None => None,
    };
    let (sensor_pin, pullup_resistor, inline_resistor) = match &spi {
        Some(spi) => (spi.bus.cs_pin.clone(), 4700.0, 0.0),
        None => (
            s.pin("sensor_pin", PinKind::Analog, pins, Share::Exclusive)?,
            s.float_or("pullup_resistor", 4700.0, Bounds::ANY.above(0.0))?,
            s.float_or("inline_resistor", 0.0, Bounds::ANY.min(0.0))?,
        ),
    };
    let min_temp = s.float("min_temp", Bounds::ANY.min(ABSOLUTE_ZERO_C))?;
    let max_temp = s.float("max_temp", Bounds::ANY.above(min_temp))?;
    let min_extrude_temp = if with_extrude_temp {
        s.float_or("min_extrude_temp", 170.0, Bounds::ANY.min(min_temp).max(max_temp))?
    } else {
        170.0
    };
    let max_power = s.float_or("max_power", 1.0, Bounds::ANY.above(0.0).max(1.0))?;
    let smooth_time = s.float_or("smooth_time", 1.0, Bounds::ANY.above(0.0))?;
    let heater_pin = s.pin("heater_pin", PinKind::Output, pins, Share::Exclusive)?;
    let pwm_cycle_time = s.float_or("pwm_cycle_time", 0.1, Bounds::ANY.above(0.0))?;
    let kinds = [("watermark", ControlKind::Watermark), ("pid", ControlKind::Pid)];
    let control = match s.choice("control", &kinds, None)? {
        ControlKind::Watermark => HeaterControl::Watermark {
            max_delta: s.float_or("max_delta", 2.0, Bounds::ANY.above(0.0))?,
        },
        ControlKind::Pid => HeaterControl::Pid {
            kp: s.float("pid_kp", Bounds::ANY)?,
            ki: s.float("pid_ki", Bounds::ANY)?,
            kd: s.float("pid_kd", Bounds::ANY)?,
        },
    };
    Ok(HeaterSection {
        name: s.name().to_string(),
        heater_pin,
        max_power,
        pwm_cycle_time,
        sensor_type,
        sensor_pin,
        pullup_resistor,
        inline_resistor,
        smooth_time,
        control,
        min_temp,
        max_temp,
        min_extrude_temp,
        spi,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ini;
    use crate::printer::reader::Reader;
    use std::path::Path;

    const BASE: &str =
        "heater_pin: PH5\nsensor_type: EPCOS 100K B57560G104F\nsensor_pin: PK6\nmin_temp: 0\nmax_temp: 130\n";

    /// `[heater_bed]` with BASE (lines 2-6) then `extra` (from line 7).
    fn heater(extra: &str) -> Result<HeaterSection, String> {
        let text = format!("[heater_bed]\n{BASE}{extra}");
        let file = ini::parse_str(&text, Path::new("printer.cfg")).map_err(|e| e.to_string())?;
        let reader = Reader::new(&file);
        let s = reader.section("heater_bed").ok_or("no section")?;
        let h = read_heater(&s, &mut PinRegistry::new(vec!["mcu".into()])).map_err(|e| e.to_string())?;
        reader.finish(|_| false).map_err(|e| e.to_string())?;
        Ok(h)
    }

    #[test]
    fn watermark_and_pid() {
        let h = heater("control: watermark\n").unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(h.control, HeaterControl::Watermark { max_delta: 2.0 });
        assert_eq!(
            (h.pullup_resistor, h.inline_resistor, h.max_power, h.smooth_time),
            (4700.0, 0.0, 1.0, 1.0)
        );
        assert_eq!(
            (h.min_temp, h.max_temp, h.min_extrude_temp, h.pwm_cycle_time),
            (0.0, 130.0, 170.0, 0.1)
        );
        assert_eq!(h.sensor_type, "EPCOS 100K B57560G104F");
        let h = heater("control: pid\npid_Kp: 22.2\npid_Ki: 1.08\npid_Kd: 114\n")
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            h.control,
            HeaterControl::Pid {
                kp: 22.2,
                ki: 1.08,
                kd: 114.0
            }
        );
    }

    #[test]
    fn errors() {
        let cases = [
            ("", "printer.cfg:1: Option 'control' in section 'heater_bed' must be specified"),
            ("control: pid\npid_Kp: 1\n", "printer.cfg:1: Option 'pid_ki' in section 'heater_bed' must be specified"),
            ("control: watermark\npid_Kp: 1\n", "printer.cfg:8: Option 'pid_kp' is not valid in section 'heater_bed'"),
            ("control: bang\n", "printer.cfg:7: [heater_bed] control: expected one of watermark, pid, got 'bang'"),
            ("control: watermark\nmax_power: 1.5\n", "printer.cfg:8: [heater_bed] max_power: must have maximum of 1, got 1.5"),
            (
                "control: watermark\nmin_extrude_temp: 200\n",
                "printer.cfg:8: [heater_bed] min_extrude_temp: must have maximum of 130, got 200",
            ),
            (
                "control: watermark\nsensor_pin: !PK7\n",
                "printer.cfg:8: [heater_bed] sensor_pin: invalid pin '!PK7': inversion '!' is not allowed on this pin",
            ),
        ];
        for (extra, want) in cases {
            assert_eq!(heater(extra).map(|_| ()), Err(want.to_string()), "{extra}");
        }
    }
}
