//! A simulated heater: heater power into a thermal mass, losses to ambient, a thermistor that
//! lags the mass, read through a pull-up divider; and the heater faults the simulator can inject.
//!
//! Physics (time in MCU seconds, clock / CLOCK_FREQ): the mass at temperature `T` (°C) gets
//! `P` watts while the heater pin is on (0 while off) and loses `k·(T − ambient)` watts:
//! `C·dT/dt = P·on − k·(T − ambient)`, i.e. `T` tends to `T_eq = ambient + P·on/k` with time
//! constant `τ = C/k`. The thermistor's temperature `S` follows the mass with its own lag
//! `τ_s`: `dS/dt = (T − S)/τ_s`. Both are solved exactly between pin changes (the pin is
//! constant in between, PWM edges included), so the result does not depend on how often the
//! ADC is read. [`ThermalModel::HOTEND`] is a 40 W cartridge in a ~13 J/K block (25 → 210 °C in
//! about 80 s), [`ThermalModel::BED`] a 150 W bed of ~500 J/K (25 → 60 °C in about 2.3 min).
//!
//! The sensor is Klipper's "Generic 3950": an NTC of 100 kΩ at 25 °C, β = 3950, to ground under
//! a 4.7 kΩ pull-up: `R = R25·e^(β(1/T − 1/T25))` (kelvin), `adc = ADC_MAX · R / (R + 4700)`;
//! or, given one ([`Heater::with_curve`]), the response of the sensor the host configured
//! ([`SensorCurve`]).
//!
//! Faults, from an MCU time on: [`HeaterFault::OpenThermistor`] (the divider reads ADC_MAX),
//! [`HeaterFault::NoHeat`] (the pin still switches but no power reaches the mass), and
//! [`HeaterFault::FrozenSensor`] (the ADC keeps the value it read when the fault began).

use super::sensor_curve::SensorCurve;

/// Ambient temperature (°C).
pub const AMBIENT_C: f64 = 25.0;
/// Largest ADC reading.
pub const ADC_MAX: f64 = 4095.0;
const R25: f64 = 100_000.0;
const BETA: f64 = 3950.0;
const PULLUP: f64 = 4700.0;
const KELVIN: f64 = 273.15;

/// Thermal constants of one heater.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThermalModel {
    /// Heater power while the pin is on (W).
    pub power_w: f64,
    /// Heat capacity of the heated mass (J/K).
    pub capacity_j_per_k: f64,
    /// Loss to ambient (W/K).
    pub loss_w_per_k: f64,
    /// Lag of the thermistor behind the mass (s).
    pub sensor_lag_s: f64,
}

impl ThermalModel {
    /// A 40 W hotend: 13.3 J/K (aluminium block, cartridge, nozzle), 0.12 W/K lost (settles
    /// near 358 °C at full power, τ = 111 s), thermistor lag 2 s.
    pub const HOTEND: ThermalModel = ThermalModel {
        power_w: 40.0,
        capacity_j_per_k: 13.3,
        loss_w_per_k: 0.12,
        sensor_lag_s: 2.0,
    };
    /// A 150 W bed: 500 J/K (a 3 mm aluminium plate of 235 mm square), 1.2 W/K lost (settles
    /// near 150 °C at full power, τ = 417 s), thermistor lag 8 s.
    pub const BED: ThermalModel = ThermalModel {
        power_w: 150.0,
        capacity_j_per_k: 500.0,
        loss_w_per_k: 1.2,
        sensor_lag_s: 8.0,
    };

    /// The mass's time constant `C/k` (s).
    pub fn tau_s(&self) -> f64 {
        self.capacity_j_per_k / self.loss_w_per_k
    }

    /// The mass's and the sensor's temperatures (°C) `dt` seconds after `(mass, sensor)` with
    /// `power` (0..=1 of the heater's) applied throughout: the exact solution.
    pub fn solve(&self, (mass, sensor): (f64, f64), power: f64, dt: f64) -> (f64, f64) {
        let eq = AMBIENT_C + power * self.power_w / self.loss_w_per_k;
        let tau = self.tau_s();
        let e1 = (-dt / tau).exp();
        let (t0, s0, lag) = (mass - eq, sensor - eq, self.sensor_lag_s);
        let sensor = if lag <= 0.0 {
            t0 * e1 + eq
        } else if (tau - lag).abs() < 1e-9 {
            // Equal time constants: S = eq + (s0 + t0·dt/τ)·e^(−dt/τ).
            eq + (s0 + t0 * dt / tau) * e1
        } else {
            let a = t0 * tau / (tau - lag);
            eq + a * e1 + (s0 - a) * (-dt / lag).exp()
        };
        (eq + t0 * e1, sensor)
    }

    /// Temperature the mass settles at with the heater always on (°C).
    pub fn full_power_c(&self) -> f64 {
        AMBIENT_C + self.power_w / self.loss_w_per_k
    }

    /// Seconds at full power for the *sensor* to go from ambient to `target_c` (`None` if the
    /// heater cannot get there), found by stepping the exact solution in 10 ms steps.
    pub fn heat_up_s(&self, target_c: f64) -> Option<f64> {
        if target_c >= self.full_power_c() {
            return None;
        }
        let mut h = Heater::new(0, 0, *self);
        h.set(true, 0.0);
        let mut t = 0.0;
        while h.sensor_temperature(t) < target_c {
            t += 0.01;
        }
        Some(t)
    }
}

/// A fault injected into one heater.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HeaterFault {
    /// The thermistor's wire broke: the ADC reads its maximum.
    OpenThermistor,
    /// The heater stops heating (burnt cartridge, loose wire) though its pin still switches.
    NoHeat,
    /// The sensor's reading freezes at its value when the fault begins.
    FrozenSensor,
}

/// One heater and its sensor.
#[derive(Debug, Clone, PartialEq)]
pub struct Heater {
    /// Heater output pin.
    pub heater_pin: u8,
    /// Thermistor ADC pin.
    pub sensor_pin: u8,
    model: ThermalModel,
    temp_c: f64,
    sensor_c: f64,
    on: bool,
    at_s: f64,
    fault: Option<(HeaterFault, f64)>,
    frozen_adc: Option<u16>,
    /// The configured sensor's response (`None`: the default β3950 thermistor).
    curve: Option<SensorCurve>,
    /// The heater is on while its pin is low.
    active_low: bool,
}

impl Heater {
    /// A cold heater (ambient, off) at time 0.
    pub fn new(heater_pin: u8, sensor_pin: u8, model: ThermalModel) -> Heater {
        Heater {
            heater_pin,
            sensor_pin,
            model,
            temp_c: AMBIENT_C,
            sensor_c: AMBIENT_C,
            on: false,
            at_s: 0.0,
            fault: None,
            frozen_adc: None,
            curve: None,
            active_low: false,
        }
    }

    /// With `active_low`, the heater is on while its pin is low (an inverted `heater_pin`).
    pub fn active_low(mut self, active_low: bool) -> Heater {
        self.active_low = active_low;
        self
    }

    /// The heater pin's level changed at `t_s`.
    pub fn set_level(&mut self, level: bool, t_s: f64) {
        self.set(level != self.active_low, t_s);
    }

    /// Reads its sensor through `curve` (the sensor the host configured) instead of the
    /// default β3950 thermistor.
    pub fn with_curve(mut self, curve: SensorCurve) -> Heater {
        self.curve = Some(curve);
        self
    }

    /// The sensor's ADC reading at `temp_c`.
    fn reading(&self, temp_c: f64) -> u16 {
        match &self.curve {
            Some(c) => c.adc(temp_c),
            None => adc_of(temp_c),
        }
    }

    /// Injects `fault` from MCU time `from_s` on.
    pub fn with_fault(mut self, fault: HeaterFault, from_s: f64) -> Heater {
        self.fault = Some((fault, from_s));
        self
    }

    /// Whether the sensor is disconnected at `t_s` (an `open` fault).
    pub fn sensor_open(&self, t_s: f64) -> bool {
        self.faulted(HeaterFault::OpenThermistor, t_s)
    }

    fn faulted(&self, kind: HeaterFault, t_s: f64) -> bool {
        self.fault.is_some_and(|(f, from)| f == kind && t_s >= from)
    }

    /// Solves the model from `at_s` to `t_s` with the pin constant.
    fn solve(&mut self, t_s: f64) {
        let dt = t_s - self.at_s;
        if dt <= 0.0 {
            return;
        }
        let power = if self.on { 1.0 } else { 0.0 };
        (self.temp_c, self.sensor_c) = self.model.solve((self.temp_c, self.sensor_c), power, dt);
        self.at_s = t_s;
    }

    /// Advances to `t_s`, switching the power off at the start of a `NoHeat` fault and keeping
    /// the reading at the start of a `FrozenSensor` fault.
    fn advance(&mut self, t_s: f64) {
        match self.fault {
            Some((HeaterFault::NoHeat, from)) if self.on && t_s > from => {
                self.solve(from.max(self.at_s));
                self.on = false;
            }
            Some((HeaterFault::FrozenSensor, from)) if self.frozen_adc.is_none() && t_s >= from => {
                self.solve(from);
                self.frozen_adc = Some(self.reading(self.sensor_c));
            }
            _ => {}
        }
        self.solve(t_s);
    }

    /// The heater pin changed at `t_s`.
    pub fn set(&mut self, on: bool, t_s: f64) {
        self.advance(t_s);
        self.on = on && !self.faulted(HeaterFault::NoHeat, t_s);
    }

    /// Temperature of the heated mass at `t_s` (°C).
    pub fn temperature(&mut self, t_s: f64) -> f64 {
        self.advance(t_s);
        self.temp_c
    }

    /// Temperature of the thermistor at `t_s` (°C).
    pub fn sensor_temperature(&mut self, t_s: f64) -> f64 {
        self.advance(t_s);
        self.sensor_c
    }

    /// ADC reading at `t_s`, faults included.
    pub fn adc(&mut self, t_s: f64) -> u16 {
        let sensor_c = self.sensor_temperature(t_s);
        let value = self.reading(sensor_c);
        if self.faulted(HeaterFault::OpenThermistor, t_s) {
            return ADC_MAX as u16;
        }
        match self.frozen_adc {
            Some(frozen) if self.faulted(HeaterFault::FrozenSensor, t_s) => frozen,
            _ => value,
        }
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

    impl Heater {
        /// Sensor temperature after heating from `from_s` to `to_s`.
        fn heat(mut self, from_s: f64, to_s: f64) -> f64 {
            self.set(true, from_s);
            self.sensor_temperature(to_s)
        }
    }

    #[test]
    fn divider_matches_the_thermistor_table() {
        // 25 °C: 100k / 104.7k of 4095.
        assert_eq!(adc_of(25.0), 3911);
        // Hotter reads lower; 200 °C is about 745 Ω: 4095 · 745 / 5445 ≈ 560.
        assert!((555..=565).contains(&adc_of(200.0)), "{}", adc_of(200.0));
        assert!(adc_of(100.0) > adc_of(150.0));
    }

    #[test]
    fn heat_up_times_are_a_printers() {
        let hotend = ThermalModel::HOTEND.heat_up_s(210.0).unwrap();
        let bed = ThermalModel::BED.heat_up_s(60.0).unwrap();
        eprintln!("full power from 25 °C: hotend to 210 °C {hotend:.1} s, bed to 60 °C {bed:.1} s");
        assert!((60.0..=120.0).contains(&hotend), "hotend 25→210 °C in {hotend} s");
        let bed = ThermalModel::BED.heat_up_s(60.0).unwrap();
        assert!((90.0..=300.0).contains(&bed), "bed 25→60 °C in {bed} s");
        assert!(bed > hotend);
        assert_eq!(ThermalModel::BED.heat_up_s(200.0), None);
    }

    #[test]
    fn exact_solution_matches_small_steps_and_energy_balance() {
        // Integrate the two ODEs with Euler steps of 1 ms and compare.
        let m = ThermalModel::HOTEND;
        let mut h = Heater::new(1, 2, m);
        h.set(true, 0.0);
        let (mut t, mut s) = (AMBIENT_C, AMBIENT_C);
        let dt = 0.001;
        for _ in 0..30_000 {
            let dtemp = (m.power_w - m.loss_w_per_k * (t - AMBIENT_C)) / m.capacity_j_per_k;
            s += (t - s) / m.sensor_lag_s * dt;
            t += dtemp * dt;
        }
        assert!(
            (h.temperature(30.0) - t).abs() < 0.05,
            "{} vs {t}",
            h.temperature(30.0)
        );
        assert!((h.sensor_temperature(30.0) - s).abs() < 0.05);
        // The sensor lags the mass while heating.
        assert!(h.sensor_temperature(30.0) < h.temperature(30.0));
        // Pin off: cools back to ambient.
        h.set(false, 30.0);
        assert!(h.temperature(3000.0) < AMBIENT_C + 0.1);
        assert!(h.adc(3000.0) > 3900);
    }

    #[test]
    fn pwm_average_power_settles_in_between() {
        // 50 % duty at a 0.1 s cycle for 20 τ settles near ambient + P/(2k).
        let m = ThermalModel::HOTEND;
        let mut h = Heater::new(1, 2, m);
        let mut t = 0.0;
        while t < 20.0 * m.tau_s() {
            h.set(true, t);
            h.set(false, t + 0.05);
            t += 0.1;
        }
        let expect = AMBIENT_C + m.power_w / m.loss_w_per_k / 2.0;
        assert!((h.temperature(t) - expect).abs() < 0.5, "{}", h.temperature(t));
    }

    #[test]
    fn an_active_low_heater_heats_while_its_pin_is_low() {
        let m = ThermalModel::HOTEND;
        let mut low = Heater::new(1, 2, m).active_low(true);
        low.set_level(true, 0.0);
        assert!(low.temperature(60.0) < AMBIENT_C + 0.1, "pin high: off");
        low.set_level(false, 60.0);
        assert!(low.temperature(120.0) > 100.0, "pin low: on");
        let mut high = Heater::new(1, 2, m);
        high.set_level(true, 0.0);
        assert!(high.temperature(60.0) > 100.0);
    }

    #[test]
    fn injected_faults() {
        let m = ThermalModel::HOTEND;
        let mut open = Heater::new(1, 2, m).with_fault(HeaterFault::OpenThermistor, 10.0);
        open.set(true, 0.0);
        assert!(open.adc(9.9) < 3900);
        assert_eq!(open.adc(10.0), 4095);

        let mut dead = Heater::new(1, 2, m).with_fault(HeaterFault::NoHeat, 10.0);
        dead.set(true, 0.0);
        let peak = dead.temperature(10.0);
        assert!(peak > 50.0, "{peak}");
        assert!(dead.temperature(60.0) < peak, "no power after the fault");
        dead.set(true, 60.0);
        assert!(dead.temperature(120.0) < peak);

        let mut frozen = Heater::new(1, 2, m).with_fault(HeaterFault::FrozenSensor, 10.0);
        frozen.set(true, 0.0);
        let stuck = frozen.adc(30.0);
        assert_eq!(stuck, adc_of(Heater::new(1, 2, m).heat(0.0, 10.0)));
        assert_eq!(frozen.adc(50.0), stuck);
        assert!(frozen.temperature(100.0) > 150.0, "the mass keeps heating");
        assert!(adc_of(frozen.sensor_temperature(100.0)) < stuck);
    }
}
