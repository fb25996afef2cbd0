//! The MCU's own temperature sensor (`sensor_type: temperature_mcu`): a linear sensor on the
//! MCU's `ADC_TEMPERATURE` channel, `T = base + slope · adc` (adc the 0..1 fraction), with
//! Klipper's calibration per MCU family (the dictionary's `MCU` constant), overridden by the
//! config's `sensor_temperature1`/`sensor_adc1` (and `…2`) points.
//!
//! A family's datasheet line `V = V0 + dV/dT · (T − T0)`, read against a reference `Vref`,
//! gives `slope = Vref / (dV/dT)` per unit of adc and `base = T0 − (V0 / Vref) · slope`.
//! Klipper reads the STM32F0/F4/G0/H7 and SAMD families' factory calibration from flash
//! (`debug_read`), which Cadence's MCU firmware does not offer: those need both points in the
//! config. The simulator (`linux-sim`) models an STM32F1's sensor
//! ([`firmware::sim::mcu_temp`]).

use super::thermistor::{Element, Sensor};

/// The pin name of the MCU's own sensor in the dictionary (Klipper's).
pub const ADC_TEMPERATURE: &str = "ADC_TEMPERATURE";

/// `temperature_mcu`'s calibration as configured.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct McuSensor {
    /// `sensor_temperature1` (°C), `sensor_adc1` (0..1).
    pub point1: Option<(f64, f64)>,
    /// `sensor_temperature2`, `sensor_adc2`.
    pub point2: Option<(f64, f64)>,
}

/// Why an MCU's own sensor cannot be calibrated.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum McuSensorError {
    /// No known line for this MCU and the config does not give both points.
    #[error(
        "MCU temperature not supported on {0} without a calibration (set sensor_temperature1, \
         sensor_adc1, sensor_temperature2 and sensor_adc2)"
    )]
    Unsupported(String),
    /// The two points have the same ADC value.
    #[error("sensor_adc1 and sensor_adc2 must differ")]
    SamePoints,
}

/// A datasheet line: `v0` volts at `t0` °C, `dv_dt` V/°C, against `vref` volts.
#[derive(Debug, Clone, Copy)]
struct Datasheet {
    t0: f64,
    v0: f64,
    dv_dt: f64,
    vref: f64,
}

impl Datasheet {
    /// `(base, slope)` of the line in ADC fractions.
    fn line(self) -> (f64, f64) {
        let slope = self.vref / self.dv_dt;
        (self.t0 - self.v0 / self.vref * slope, slope)
    }
}

const fn sheet(t0: f64, v0: f64, dv_dt: f64, vref: f64) -> Datasheet {
    Datasheet { t0, v0, dv_dt, vref }
}

/// Klipper's fixed calibration line `(base, slope)` of MCU family `mcu_type`, for the families
/// whose line is in their datasheet (not in their flash).
pub fn family_line(mcu_type: &str) -> Option<(f64, f64)> {
    use firmware::sim::mcu_temp as sim;
    let families = [
        ("rp2", sheet(27.0, 0.706, -0.001721, 3.3)),
        ("sam3", sheet(27.0, 0.8, 0.00265, 3.3)),
        ("sam4", sheet(27.0, 1.44, 0.0047, 3.3)),
        ("same70", sheet(25.0, 0.72, 0.00233, 3.3)),
        ("stm32f1", sheet(25.0, 1.43, -0.0043, 3.3)),
        ("stm32f2", sheet(25.0, 0.76, 0.0025, 3.3)),
        ("linux-sim", sheet(25.0, sim::V25, sim::SLOPE_V_PER_C, sim::VREF)),
    ];
    families
        .iter()
        .find(|(prefix, _)| mcu_type.starts_with(prefix))
        .map(|(_, s)| s.line())
}

impl McuSensor {
    /// The sensor on an MCU of type `mcu_type`.
    pub fn sensor(&self, mcu_type: &str) -> Result<Sensor, McuSensorError> {
        let (base, slope) = match (self.point1, self.point2) {
            (Some((t1, a1)), Some((t2, a2))) => {
                if a1 == a2 {
                    return Err(McuSensorError::SamePoints);
                }
                let slope = (t2 - t1) / (a2 - a1);
                (t1 - a1 * slope, slope)
            }
            (Some((t1, a1)), None) => {
                let (_, slope) =
                    family_line(mcu_type).ok_or_else(|| McuSensorError::Unsupported(mcu_type.to_string()))?;
                (t1 - a1 * slope, slope)
            }
            _ => family_line(mcu_type).ok_or_else(|| McuSensorError::Unsupported(mcu_type.to_string()))?,
        };
        Ok(Sensor {
            element: Element::Linear { base, slope },
            pullup: 0.0,
            inline: 0.0,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DEFAULT: McuSensor = McuSensor {
        point1: None,
        point2: None,
    };

    #[test]
    fn stm32f1_line_is_klippers() {
        // Klipper: slope = 3.3 / -0.0043, base from 25 °C at 1.43 / 3.3.
        let s = DEFAULT.sensor("stm32f103xe").unwrap();
        assert!((s.temperature(1.43 / 3.3) - 25.0).abs() < 1e-9);
        let slope = 3.3 / -0.0043;
        assert!((s.temperature(1.43 / 3.3 + 0.01) - (25.0 + 0.01 * slope)).abs() < 1e-9);
        assert!((s.temperature(s.adc(60.0)) - 60.0).abs() < 1e-9);
    }

    #[test]
    fn the_simulator_reads_what_the_host_converts() {
        let s = DEFAULT.sensor("linux-sim").unwrap();
        for t in [25.0, 40.0] {
            let adc = f64::from(firmware::sim::mcu_temp::adc_of(t)) / 4095.0;
            assert!((s.temperature(adc) - t).abs() < 0.5, "{t}");
        }
    }

    #[test]
    fn points_override_and_unknown_families_need_both() {
        let one = McuSensor {
            point1: Some((30.0, 0.4)),
            point2: None,
        };
        let s = one.sensor("rp2040").unwrap();
        assert!((s.temperature(0.4) - 30.0).abs() < 1e-9);
        let e = one.sensor("stm32f446xx").unwrap_err();
        assert!(e.to_string().contains("stm32f446xx"), "{e}");
        let two = McuSensor {
            point1: Some((30.0, 0.4)),
            point2: Some((110.0, 0.5)),
        };
        let s = two.sensor("stm32f446xx").unwrap();
        assert!((s.temperature(0.5) - 110.0).abs() < 1e-9);
        let same = McuSensor {
            point1: Some((30.0, 0.4)),
            point2: Some((110.0, 0.4)),
        };
        assert_eq!(same.sensor("stm32f1"), Err(McuSensorError::SamePoints));
        assert!(DEFAULT.sensor("atmega2560").is_err());
    }
}
