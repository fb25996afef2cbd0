//! `[verify_heater]`: the thermal runaway check of one heater, run once a second with the
//! heater's temperature and target, as Klipper does it.
//!
//! Near target (at or above `target − hysteresis`, or no target) everything resets, and the
//! accumulated error clears while at or below `target + hysteresis`. Below it, each check adds
//! `target − hysteresis − temp` to the error. After a target change the heater is "approaching":
//! it must gain `heating_gain` °C within every `check_gain_time` seconds (each gain restarts the
//! window and clears the error; while the approach starts, the goal follows a falling
//! temperature); a window that passes without the gain ends the approach. Outside an approach,
//! an error of `max_error` or more is a fault: "Heater NAME not heating at expected rate".
//! Defaults: max_error 120, check_gain_time 20 s (60 s for `heater_bed`), hysteresis 5 °C,
//! heating_gain 2 °C.

/// Seconds between checks.
pub const CHECK_INTERVAL_S: f64 = 1.0;

/// `[verify_heater NAME]` options.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VerifyConfig {
    /// `max_error`.
    pub max_error: f64,
    /// `check_gain_time` (s).
    pub check_gain_time: f64,
    /// `hysteresis` (°C).
    pub hysteresis: f64,
    /// `heating_gain` (°C).
    pub heating_gain: f64,
}

impl VerifyConfig {
    /// Klipper's defaults for the heater called `heater_name`.
    pub fn defaults_for(heater_name: &str) -> VerifyConfig {
        VerifyConfig {
            max_error: 120.0,
            check_gain_time: if heater_name == "heater_bed" { 60.0 } else { 20.0 },
            hysteresis: 5.0,
            heating_gain: 2.0,
        }
    }
}

/// A thermal runaway: the message the printer shuts down with.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("Heater {heater} not heating at expected rate")]
pub struct HeaterFault {
    /// The heater's name.
    pub heater: String,
}

/// The check's state for one heater.
#[derive(Debug, Clone, PartialEq)]
pub struct VerifyHeater {
    name: String,
    config: VerifyConfig,
    approaching: bool,
    starting_approach: bool,
    last_target: f64,
    goal_temp: f64,
    goal_time: f64,
    error: f64,
}

impl VerifyHeater {
    /// The check of heater `name`.
    pub fn new(name: &str, config: VerifyConfig) -> VerifyHeater {
        VerifyHeater {
            name: name.to_string(),
            config,
            approaching: false,
            starting_approach: false,
            last_target: 0.0,
            goal_temp: 0.0,
            goal_time: 0.0,
            error: 0.0,
        }
    }

    /// The accumulated error.
    pub fn error(&self) -> f64 {
        self.error
    }

    /// True while the heater is approaching its target.
    pub fn approaching(&self) -> bool {
        self.approaching
    }

    /// One check at `time` (s) with the heater at `temp` and its `target` (°C); call every
    /// [`CHECK_INTERVAL_S`].
    pub fn check(&mut self, time: f64, temp: f64, target: f64) -> Result<(), HeaterFault> {
        let c = self.config;
        if temp >= target - c.hysteresis || target <= 0.0 {
            self.approaching = false;
            self.starting_approach = false;
            if temp <= target + c.hysteresis {
                self.error = 0.0;
            }
            self.last_target = target;
            return Ok(());
        }
        self.error += target - c.hysteresis - temp;
        if !self.approaching {
            if target != self.last_target {
                self.approaching = true;
                self.starting_approach = true;
                self.goal_temp = temp + c.heating_gain;
                self.goal_time = time + c.check_gain_time;
            } else if self.error >= c.max_error {
                return Err(HeaterFault {
                    heater: self.name.clone(),
                });
            }
        } else if temp >= self.goal_temp {
            self.starting_approach = false;
            self.error = 0.0;
            self.goal_temp = temp + c.heating_gain;
            self.goal_time = time + c.check_gain_time;
        } else if time >= self.goal_time {
            self.approaching = false;
        } else if self.starting_approach {
            self.goal_temp = self.goal_temp.min(temp + c.heating_gain);
        }
        self.last_target = target;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::heaters::control::{Control, Pid, PidGains};
    use crate::heaters::thermistor::Sensor;
    use firmware::sim::heater::{Heater, HeaterFault as SimFault, ThermalModel};

    /// Heats `heater` towards `target` with PID, checking every second; the time of the fault.
    fn run(name: &str, mut heater: Heater, target: f64, seconds: f64) -> Option<(f64, String)> {
        let gains = PidGains {
            kp: 30.0,
            ki: 1.2,
            kd: 180.0,
        };
        let mut pid = Pid::new(gains, 1.0, 1.0);
        let mut verify = VerifyHeater::new(name, VerifyConfig::defaults_for(name));
        let sensor = Sensor::named("Generic 3950", 4700.0, 0.0).ok()?;
        let mut t = 0.0;
        let mut next_check = 0.0;
        while t < seconds {
            // The host sees the sensor through the ADC (a frozen or open sensor included).
            let adc = heater.adc(t) as f64 / 4095.0;
            let temp = sensor.temperature(adc);
            let power = pid.update(t, temp, target);
            heater.set(power > 0.0, t);
            if power > 0.0 && power < 1.0 {
                heater.set(false, t + 0.3 * power);
            }
            if t >= next_check {
                if let Err(e) = verify.check(t, temp, target) {
                    return Some((t, e.to_string()));
                }
                next_check += CHECK_INTERVAL_S;
            }
            t += 0.3;
        }
        None
    }

    #[test]
    fn defaults_are_klippers() {
        let e = VerifyConfig::defaults_for("extruder");
        assert_eq!(
            (e.max_error, e.check_gain_time, e.hysteresis, e.heating_gain),
            (120.0, 20.0, 5.0, 2.0)
        );
        assert_eq!(VerifyConfig::defaults_for("heater_bed").check_gain_time, 60.0);
    }

    #[test]
    fn a_working_heater_passes_and_holds() {
        let hotend = Heater::new(0, 0, ThermalModel::HOTEND);
        assert_eq!(run("extruder", hotend, 210.0, 600.0), None);
        let bed = Heater::new(0, 0, ThermalModel::BED);
        assert_eq!(run("heater_bed", bed, 60.0, 900.0), None);
    }

    #[test]
    fn a_heater_that_never_heats_faults_after_check_gain_time() {
        let mut v = VerifyHeater::new("extruder", VerifyConfig::defaults_for("extruder"));
        // Stuck at 25 °C with target 210: approaching for 20 s, then error ≥ 120 at once.
        let mut fault = None;
        for s in 0..60 {
            if let Err(e) = v.check(s as f64, 25.0, 210.0) {
                fault = Some((s, e));
                break;
            }
        }
        let (at, e) = fault.unwrap();
        assert_eq!(at, 21);
        assert_eq!(e.to_string(), "Heater extruder not heating at expected rate");
    }

    #[test]
    fn injected_simulator_faults_end_in_a_fault() {
        // The heater stops heating 30 s into the heat-up, halfway there.
        let dead = Heater::new(0, 0, ThermalModel::HOTEND).with_fault(SimFault::NoHeat, 30.0);
        let (at, msg) = run("extruder", dead, 210.0, 600.0).unwrap();
        eprintln!("hotend heater dead at 30 s of a heat-up to 210 C: verify_heater fault at {at:.1} s");
        assert!((30.0..=60.0).contains(&at), "{at}");
        assert_eq!(msg, "Heater extruder not heating at expected rate");
        // The sensor freezes at 30 s: it stops approaching, same fault.
        let frozen = Heater::new(0, 0, ThermalModel::HOTEND).with_fault(SimFault::FrozenSensor, 30.0);
        let (at, _) = run("extruder", frozen, 210.0, 600.0).unwrap();
        eprintln!("hotend sensor frozen at 30 s of a heat-up to 210 C: verify_heater fault at {at:.1} s");
        assert!((30.0..=60.0).contains(&at), "{at}");
        // The bed's heater dies while it holds 60 °C: it cools below target − hysteresis and
        // the error grows until the fault.
        let bed_dead = Heater::new(0, 0, ThermalModel::BED).with_fault(SimFault::NoHeat, 200.0);
        let (at, msg) = run("heater_bed", bed_dead, 60.0, 900.0).unwrap();
        eprintln!("bed heater dead at 200 s while holding 60 C: verify_heater fault at {at:.1} s");
        assert!(at > 200.0, "{at}");
        assert_eq!(msg, "Heater heater_bed not heating at expected rate");
    }

    #[test]
    fn a_target_change_restarts_the_approach() {
        let mut v = VerifyHeater::new("extruder", VerifyConfig::defaults_for("extruder"));
        v.check(0.0, 25.0, 200.0).unwrap();
        assert!(v.approaching());
        // Gains 2 °C each 10 s: keeps approaching.
        for s in 1..50 {
            v.check(s as f64, 25.0 + 0.25 * s as f64, 200.0).unwrap();
        }
        assert!(v.approaching());
        // At target: reset; a higher target starts a new approach.
        v.check(50.0, 199.0, 200.0).unwrap();
        assert_eq!((v.approaching(), v.error()), (false, 0.0));
        v.check(51.0, 199.0, 250.0).unwrap();
        assert!(v.approaching());
        // Turned off: never a fault.
        for s in 52..200 {
            v.check(s as f64, 25.0, 0.0).unwrap();
        }
    }
}
