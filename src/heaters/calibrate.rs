//! `PID_CALIBRATE HEATER= TARGET=` as a pure algorithm on samples: the relay method Klipper
//! uses. The heater runs at full power until the temperature reaches the target, then off
//! until it falls to `target − 5 °C`, and so on; each switch records the extreme temperature
//! (and its time) of the half-cycle that just ended. After 12 peaks the oscillation's
//! amplitude `a` (half a peak-to-peak swing) and period `Tu` give the ultimate gain by the
//! Åström–Hägglund relay formula `Ku = 4·max_power / (π·a)`, and Ziegler–Nichols' classic PID
//! rule the gains: `Kp = 0.6·Ku`, `Ti = Tu/2`, `Td = Tu/8`, `Ki = Kp/Ti`, `Kd = Kp·Td`, in
//! Klipper's units (×255). The cycle used is the one whose period is the median of the cycles
//! from the 4th peak on (the first swings carry the heat-up).

use super::control::{PidGains, PID_PARAM_BASE};

/// Where `PID_CALIBRATE … WRITE_FILE=1` writes its samples (Klipper's file).
pub const WRITE_FILE: &str = "/tmp/heattest.txt";

/// Klipper's answer to a finished PID_CALIBRATE.
pub fn report(g: &PidGains) -> String {
    format!(
        "PID parameters: pid_Kp={:.3} pid_Ki={:.3} pid_Kd={:.3}\n\
         The SAVE_CONFIG command will update the printer config file\n\
         with these parameters and restart the printer.",
        g.kp, g.ki, g.kd
    )
}

/// The options SAVE_CONFIG keeps for heater `section`: `control: pid` and the gains, as
/// Klipper writes them (three decimals).
pub fn save_changes(changes: &mut sysconfig::autosave::Changes, section: &str, g: &PidGains) {
    changes.set(section, "control", "pid");
    changes.set(section, "pid_Kp", format!("{:.3}", g.kp));
    changes.set(section, "pid_Ki", format!("{:.3}", g.ki));
    changes.set(section, "pid_Kd", format!("{:.3}", g.kd));
}

/// Degrees below the target at which the relay turns the heater back on.
pub const TUNE_PID_DELTA: f64 = 5.0;
/// Peaks recorded before the result is computed.
pub const PEAKS_NEEDED: usize = 12;

/// A relay calibration in progress.
#[derive(Debug, Clone, PartialEq)]
pub struct RelayTuner {
    target: f64,
    max_power: f64,
    heating: bool,
    peak: f64,
    peak_time: f64,
    peaks: Vec<(f64, f64)>,
}

impl RelayTuner {
    /// Calibration at `target` °C with the heater's `max_power`.
    pub fn new(target: f64, max_power: f64) -> RelayTuner {
        RelayTuner {
            target,
            max_power,
            heating: true,
            peak: f64::INFINITY,
            peak_time: 0.0,
            peaks: Vec::with_capacity(PEAKS_NEEDED),
        }
    }

    /// The reading `temp` at `time`: the power to apply until the next reading.
    pub fn update(&mut self, time: f64, temp: f64) -> f64 {
        if self.heating && temp >= self.target {
            self.heating = false;
            self.record_peak();
        } else if !self.heating && temp <= self.target - TUNE_PID_DELTA {
            self.heating = true;
            self.record_peak();
        }
        let extreme = if self.heating {
            temp < self.peak
        } else {
            temp > self.peak
        };
        if extreme {
            self.peak = temp;
            self.peak_time = time;
        }
        if self.done() || !self.heating {
            0.0
        } else {
            self.max_power
        }
    }

    fn record_peak(&mut self) {
        self.peaks.push((self.peak, self.peak_time));
        self.peak = if self.heating {
            f64::INFINITY
        } else {
            f64::NEG_INFINITY
        };
    }

    /// True once enough peaks are recorded.
    pub fn done(&self) -> bool {
        self.peaks.len() >= PEAKS_NEEDED
    }

    /// The (temperature, time) extremes so far (the first is the start of the heat-up).
    pub fn peaks(&self) -> &[(f64, f64)] {
        &self.peaks
    }

    /// The gains from the peak at `pos` (≥ 2): amplitude from peaks `pos − 1`, `pos`; period
    /// from `pos − 2` to `pos`.
    fn gains_at(&self, pos: usize) -> PidGains {
        let amplitude = 0.5 * (self.peaks[pos].0 - self.peaks[pos - 1].0).abs();
        let tu = self.peaks[pos].1 - self.peaks[pos - 2].1;
        let ku = 4.0 * self.max_power / (std::f64::consts::PI * amplitude);
        let (ti, td) = (0.5 * tu, 0.125 * tu);
        let kp = 0.6 * ku * PID_PARAM_BASE;
        PidGains {
            kp,
            ki: kp / ti,
            kd: kp * td,
        }
    }

    /// The calibrated gains, once [`done`](Self::done).
    pub fn result(&self) -> Option<PidGains> {
        if !self.done() {
            return None;
        }
        let mut cycles: Vec<(f64, usize)> = (4..self.peaks.len())
            .map(|pos| (self.peaks[pos].1 - self.peaks[pos - 2].1, pos))
            .collect();
        cycles.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let (_, pos) = cycles[cycles.len() / 2];
        Some(self.gains_at(pos))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::heaters::control::tests::run_plant;
    use crate::heaters::control::{Control, Pid};
    use firmware::sim::heater::ThermalModel;

    #[test]
    fn a_sine_gives_the_textbook_gains() {
        // Peaks of a 10 °C peak-to-peak swing with a 30 s period around 200 °C.
        let mut tuner = RelayTuner::new(205.0, 1.0);
        tuner.peaks = (0..PEAKS_NEEDED)
            .map(|i| (if i % 2 == 0 { 195.0 } else { 205.0 }, 15.0 * i as f64))
            .collect();
        let g = tuner.result().unwrap();
        // a = 5: Ku = 4/(5π) = 0.254648; Kp = 0.6·Ku·255 = 38.961; Ti = 15, Td = 3.75.
        assert!((g.kp - 38.961).abs() < 1e-3, "{g:?}");
        assert!((g.ki - 38.961 / 15.0).abs() < 1e-3);
        assert!((g.kd - 38.961 * 3.75).abs() < 1e-2);
    }

    /// A calibration on the simulated hotend, readings every 0.3 s (the samples PID_CALIBRATE
    /// gets), then those gains holding 210 °C.
    #[test]
    fn calibrates_the_simulated_hotend() {
        struct Relay(RelayTuner);
        impl Control for Relay {
            fn update(&mut self, time: f64, temp: f64, _target: f64) -> f64 {
                self.0.update(time, temp)
            }
            fn busy(&self, _smoothed: f64, _target: f64) -> bool {
                !self.0.done()
            }
        }
        let mut relay = Relay(RelayTuner::new(210.0, 1.0));
        let (temps, _) = run_plant(ThermalModel::HOTEND, &mut relay, 210.0, 1200.0);
        assert!(relay.0.done(), "{:?}", relay.0.peaks());
        let gains = relay.0.result().unwrap();
        eprintln!("PID_CALIBRATE on the simulated hotend at 210 °C: {gains:?}");
        assert!(temps.iter().all(|t| *t < 225.0));
        assert!((5.0..200.0).contains(&gains.kp), "{gains:?}");
        assert!(gains.ki > 0.0 && gains.kd > gains.kp);
        let mut pid = Pid::new(gains, 1.0, 1.0);
        let (temps, _) = run_plant(ThermalModel::HOTEND, &mut pid, 210.0, 900.0);
        let last = &temps[temps.len() - 300..];
        assert!(last.iter().all(|t| (t - 210.0).abs() < 1.0), "{last:?}");
    }

    #[test]
    fn the_report_and_the_saved_options_are_klippers() {
        let g = PidGains {
            kp: 22.2,
            ki: 1.08,
            kd: 114.0,
        };
        assert_eq!(
            report(&g),
            "PID parameters: pid_Kp=22.200 pid_Ki=1.080 pid_Kd=114.000\n\
             The SAVE_CONFIG command will update the printer config file\n\
             with these parameters and restart the printer."
        );
        let mut c = sysconfig::autosave::Changes::default();
        save_changes(&mut c, "heater_bed", &g);
        let sysconfig::autosave::SectionChange::Set(opts) = &c.items()[0].1 else {
            panic!("{c:?}");
        };
        assert_eq!(c.items()[0].0, "heater_bed");
        assert_eq!(opts[0], ("control".to_string(), "pid".to_string()));
        assert_eq!(opts[3], ("pid_kd".to_string(), "114.000".to_string()));
    }

    #[test]
    fn not_done_without_enough_peaks() {
        let mut tuner = RelayTuner::new(100.0, 1.0);
        assert_eq!(tuner.update(0.0, 20.0), 1.0);
        assert_eq!(tuner.update(1.0, 101.0), 0.0, "off once at target");
        assert_eq!(tuner.update(2.0, 97.0), 0.0, "off until target − 5");
        assert_eq!(tuner.update(3.0, 95.0), 1.0);
        assert_eq!(tuner.peaks(), &[(20.0, 0.0), (101.0, 1.0)]);
        assert_eq!(tuner.result(), None);
    }
}
