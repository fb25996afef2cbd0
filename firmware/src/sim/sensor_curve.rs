//! The simulated temperature sensor's response: the ADC reading an analog input gives at a
//! temperature, as the host's configured sensor would give it (`--sensor-curve`).
//!
//! The host knows the sensor (a named thermistor, a `[thermistor]` curve, a PT100 behind its
//! amplifier, a PT1000, their pull-up and inline resistors); the simulator only needs its
//! response, so the host hands over a table of (°C, ADC fraction of full scale) points, in
//! rising temperature, and the simulator interpolates linearly between them (beyond the ends
//! it keeps the end's value). With points every 2 °C the interpolation error of an NTC's
//! divider stays far below a tenth of a degree in the printing range. Without a table an input
//! reads Klipper's "Generic 3950" under a 4.7 kΩ pull-up ([`super::heater::adc_of`]).
//!
//! Argument form: `T:F/T:F/…` (°C and fraction, at least two points, temperatures strictly
//! rising, fractions in 0..=1).

use super::heater::ADC_MAX;

/// Points a table may have (a 2 °C step over −50..500 °C needs 276).
pub const MAX_POINTS: usize = 1024;

/// A sensor's ADC fraction at rising temperatures.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorCurve {
    points: Vec<(f64, f64)>,
}

impl SensorCurve {
    /// `fraction(t)` sampled every `step` °C from `from` to `to` (both included).
    pub fn sample(
        from: f64,
        to: f64,
        step: f64,
        fraction: impl Fn(f64) -> f64,
    ) -> Result<SensorCurve, String> {
        if !(step > 0.0 && from.is_finite() && to > from) {
            return Err(format!("bad sampling {from}..{to} step {step}"));
        }
        let n = ((to - from) / step).ceil() as usize;
        let points = (0..=n)
            .map(|i| {
                let t = (from + i as f64 * step).min(to);
                (t, fraction(t).clamp(0.0, 1.0))
            })
            .collect();
        SensorCurve::new(points)
    }

    /// The table `points`, checked.
    pub fn new(points: Vec<(f64, f64)>) -> Result<SensorCurve, String> {
        if points.len() < 2 || points.len() > MAX_POINTS {
            return Err(format!(
                "a sensor curve needs 2 to {MAX_POINTS} points, got {}",
                points.len()
            ));
        }
        if let Some(&(t, f)) = points
            .iter()
            .find(|(t, f)| !t.is_finite() || !(0.0..=1.0).contains(f))
        {
            return Err(format!(
                "sensor curve point {t}:{f}: the fraction must be in 0..=1"
            ));
        }
        for w in points.windows(2) {
            if w[1].0 <= w[0].0 {
                return Err(format!(
                    "sensor curve temperatures must rise: {} then {}",
                    w[0].0, w[1].0
                ));
            }
        }
        Ok(SensorCurve { points })
    }

    /// Parses `T:F/T:F/…`.
    pub fn parse(s: &str) -> Result<SensorCurve, String> {
        let points = s
            .split('/')
            .map(|p| {
                let (t, f) = p
                    .split_once(':')
                    .ok_or_else(|| format!("sensor curve point `{p}` is not TEMPERATURE:FRACTION"))?;
                let num = |v: &str| {
                    v.trim()
                        .parse::<f64>()
                        .map_err(|_| format!("sensor curve point `{p}`: `{v}` is not a number"))
                };
                Ok((num(t)?, num(f)?))
            })
            .collect::<Result<Vec<_>, String>>()?;
        SensorCurve::new(points)
    }

    /// The argument form [`SensorCurve::parse`] reads.
    pub fn to_arg(&self) -> String {
        let parts: Vec<String> = self.points.iter().map(|(t, f)| format!("{t}:{f:.7}")).collect();
        parts.join("/")
    }

    /// The fraction of full scale at `temp_c`.
    pub fn fraction(&self, temp_c: f64) -> f64 {
        let first = self.points[0];
        let last = self.points[self.points.len() - 1];
        if temp_c.is_nan() || temp_c <= first.0 {
            return first.1;
        }
        if temp_c >= last.0 {
            return last.1;
        }
        let i = self.points.partition_point(|p| p.0 <= temp_c);
        let ((t0, f0), (t1, f1)) = (self.points[i - 1], self.points[i]);
        f0 + (f1 - f0) * (temp_c - t0) / (t1 - t0)
    }

    /// The ADC reading at `temp_c`.
    pub fn adc(&self, temp_c: f64) -> u16 {
        (self.fraction(temp_c) * ADC_MAX).round().clamp(0.0, ADC_MAX) as u16
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn interpolates_and_keeps_the_ends() {
        let c = SensorCurve::parse("0:0.9/100:0.5/200:0.1").unwrap();
        assert_eq!(c.fraction(50.0), 0.7);
        assert!((c.fraction(150.0) - 0.3).abs() < 1e-12);
        assert_eq!(c.fraction(-40.0), 0.9);
        assert_eq!(c.fraction(900.0), 0.1);
        assert_eq!(c.adc(200.0), (0.1 * ADC_MAX).round() as u16);
        assert_eq!(SensorCurve::parse(&c.to_arg()).unwrap(), c);
    }

    #[test]
    fn sampled_beta_3950_reads_as_the_default_sensor() {
        // The default sensor as a table: within an ADC count of the formula.
        let pullup = 4700.0;
        let c = SensorCurve::sample(-40.0, 450.0, 2.0, |t| {
            let r = 100_000.0 * (3950.0 * (1.0 / (t + 273.15) - 1.0 / 298.15)).exp();
            r / (r + pullup)
        })
        .unwrap();
        for t in [25.0, 61.0, 199.3, 250.0] {
            let d = i32::from(c.adc(t)) - i32::from(super::super::heater::adc_of(t));
            assert!(
                d.abs() <= 2,
                "{t} °C: {} vs {}",
                c.adc(t),
                super::super::heater::adc_of(t)
            );
        }
    }

    #[test]
    fn bad_tables_are_refused() {
        for bad in [
            "",
            "1:0.5",
            "0:0.5/0:0.4",
            "10:0.5/0:0.4",
            "0:1.5/1:0.2",
            "a:0.1/2:0.2",
            "0-0.1/2:0.2",
        ] {
            assert!(SensorCurve::parse(bad).is_err(), "{bad}");
        }
    }

    proptest! {
        /// Any input parses or is refused without a panic; a parsed table reads in 0..=ADC_MAX
        /// at any temperature.
        #[test]
        fn parse_never_panics(s in "[-0-9.:/a]{0,40}", t in -1e4f64..1e4) {
            if let Ok(c) = SensorCurve::parse(&s) {
                prop_assert!(f64::from(c.adc(t)) <= ADC_MAX);
            }
        }
    }
}
