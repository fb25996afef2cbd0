//! A simulated heater: first-order thermal model read through a thermistor divider.
//!
//! Temperature follows `dT/dt = (T_eq − T) / TAU` with `T_eq` = [`HOT_C`] while the heater pin
//! is on and [`AMBIENT_C`] while off, solved exactly between events:
//! `T(t + dt) = T_eq + (T − T_eq)·e^(−dt/TAU)`; time is MCU seconds (clock / CLOCK_FREQ).
//! The sensor is an NTC 100 kΩ (at 25 °C), β = 3950, to ground under a 4.7 kΩ pull-up:
//! `R = R25·e^(β(1/T − 1/T25))` (kelvin), `adc = ADC_MAX · R / (R + 4700)`.

/// Ambient temperature (°C).
pub const AMBIENT_C: f64 = 25.0;
/// Temperature the heater settles at while always on (°C).
pub const HOT_C: f64 = 300.0;
/// Time constant (s of MCU time).
pub const TAU_S: f64 = 30.0;
/// Largest ADC reading.
pub const ADC_MAX: f64 = 4095.0;
const R25: f64 = 100_000.0;
const BETA: f64 = 3950.0;
const PULLUP: f64 = 4700.0;
const KELVIN: f64 = 273.15;

/// One heater and its sensor.
#[derive(Debug, Clone, PartialEq)]
pub struct Heater {
    /// Heater output pin.
    pub heater_pin: u8,
    /// Thermistor ADC pin.
    pub sensor_pin: u8,
    temp_c: f64,
    on: bool,
    at_s: f64,
}

impl Heater {
    /// A cold heater (ambient, off) at time 0.
    pub fn new(heater_pin: u8, sensor_pin: u8) -> Heater {
        Heater {
            heater_pin,
            sensor_pin,
            temp_c: AMBIENT_C,
            on: false,
            at_s: 0.0,
        }
    }

    fn advance(&mut self, t_s: f64) {
        let dt = t_s - self.at_s;
        if dt > 0.0 {
            let eq = if self.on { HOT_C } else { AMBIENT_C };
            self.temp_c = eq + (self.temp_c - eq) * (-dt / TAU_S).exp();
            self.at_s = t_s;
        }
    }

    /// The heater pin changed at `t_s`.
    pub fn set(&mut self, on: bool, t_s: f64) {
        self.advance(t_s);
        self.on = on;
    }

    /// Temperature at `t_s` (°C).
    pub fn temperature(&mut self, t_s: f64) -> f64 {
        self.advance(t_s);
        self.temp_c
    }

    /// ADC reading at `t_s`.
    pub fn adc(&mut self, t_s: f64) -> u16 {
        adc_of(self.temperature(t_s))
    }
}

/// ADC reading of the divider at `temp_c`.
pub fn adc_of(temp_c: f64) -> u16 {
    let t = temp_c + KELVIN;
    let r = R25 * (BETA * (1.0 / t - 1.0 / (25.0 + KELVIN))).exp();
    (ADC_MAX * r / (r + PULLUP)).round().clamp(0.0, ADC_MAX) as u16
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn divider_matches_the_thermistor_table() {
        // 25 °C: 100k / 104.7k of 4095.
        assert_eq!(adc_of(25.0), 3911);
        // Hotter reads lower; 200 °C is about 745 Ω: 4095 · 745 / 5445 ≈ 560.
        assert!((555..=565).contains(&adc_of(200.0)), "{}", adc_of(200.0));
        assert!(adc_of(100.0) > adc_of(150.0));
    }

    #[test]
    fn heats_towards_hot_and_cools_back() {
        let mut h = Heater::new(1, 2);
        assert_eq!(h.temperature(10.0), AMBIENT_C);
        h.set(true, 10.0);
        let t = h.temperature(10.0 + TAU_S);
        let expect = HOT_C + (AMBIENT_C - HOT_C) * (-1f64).exp();
        assert!((t - expect).abs() < 1e-9);
        h.set(false, 10.0 + TAU_S);
        assert!(h.temperature(1000.0) < AMBIENT_C + 1.0);
        assert!(h.adc(1000.0) > 3900);
    }
}
