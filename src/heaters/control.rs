//! Heater control as Klipper does it: the heater's temperature smoothing, `control: pid` and
//! `control: watermark`. Each takes a sensor reading (time in seconds, °C) and the target and
//! returns the heater's power, 0..=max_power; time is an argument, nothing here reads a clock.
//!
//! PID gains are in Klipper's config units (`pid_Kp`, `pid_Ki`, `pid_Kd`): a power of 1.0 is
//! 255 units, so `power = (Kp·e + Ki·∫e dt − Kd·dT/dt) / 255`. The derivative is of the
//! temperature (not the error) smoothed over `smooth_time`; the integral is kept within
//! `0..=max_power·255/Ki` and is not advanced while the output is saturated (anti-windup). The
//! heater counts as settled (M109 stops waiting) within 1 °C of target and a slope below
//! 0.1 °C/s. Watermark: full `max_power` below `target − max_delta`, off above
//! `target + max_delta`, unchanged in between.

use firmware::sim::heater::{ThermalModel, AMBIENT_C};

/// Power of 1.0 in Klipper's PID units.
pub const PID_PARAM_BASE: f64 = 255.0;
/// A PID heater is settled within this many °C of its target ...
pub const PID_SETTLE_DELTA: f64 = 1.0;
/// ... and with a temperature slope below this (°C/s).
pub const PID_SETTLE_SLOPE: f64 = 0.1;

/// Exponential smoothing of the readings over `smooth_time` (Klipper's heater smoothing, the
/// temperature M105 and the status report).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Smoothed {
    smooth_time: f64,
    value: Option<f64>,
    last_time: f64,
}

impl Smoothed {
    /// A smoother over `smooth_time` seconds (> 0).
    pub fn new(smooth_time: f64) -> Smoothed {
        Smoothed {
            smooth_time: smooth_time.max(1e-6),
            value: None,
            last_time: 0.0,
        }
    }

    /// Adds the reading `temp` taken at `time`; returns the smoothed temperature.
    pub fn update(&mut self, time: f64, temp: f64) -> f64 {
        let v = match self.value {
            None => temp,
            Some(v) => {
                let adj = ((time - self.last_time) / self.smooth_time).clamp(0.0, 1.0);
                v + (temp - v) * adj
            }
        };
        self.value = Some(v);
        self.last_time = time;
        v
    }

    /// The smoothed temperature (`None` before the first reading).
    pub fn value(&self) -> Option<f64> {
        self.value
    }
}

/// What a controller does with a reading.
pub trait Control {
    /// The power (0..=max_power) after the reading `temp` at `time` with `target`.
    fn update(&mut self, time: f64, temp: f64, target: f64) -> f64;
    /// True while the heater has not settled at `target` (M109/M190 keep waiting).
    fn busy(&self, smoothed_temp: f64, target: f64) -> bool;
}

/// `control: watermark`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Watermark {
    max_delta: f64,
    max_power: f64,
    heating: bool,
}

impl Watermark {
    /// With `max_delta` (°C) and `max_power` (0..=1).
    pub fn new(max_delta: f64, max_power: f64) -> Watermark {
        Watermark {
            max_delta,
            max_power,
            heating: false,
        }
    }
}

impl Control for Watermark {
    fn update(&mut self, _time: f64, temp: f64, target: f64) -> f64 {
        if self.heating {
            if temp >= target + self.max_delta {
                self.heating = false;
            }
        } else if temp <= target - self.max_delta {
            self.heating = true;
        }
        if self.heating && target > 0.0 {
            self.max_power
        } else {
            0.0
        }
    }

    fn busy(&self, smoothed_temp: f64, target: f64) -> bool {
        smoothed_temp < target - self.max_delta
    }
}

/// PID gains in Klipper's config units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PidGains {
    /// `pid_Kp`.
    pub kp: f64,
    /// `pid_Ki`.
    pub ki: f64,
    /// `pid_Kd`.
    pub kd: f64,
}

/// `control: pid`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pid {
    kp: f64,
    ki: f64,
    kd: f64,
    max_power: f64,
    smooth_time: f64,
    integ_max: f64,
    prev: Option<(f64, f64)>,
    deriv: f64,
    integ: f64,
}

impl Pid {
    /// With `gains` (Klipper units), `max_power` (0..=1) and the sensor's `smooth_time` (s).
    pub fn new(gains: PidGains, max_power: f64, smooth_time: f64) -> Pid {
        let (kp, ki, kd) = (
            gains.kp / PID_PARAM_BASE,
            gains.ki / PID_PARAM_BASE,
            gains.kd / PID_PARAM_BASE,
        );
        Pid {
            kp,
            ki,
            kd,
            max_power,
            smooth_time: smooth_time.max(1e-6),
            integ_max: if ki > 0.0 { max_power / ki } else { 0.0 },
            prev: None,
            deriv: 0.0,
            integ: 0.0,
        }
    }

    /// The smoothed temperature slope (°C/s).
    pub fn slope(&self) -> f64 {
        self.deriv
    }
}

impl Control for Pid {
    fn update(&mut self, time: f64, temp: f64, target: f64) -> f64 {
        let (prev_time, prev_temp) = self.prev.unwrap_or((time, temp));
        let dt = (time - prev_time).max(0.0);
        // Slope of the temperature, smoothed over smooth_time.
        let deriv = if dt >= self.smooth_time {
            (temp - prev_temp) / dt
        } else {
            (self.deriv * (self.smooth_time - dt) + (temp - prev_temp)) / self.smooth_time
        };
        let err = target - temp;
        let integ = (self.integ + err * dt).clamp(0.0, self.integ_max);
        let co = self.kp * err + self.ki * integ - self.kd * deriv;
        let power = co.clamp(0.0, self.max_power);
        self.prev = Some((time, temp));
        self.deriv = deriv;
        if co == power {
            self.integ = integ;
        }
        if target > 0.0 {
            power
        } else {
            0.0
        }
    }

    fn busy(&self, smoothed_temp: f64, target: f64) -> bool {
        (target - smoothed_temp).abs() > PID_SETTLE_DELTA || self.deriv.abs() > PID_SETTLE_SLOPE
    }
}

/// Makes up for the time a PWM update waits before it takes effect, on a time-scaled simulated
/// MCU only: its updates must be sent seconds of MCU time ahead (a wall-clock margin against
/// host pauses: 0.25 s of wall time is 12.5 s of MCU time at 50×), a dead time in which a PID
/// tuned for a real board's 0.3 s would swing around its target and never settle (M109 would
/// wait forever). A Smith predictor: the simulated heater's own thermal model (which the host
/// chose for it, [`super::objects::SimKind`]) runs twice on the powers sent, once as if each
/// acted when it was decided and once when it really acts; their difference added to the
/// reading is what the sensor would show without the delay. On a real board the delay is
/// Klipper's and readings go to the control unchanged. `verify_heater` always judges the
/// reading itself.
#[derive(Debug, Clone)]
pub struct SmithPredictor {
    undelayed: Plant,
    delayed: Plant,
    /// Powers sent and not yet acting on `delayed`: (MCU time it acts from, power 0..=1).
    pending: std::collections::VecDeque<(f64, f64)>,
}

impl SmithPredictor {
    /// For a heater simulated with `model`, cold (ambient, off) at time 0.
    pub fn new(model: ThermalModel) -> SmithPredictor {
        SmithPredictor {
            undelayed: Plant::new(model),
            delayed: Plant::new(model),
            pending: std::collections::VecDeque::with_capacity(64),
        }
    }

    /// The reading `temp` at `time` (s) as the sensor would show it without the delay.
    pub fn predict(&mut self, time: f64, temp: f64) -> f64 {
        while let Some(&(at, power)) = self.pending.front().filter(|(at, _)| *at <= time) {
            self.delayed.set(power, at);
            self.pending.pop_front();
        }
        temp + self.undelayed.sensor_at(time) - self.delayed.sensor_at(time)
    }

    /// The control decided `power` (0..=1 of the heater's full power) at `time`.
    pub fn decided(&mut self, power: f64, time: f64) {
        self.undelayed.set(power, time);
    }

    /// `power` was sent to act from `at` (the MCU queues few updates, so what is sent may be
    /// the mean of several decisions: the prediction follows what the heater really gets).
    pub fn sent(&mut self, power: f64, at: f64) {
        if self.pending.len() == self.pending.capacity() {
            // Never reached with the loop's send spacing; keeps the queue bounded regardless.
            if let Some((at, power)) = self.pending.pop_front() {
                self.delayed.set(power, at);
            }
        }
        self.pending.push_back((at, power));
    }
}

/// The simulated heater's two temperatures (the heated mass, the thermistor lagging it),
/// driven by an average power: the exact solution between power changes.
#[derive(Debug, Clone, Copy)]
struct Plant {
    model: ThermalModel,
    mass: f64,
    sensor: f64,
    power: f64,
    at: f64,
}

impl Plant {
    fn new(model: ThermalModel) -> Plant {
        Plant {
            model,
            mass: AMBIENT_C,
            sensor: AMBIENT_C,
            power: 0.0,
            at: 0.0,
        }
    }

    fn advance(&mut self, t: f64) {
        let dt = t - self.at;
        if dt > 0.0 {
            (self.mass, self.sensor) = self.model.solve((self.mass, self.sensor), self.power, dt);
            self.at = t;
        }
    }

    fn set(&mut self, power: f64, t: f64) {
        self.advance(t);
        self.power = power.clamp(0.0, 1.0);
    }

    fn sensor_at(&mut self, t: f64) -> f64 {
        self.advance(t);
        self.sensor
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use firmware::sim::heater::{Heater, ThermalModel};

    /// Runs `control` on the simulator's thermal model for `seconds`: a reading every 0.3 s
    /// (Klipper's report time), the power applied as PWM with a 0.1 s cycle. Returns the
    /// sensor temperatures read and the powers set.
    pub(crate) fn run_plant(
        model: ThermalModel,
        control: &mut dyn Control,
        target: f64,
        seconds: f64,
    ) -> (Vec<f64>, Vec<f64>) {
        let mut h = Heater::new(0, 0, model);
        let (mut temps, mut powers) = (Vec::new(), Vec::new());
        let mut t = 0.0;
        while t < seconds {
            let temp = h.sensor_temperature(t);
            let power = control.update(t, temp, target);
            temps.push(temp);
            powers.push(power);
            for cycle in 0..3 {
                let start = t + 0.1 * cycle as f64;
                h.set(power > 0.0, start);
                if power > 0.0 && power < 1.0 {
                    h.set(false, start + 0.1 * power);
                }
            }
            t += 0.3;
        }
        (temps, powers)
    }

    #[test]
    fn smoothing_follows_smooth_time() {
        let mut s = Smoothed::new(1.0);
        assert_eq!(s.value(), None);
        assert_eq!(s.update(0.0, 20.0), 20.0);
        assert_eq!(s.update(0.5, 30.0), 25.0);
        assert_eq!(
            s.update(2.0, 40.0),
            40.0,
            "a gap of a full smooth_time catches up"
        );
    }

    #[test]
    fn pid_terms_are_in_klippers_units() {
        // Kp 25.5: 1 °C of error is 0.1 of full power; saturates at max_power.
        let gains = PidGains {
            kp: 25.5,
            ki: 0.0,
            kd: 0.0,
        };
        let mut pid = Pid::new(gains, 0.8, 1.0);
        assert!((pid.update(0.0, 199.0, 200.0) - 0.1).abs() < 1e-12);
        assert_eq!(pid.update(0.3, 150.0, 200.0), 0.8);
        assert_eq!(pid.update(0.6, 210.0, 200.0), 0.0);
        assert_eq!(pid.update(0.9, 20.0, 0.0), 0.0, "target 0 is off");
        // Ki: the integral of 1 °C for 2 s at Ki 25.5 is 0.2 (with no P term).
        let mut pid = Pid::new(
            PidGains {
                kp: 0.0,
                ki: 25.5,
                kd: 0.0,
            },
            1.0,
            1.0,
        );
        pid.update(0.0, 199.0, 200.0);
        assert!((pid.update(2.0, 199.0, 200.0) - 0.2).abs() < 1e-12);
        // Kd: rising 1 °C/s for longer than smooth_time takes Kd/255 per °C/s.
        let mut pid = Pid::new(
            PidGains {
                kp: 0.0,
                ki: 0.0,
                kd: 25.5,
            },
            1.0,
            1.0,
        );
        pid.update(0.0, 100.0, 200.0);
        assert_eq!(pid.update(2.0, 102.0, 200.0), 0.0);
        assert!((pid.slope() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn pid_holds_the_simulated_hotend_at_target() {
        // Hand-picked gains (calibrate's test holds 210 °C with the gains PID_CALIBRATE finds).
        let gains = PidGains {
            kp: 30.0,
            ki: 1.2,
            kd: 180.0,
        };
        let mut pid = Pid::new(gains, 1.0, 1.0);
        let (temps, powers) = run_plant(ThermalModel::HOTEND, &mut pid, 210.0, 600.0);
        let peak = temps.iter().cloned().fold(f64::MIN, f64::max);
        assert!(peak < 220.0, "overshoot to {peak}");
        let last: Vec<f64> = temps[temps.len() - 300..].to_vec();
        assert!(last.iter().all(|t| (t - 210.0).abs() < 1.0), "{last:?}");
        // Holding 210 °C takes (210 − 25)·0.12 W/K of 40 W: 55 %.
        let hold = powers[powers.len() - 300..].iter().sum::<f64>() / 300.0;
        assert!((hold - 0.555).abs() < 0.03, "{hold}");
        assert!(!pid.busy(210.2, 210.0));
        assert!(pid.busy(205.0, 210.0));
    }

    #[test]
    fn watermark_keeps_within_its_band() {
        let mut w = Watermark::new(2.0, 1.0);
        assert_eq!(w.update(0.0, 20.0, 60.0), 1.0);
        assert_eq!(
            w.update(1.0, 60.0, 60.0),
            1.0,
            "heats on until target + max_delta"
        );
        assert_eq!(w.update(2.0, 62.0, 60.0), 0.0);
        assert_eq!(w.update(3.0, 59.0, 60.0), 0.0, "off until target − max_delta");
        assert_eq!(w.update(4.0, 58.0, 60.0), 1.0);
        let mut w = Watermark::new(2.0, 1.0);
        let (temps, _) = run_plant(ThermalModel::BED, &mut w, 60.0, 1200.0);
        let settled = &temps[temps.len() / 2..];
        // The bed's lag carries it a little past the band.
        assert!(settled.iter().all(|t| (55.0..65.0).contains(t)), "{settled:?}");
        assert!(!w.busy(58.5, 60.0));
    }

    /// Runs Klipper-style PID gains on `model` with each update acting `lead` seconds after
    /// its reading (with `predict`, through the Smith predictor): whether M109's settle check
    /// ends, and the last minute's worst distance from target.
    fn with_dead_time(model: ThermalModel, target: f64, lead: f64, predict: bool) -> (bool, f64) {
        let mut pid = Pid::new(
            PidGains {
                kp: 22.2,
                ki: 1.08,
                kd: 114.0,
            },
            1.0,
            1.0,
        );
        let mut smith = SmithPredictor::new(model);
        let mut h = Heater::new(0, 0, model);
        let mut pending = std::collections::VecDeque::new();
        let (mut settled, mut worst, mut t) = (false, 0.0_f64, 0.0);
        let mut last_sent: Option<f64> = None;
        let (mut sum, mut n, mut in_force) = (0.0, 0.0, 0.0);
        while t < 1200.0 {
            let temp = h.sensor_temperature(t);
            let seen = if predict { smith.predict(t, temp) } else { temp };
            let power = pid.update(t, seen, target);
            smith.decided(power, t);
            sum += power;
            n += 1.0;
            // As the heater loop sends: the mean of the decisions since the last update once a
            // fifth of the lead has passed (the MCU queues few updates).
            if last_sent.is_none_or(|at| t + lead - at >= lead / 5.0 - 1e-9) {
                let mean = sum / n;
                smith.sent(mean, t + lead);
                pending.push_back((t + lead, mean));
                last_sent = Some(t + lead);
                (sum, n) = (0.0, 0.0);
            }
            // The MCU's PWM over the next 0.3 s: 0.1 s cycles of the value in force.
            for c in 0..3 {
                let start = t + 0.1 * f64::from(c);
                while let Some(&(_, power)) = pending.front().filter(|(at, _)| *at <= start) {
                    in_force = power;
                    pending.pop_front();
                }
                h.set(in_force > 0.0, start);
                if in_force > 0.0 && in_force < 1.0 {
                    h.set(false, start + 0.1 * in_force);
                }
            }
            settled |= !pid.busy(temp, target);
            if t > 1140.0 {
                worst = worst.max((temp - target).abs());
            }
            t += 0.3;
        }
        (settled, worst)
    }

    #[test]
    fn a_long_update_lead_is_made_up_for_by_the_smith_predictor() {
        let hotend = ThermalModel::HOTEND;
        assert!(
            with_dead_time(hotend, 200.0, 0.3, false).0,
            "Klipper's own delay settles"
        );
        let (_, worst) = with_dead_time(hotend, 200.0, 8.0, false);
        assert!(worst > 5.0, "8 s of dead time keeps swinging: {worst}");
        // 0.25 s of wall time at 50× is 12.5 s of MCU time.
        for lead in [2.0, 4.0, 12.5, 15.0] {
            let (settled, worst) = with_dead_time(hotend, 200.0, lead, true);
            assert!(settled && worst < 0.5, "lead {lead}: {settled} {worst}");
        }
        let (settled, worst) = with_dead_time(ThermalModel::BED, 60.0, 12.5, true);
        assert!(settled && worst < 0.5, "bed: {settled} {worst}");
    }
}
