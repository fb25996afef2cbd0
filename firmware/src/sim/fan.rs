//! A simulated fan with a tachometer: its speed follows the mean power of its output pin (the
//! rotor's inertia smooths the PWM), and its tachometer output changes level `2·ppr` times per
//! revolution, as a fan's open-collector tach line read with a pull-up does.
//!
//! Physics (time in MCU seconds): with the pin's duty `d` (the level 0/1 of a software PWM, or
//! a hardware PWM's value / PWM_MAX), the speed `ω` (rev/s) obeys `dω/dt = (d·ω_max − ω)/τ`,
//! solved exactly between pin changes: `ω(t) = ω∞ + (ω0 − ω∞)·e^(−t/τ)`, and the revolutions
//! in that time are `ω∞·t + (ω0 − ω∞)·τ·(1 − e^(−t/τ))`. [`MAX_RPM`] at full power, τ =
//! [`SPIN_UP_S`].

use super::cli::parse_pin;

/// The fan's speed at full power (rev/min).
pub const MAX_RPM: f64 = 5000.0;
/// The speed's time constant (s).
pub const SPIN_UP_S: f64 = 0.5;

/// `--fan OUT_PIN=TACH_PIN[,PPR]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FanSpec {
    /// The pin that powers it.
    pub out_pin: u8,
    /// Its tachometer output.
    pub tach_pin: u8,
    /// Tach pulses per revolution (default 2).
    pub ppr: u32,
}

impl FanSpec {
    /// Parses `OUT_PIN=TACH_PIN[,PPR]`.
    pub fn parse(s: &str) -> Result<FanSpec, String> {
        let (out, rest) = s.split_once('=').ok_or("expected OUT_PIN=TACH_PIN[,PPR]")?;
        let (tach, ppr) = rest.split_once(',').unwrap_or((rest, "2"));
        let ppr = ppr
            .parse::<u32>()
            .ok()
            .filter(|&p| p > 0)
            .ok_or_else(|| format!("`{ppr}` is not a pulse count per revolution"))?;
        Ok(FanSpec {
            out_pin: parse_pin(out)?,
            tach_pin: parse_pin(tach)?,
            ppr,
        })
    }
}

/// A fan's state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fan {
    /// Its pins.
    pub spec: FanSpec,
    time: f64,
    duty: f64,
    speed_rps: f64,
    revs: f64,
}

impl Fan {
    /// A fan at rest.
    pub fn new(spec: FanSpec) -> Fan {
        Fan {
            spec,
            time: 0.0,
            duty: 0.0,
            speed_rps: 0.0,
            revs: 0.0,
        }
    }

    fn advance(&mut self, t: f64) {
        let dt = t - self.time;
        if dt <= 0.0 {
            return;
        }
        let target = self.duty * MAX_RPM / 60.0;
        let decay = (-dt / SPIN_UP_S).exp();
        self.revs += target * dt + (self.speed_rps - target) * SPIN_UP_S * (1.0 - decay);
        self.speed_rps = target + (self.speed_rps - target) * decay;
        self.time = t;
    }

    /// The output's duty becomes `duty` (0..=1) at `t`.
    pub fn set(&mut self, duty: f64, t: f64) {
        self.advance(t);
        self.duty = duty.clamp(0.0, 1.0);
    }

    /// The speed at `t` (rev/min).
    pub fn rpm(&mut self, t: f64) -> f64 {
        self.advance(t);
        self.speed_rps * 60.0
    }

    /// The tach line's level at `t`.
    pub fn tach_level(&mut self, t: f64) -> bool {
        self.advance(t);
        (self.revs * 2.0 * f64::from(self.spec.ppr)).floor() as u64 % 2 == 1
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spins_up_to_its_duty_and_the_tach_counts_revolutions() {
        let mut f = Fan::new(FanSpec::parse("PE11=PE10").unwrap());
        assert_eq!(f.spec.ppr, 2);
        f.set(0.5, 0.0);
        assert!((f.rpm(10.0 * SPIN_UP_S) - 2500.0).abs() < 1.0);
        // Level changes over one second at 2500 rpm: 2 · ppr · 41.7 rev.
        let (mut changes, mut last) = (0, f.tach_level(10.0));
        let mut t = 10.0;
        while t < 11.0 {
            t += 0.0005;
            let l = f.tach_level(t);
            changes += usize::from(l != last);
            last = l;
        }
        assert!((changes as f64 - 2500.0 / 60.0 * 4.0).abs() < 2.0, "{changes}");
        assert!(FanSpec::parse("PE11=PE10,0").is_err());
    }
}
