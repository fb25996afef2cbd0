//! The simulated MCU's own temperature sensor (Klipper's `ADC_TEMPERATURE` channel): the chip
//! warms from ambient towards its running temperature, and the sensor reads it the way an
//! STM32F1's does.
//!
//! The STM32F1 datasheet's typical sensor gives `V = V25 + slope·(T − 25 °C)` with
//! `V25 = 1.43 V` and `slope = −4.3 mV/°C`, read against a 3.3 V reference:
//! `adc = ADC_MAX · V / 3.3`. The host converts back with Klipper's STM32F1 calibration, the
//! same line. The die starts at [`AMBIENT_C`](super::heater::AMBIENT_C) and approaches
//! [`RUNNING_C`] with time constant [`WARM_UP_S`]: `T(t) = run − (run − ambient)·e^(−t/τ)`.

use super::heater::{ADC_MAX, AMBIENT_C};

/// Sensor voltage at 25 °C (V).
pub const V25: f64 = 1.43;
/// Sensor slope (V/°C).
pub const SLOPE_V_PER_C: f64 = -0.0043;
/// The ADC's reference voltage (V).
pub const VREF: f64 = 3.3;
/// The die's temperature once warm (°C).
pub const RUNNING_C: f64 = 40.0;
/// The die's warm-up time constant (s of MCU time).
pub const WARM_UP_S: f64 = 120.0;

/// The die's temperature `t_s` seconds after power-up (°C).
pub fn die_temperature(t_s: f64) -> f64 {
    RUNNING_C - (RUNNING_C - AMBIENT_C) * (-t_s.max(0.0) / WARM_UP_S).exp()
}

/// The ADC reading of the sensor at `temp_c`.
pub fn adc_of(temp_c: f64) -> u16 {
    let v = V25 + SLOPE_V_PER_C * (temp_c - 25.0);
    (ADC_MAX * v / VREF).round().clamp(0.0, ADC_MAX) as u16
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn warms_from_ambient_to_running() {
        assert_eq!(die_temperature(0.0), AMBIENT_C);
        assert!((die_temperature(10.0 * WARM_UP_S) - RUNNING_C).abs() < 0.01);
        assert!(die_temperature(60.0) > AMBIENT_C && die_temperature(60.0) < RUNNING_C);
    }

    #[test]
    fn reads_the_datasheet_line() {
        // 1.43 V of 3.3 V at 25 °C; hotter reads lower.
        assert_eq!(adc_of(25.0), (4095.0 * 1.43 / 3.3_f64).round() as u16);
        assert!(adc_of(40.0) < adc_of(25.0));
    }
}
