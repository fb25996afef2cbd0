//! Temperature sensors read through the MCU's ADC: the conversion between an ADC fraction
//! (reading / (sample_count · ADC_MAX), 0..1) and °C, both ways.
//!
//! - Thermistors (NTC) under a pull-up resistor, with an optional inline resistor: the
//!   Steinhart–Hart equation `1/T = c1 + c2·ln R + c3·(ln R)³` (kelvin) fitted through three
//!   (temperature, resistance) points, or its β form (`c3 = 0`) from one point and β. The named
//!   thermistors of Klipper's list are defined by their datasheet points ([`named`]).
//! - Platinum RTDs (PT100, PT1000): the Callendar–Van Dusen equation of IEC 60751,
//!   `R = R0·(1 + A·T + B·T² + C·(T − 100)·T³)` (the C term below 0 °C only), either directly
//!   under a pull-up (`PT1000`) or through the INA826 amplifier circuit of E3D's PT100 board
//!   (4.4 kΩ pull-up from 5 V, gain 10; `PT100 INA826`), whose output the ADC reads against
//!   its reference voltage (5 V by default, Klipper's `adc_voltage`).
//!
//! The reverse direction (°C → ADC) gives the MCU's `min_value`/`max_value` range check.

/// 0 °C in kelvin.
pub const KELVIN: f64 = 273.15;
/// Callendar–Van Dusen A (IEC 60751).
pub const CVD_A: f64 = 3.9083e-3;
/// Callendar–Van Dusen B (IEC 60751).
pub const CVD_B: f64 = -5.775e-7;
/// Callendar–Van Dusen C, below 0 °C (IEC 60751).
pub const CVD_C: f64 = -4.183e-12;
/// ADC fractions are kept this far from 0 and 1 so that the divider stays finite.
const ADC_EPSILON: f64 = 1e-5;

/// Why a sensor cannot be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SensorError {
    /// The three points do not give a valid Steinhart–Hart fit (not an NTC).
    #[error(
        "the thermistor's points do not describe a thermistor (resistance must fall as temperature rises)"
    )]
    BadPoints,
    /// β must be positive.
    #[error("beta must be above 0, got {0}")]
    BadBeta(f64),
    /// `sensor_type` is not a known sensor.
    #[error("unknown sensor_type '{0}'")]
    Unknown(String),
}

/// Steinhart–Hart coefficients of an NTC thermistor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SteinhartHart {
    /// c1.
    pub c1: f64,
    /// c2.
    pub c2: f64,
    /// c3 (0 for the β form).
    pub c3: f64,
}

impl SteinhartHart {
    /// Fitted through three (°C, Ω) points.
    pub fn from_points(p1: (f64, f64), p2: (f64, f64), p3: (f64, f64)) -> Result<SteinhartHart, SensorError> {
        let inv = |t: f64| 1.0 / (t + KELVIN);
        let (l1, l2, l3) = (p1.1.ln(), p2.1.ln(), p3.1.ln());
        let (y1, y2, y3) = (inv(p1.0), inv(p2.0), inv(p3.0));
        // 1/T − 1/T1 = c2·(L − L1) + c3·(L³ − L1³), two equations in c2, c3.
        let (a1, b1, r1) = (l2 - l1, l2.powi(3) - l1.powi(3), y2 - y1);
        let (a2, b2, r2) = (l3 - l1, l3.powi(3) - l1.powi(3), y3 - y1);
        let det = a1 * b2 - a2 * b1;
        if !det.is_finite() || det == 0.0 {
            return Err(SensorError::BadPoints);
        }
        let c2 = (r1 * b2 - r2 * b1) / det;
        let c3 = (a1 * r2 - a2 * r1) / det;
        if c3 <= 0.0 {
            // Points whose fit bends the wrong way (a negative c3 has no resistance at all
            // for some temperatures): as Klipper does, the β through the outer two points.
            return SteinhartHart::from_beta(p1.0, p1.1, (l1 - l3) / (y1 - y3));
        }
        let c1 = y1 - c2 * l1 - c3 * l1.powi(3);
        let sh = SteinhartHart { c1, c2, c3 };
        if !(c1.is_finite() && c2 > 0.0 && c3.is_finite()) {
            return Err(SensorError::BadPoints);
        }
        Ok(sh)
    }

    /// The β form: resistance `r` (Ω) at `t` (°C) and β.
    pub fn from_beta(t: f64, r: f64, beta: f64) -> Result<SteinhartHart, SensorError> {
        if !(beta > 0.0 && beta.is_finite()) {
            return Err(SensorError::BadBeta(beta));
        }
        if !(r > 0.0 && r.is_finite()) {
            return Err(SensorError::BadPoints);
        }
        let c2 = 1.0 / beta;
        Ok(SteinhartHart {
            c1: 1.0 / (t + KELVIN) - c2 * r.ln(),
            c2,
            c3: 0.0,
        })
    }

    /// Temperature (°C) at resistance `r` (Ω).
    pub fn temperature(&self, r: f64) -> f64 {
        let l = r.max(f64::MIN_POSITIVE).ln();
        1.0 / (self.c1 + self.c2 * l + self.c3 * l.powi(3)) - KELVIN
    }

    /// Resistance (Ω) at `t` (°C): solves `c3·L³ + c2·L + (c1 − 1/T) = 0` for `L = ln R`
    /// (one real root since c2, c3 ≥ 0 in practice; Cardano).
    pub fn resistance(&self, t: f64) -> f64 {
        let k = self.c1 - 1.0 / (t + KELVIN);
        if self.c3 == 0.0 {
            return (-k / self.c2).exp();
        }
        let p = self.c2 / self.c3;
        let q = k / self.c3;
        let y = q / 2.0;
        let x = ((p / 3.0).powi(3) + y * y).sqrt();
        ((x - y).cbrt() - (x + y).cbrt()).exp()
    }
}

/// Resistance of a platinum RTD with `r0` Ω at 0 °C, at `t` °C.
pub fn rtd_resistance(r0: f64, t: f64) -> f64 {
    let c = if t < 0.0 {
        CVD_C * (t - 100.0) * t.powi(3)
    } else {
        0.0
    };
    r0 * (1.0 + CVD_A * t + CVD_B * t * t + c)
}

/// Temperature (°C) of a platinum RTD with `r0` Ω at 0 °C reading `r` Ω.
pub fn rtd_temperature(r0: f64, r: f64) -> f64 {
    // Above 0 °C the quadratic inverts exactly.
    let ratio = r / r0;
    if ratio >= 1.0 {
        return (-CVD_A + (CVD_A * CVD_A - 4.0 * CVD_B * (1.0 - ratio)).sqrt()) / (2.0 * CVD_B);
    }
    // Below: Newton from the quadratic's estimate (the C term is tiny).
    let mut t = (-CVD_A + (CVD_A * CVD_A - 4.0 * CVD_B * (1.0 - ratio)).max(0.0).sqrt()) / (2.0 * CVD_B);
    for _ in 0..20 {
        let f = rtd_resistance(r0, t) - r;
        let d = r0 * (CVD_A + 2.0 * CVD_B * t + CVD_C * (4.0 * t.powi(3) - 300.0 * t * t));
        let step = f / d;
        t -= step;
        if step.abs() < 1e-9 {
            break;
        }
    }
    t
}

/// How a sensor's element becomes an ADC reading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Element {
    /// An NTC thermistor.
    Thermistor(SteinhartHart),
    /// A platinum RTD with this resistance at 0 °C, directly under the pull-up.
    Rtd {
        /// Ω at 0 °C.
        r0: f64,
    },
    /// A linear sensor, `T = base + slope · adc` (the MCU's own sensor, see
    /// [`super::mcu_sensor`]).
    Linear {
        /// °C at adc 0.
        base: f64,
        /// °C per unit of adc.
        slope: f64,
    },
    /// A PT100 through the INA826 amplifier: `V = gain · supply · R / (R + pullup)`.
    Ina826Pt100 {
        /// The ADC's reference voltage (`adc_voltage`, default 5).
        adc_voltage: f64,
    },
}

/// The INA826 board's pull-up (Ω), supply (V) and gain.
const INA826: (f64, f64, f64) = (4400.0, 5.0, 10.0);

/// A sensor as configured: element, pull-up and inline resistors.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sensor {
    /// The element.
    pub element: Element,
    /// `pullup_resistor` (Ω), Klipper's default 4700.
    pub pullup: f64,
    /// `inline_resistor` (Ω) in series with the element, default 0.
    pub inline: f64,
}

impl Sensor {
    /// The named `sensor_type` with the given resistors.
    pub fn named(sensor_type: &str, pullup: f64, inline: f64) -> Result<Sensor, SensorError> {
        Ok(Sensor {
            element: named(sensor_type)?,
            pullup,
            inline,
        })
    }

    /// Temperature (°C) for an ADC fraction (0..1 of full scale).
    pub fn temperature(&self, adc: f64) -> f64 {
        let adc = adc.clamp(ADC_EPSILON, 1.0 - ADC_EPSILON);
        match self.element {
            Element::Thermistor(sh) => sh.temperature(self.resistance_of(adc)),
            Element::Rtd { r0 } => rtd_temperature(r0, self.resistance_of(adc)),
            Element::Linear { base, slope } => base + slope * adc,
            Element::Ina826Pt100 { adc_voltage } => {
                let (pullup, supply, gain) = INA826;
                // v/(gain·supply) = R/(R + pullup).
                let x = (adc * adc_voltage / (gain * supply)).clamp(ADC_EPSILON, 1.0 - ADC_EPSILON);
                rtd_temperature(100.0, pullup * x / (1.0 - x))
            }
        }
    }

    /// ADC fraction (0..1) the sensor reads at `t` °C.
    pub fn adc(&self, t: f64) -> f64 {
        let divider = |r: f64| {
            let r = r + self.inline;
            r / (r + self.pullup)
        };
        match self.element {
            Element::Thermistor(sh) => divider(sh.resistance(t)),
            Element::Rtd { r0 } => divider(rtd_resistance(r0, t)),
            Element::Linear { base, slope } => ((t - base) / slope).clamp(0.0, 1.0),
            Element::Ina826Pt100 { adc_voltage } => {
                let (pullup, supply, gain) = INA826;
                let r = rtd_resistance(100.0, t);
                (gain * supply * r / (r + pullup) / adc_voltage).clamp(0.0, 1.0)
            }
        }
    }

    fn resistance_of(&self, adc: f64) -> f64 {
        (self.pullup * adc / (1.0 - adc) - self.inline).max(f64::MIN_POSITIVE)
    }
}

/// The thermistors of Klipper's list, by datasheet points (°C, Ω) or β.
const NAMED: &[(&str, Def)] = &[
    (
        "EPCOS 100K B57560G104F",
        Def::Points((25.0, 100_000.0), (150.0, 1641.9), (250.0, 226.15)),
    ),
    (
        "ATC Semitec 104GT-2",
        Def::Points((20.0, 126_800.0), (150.0, 1360.0), (300.0, 80.65)),
    ),
    (
        "ATC Semitec 104NT-4-R025H42G",
        Def::Points((25.0, 100_000.0), (160.0, 1074.0), (300.0, 82.78)),
    ),
    ("Generic 3950", Def::Beta(25.0, 100_000.0, 3950.0)),
    (
        "Honeywell 100K 135-104LAG-J01",
        Def::Beta(25.0, 100_000.0, 3974.0),
    ),
    ("NTC 100K MGB18-104F39050L32", Def::Beta(25.0, 100_000.0, 4100.0)),
    (
        "SliceEngineering 450",
        Def::Points((25.0, 500_000.0), (200.0, 3734.0), (400.0, 240.0)),
    ),
    (
        "TDK NTCG104LH104JT1",
        Def::Points((25.0, 100_000.0), (50.0, 31_230.0), (125.0, 2066.0)),
    ),
];

#[derive(Debug, Clone, Copy)]
enum Def {
    Points((f64, f64), (f64, f64), (f64, f64)),
    Beta(f64, f64, f64),
}

/// The names [`named`] knows.
pub fn sensor_types() -> impl Iterator<Item = &'static str> {
    NAMED.iter().map(|(n, _)| *n).chain(["PT1000", "PT100 INA826"])
}

/// The element of a named `sensor_type` (Klipper's spelling; case-insensitive).
pub fn named(sensor_type: &str) -> Result<Element, SensorError> {
    let want = sensor_type.trim();
    if want.eq_ignore_ascii_case("PT1000") {
        return Ok(Element::Rtd { r0: 1000.0 });
    }
    if want.eq_ignore_ascii_case("PT100 INA826") {
        return Ok(Element::Ina826Pt100 { adc_voltage: 5.0 });
    }
    let (_, def) = NAMED
        .iter()
        .find(|(n, _)| n.eq_ignore_ascii_case(want))
        .ok_or_else(|| SensorError::Unknown(want.to_string()))?;
    let sh = match *def {
        Def::Points(a, b, c) => SteinhartHart::from_points(a, b, c)?,
        Def::Beta(t, r, beta) => SteinhartHart::from_beta(t, r, beta)?,
    };
    Ok(Element::Thermistor(sh))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol
    }

    #[test]
    fn named_thermistors_pass_through_their_datasheet_points() {
        for (name, def) in NAMED {
            let Element::Thermistor(sh) = named(name).unwrap() else {
                panic!("{name}")
            };
            let points: Vec<(f64, f64)> = match *def {
                Def::Points(a, b, c) => vec![a, b, c],
                Def::Beta(t, r, _) => vec![(t, r)],
            };
            for (t, r) in points {
                assert!(close(sh.temperature(r), t, 1e-6), "{name} at {r} Ω");
                assert!(close(sh.resistance(t) / r, 1.0, 1e-6), "{name} at {t} °C");
            }
            // NTC: resistance falls as it heats.
            assert!(sh.resistance(100.0) < sh.resistance(50.0), "{name}");
        }
        assert_eq!(sensor_types().count(), NAMED.len() + 2);
        assert!(matches!(named("generic 3950"), Ok(Element::Thermistor(_))));
        assert_eq!(named("Bogus"), Err(SensorError::Unknown("Bogus".into())));
    }

    #[test]
    fn points_that_bend_the_fit_the_wrong_way_give_the_beta_of_the_outer_two() {
        // The Makibox bed thermistor (Klipper's printer-robo3d-r2-2017.cfg): c3 < 0, β 4699.8.
        let sh = SteinhartHart::from_points((25.0, 100_000.0), (50.0, 29_536.0), (125.0, 1908.0)).unwrap();
        assert_eq!(sh.c3, 0.0);
        assert!(close(1.0 / sh.c2, 4699.8, 0.1), "{}", 1.0 / sh.c2);
        assert!(close(sh.resistance(25.0), 100_000.0, 1e-6));
        assert!(close(sh.resistance(125.0), 1908.0, 1e-6));
        let s = Sensor {
            element: Element::Thermistor(sh),
            pullup: 4700.0,
            inline: 0.0,
        };
        for t in [-40.0, 0.0, 25.0, 60.0, 125.0, 300.0] {
            let adc = s.adc(t);
            assert!(adc > 0.0 && adc < 1.0, "{t}: {adc}");
            assert!(close(s.temperature(adc), t, 1e-6), "{t}");
        }
    }

    #[test]
    fn beta_3950_matches_its_formula_and_the_simulator() {
        // β: R(100 °C) = 100k·e^(3950·(1/373.15 − 1/298.15)) = 100k·e^(−2.66281) = 6.9752 kΩ.
        let Element::Thermistor(sh) = named("Generic 3950").unwrap() else {
            panic!()
        };
        assert!(
            close(sh.resistance(100.0), 6975.2, 0.5),
            "{}",
            sh.resistance(100.0)
        );
        // The simulator's hotend thermistor is this sensor under a 4.7k pull-up.
        let s = Sensor::named("Generic 3950", 4700.0, 0.0).unwrap();
        for t in [25.0, 100.0, 210.0, 250.0] {
            let adc = firmware::sim::heater::adc_of(t) as f64 / 4095.0;
            assert!(close(s.temperature(adc), t, 0.6), "{t}: {}", s.temperature(adc));
        }
    }

    #[test]
    fn pt100_and_pt1000_follow_iec_60751() {
        // IEC 60751 table: PT100 100.00 Ω at 0 °C, 138.51 at 100, 175.86 at 200, 212.05 at 300,
        // 80.31 at −50.
        for (t, r) in [
            (0.0, 100.0),
            (100.0, 138.51),
            (200.0, 175.86),
            (300.0, 212.05),
            (-50.0, 80.31),
        ] {
            assert!(
                close(rtd_resistance(100.0, t), r, 0.01),
                "{t}: {}",
                rtd_resistance(100.0, t)
            );
            assert!(
                close(rtd_temperature(100.0, r), t, 0.03),
                "{r}: {}",
                rtd_temperature(100.0, r)
            );
            assert!(close(rtd_resistance(1000.0, t), 10.0 * r, 0.1));
        }
        let pt1000 = Sensor::named("PT1000", 4700.0, 0.0).unwrap();
        let amp = Sensor::named("PT100 INA826", 4700.0, 0.0).unwrap();
        for t in [20.0, 150.0, 280.0] {
            assert!(close(pt1000.temperature(pt1000.adc(t)), t, 1e-6));
            assert!(close(amp.temperature(amp.adc(t)), t, 1e-6));
        }
        // The amplifier's output at 100 °C: 10 · 5 V · 138.51/(138.51 + 4400) = 1.526 V of 5 V.
        assert!(close(amp.adc(100.0), 1.526 / 5.0, 0.001), "{}", amp.adc(100.0));
    }

    #[test]
    fn inline_resistor_and_bad_definitions() {
        let plain = Sensor::named("EPCOS 100K B57560G104F", 4700.0, 0.0).unwrap();
        let inline = Sensor::named("EPCOS 100K B57560G104F", 4700.0, 100.0).unwrap();
        // The inline resistor adds to the element: the same reading is a hotter element.
        let adc = plain.adc(250.0);
        assert!(inline.temperature(adc) > 255.0, "{}", inline.temperature(adc));
        assert!(close(inline.temperature(inline.adc(250.0)), 250.0, 1e-6));
        assert!(SteinhartHart::from_points((25.0, 100.0), (50.0, 200.0), (75.0, 400.0)).is_err());
        assert_eq!(
            SteinhartHart::from_beta(25.0, 1e5, 0.0),
            Err(SensorError::BadBeta(0.0))
        );
        // An open sensor (ADC at max) reads colder than any min_temp; a short, hotter.
        assert!(plain.temperature(1.0) < -50.0);
        assert!(plain.temperature(0.0) > 500.0);
    }

    #[test]
    fn adc_and_temperature_invert_over_the_range() {
        for name in sensor_types() {
            let s = Sensor::named(name, 4700.0, 0.0).unwrap();
            for step in 0..=740 {
                let t = -20.0 + 0.5 * step as f64;
                let adc = s.adc(t);
                if adc > 2.0 * ADC_EPSILON && adc < 1.0 - 2.0 * ADC_EPSILON {
                    assert!(close(s.temperature(adc), t, 1e-4), "{name} {t}");
                }
            }
        }
    }

    #[test]
    fn any_reading_gives_a_number() {
        let s = Sensor::named("ATC Semitec 104GT-2", 4700.0, 0.0).unwrap();
        for adc in [f64::NEG_INFINITY, -1.0, 0.0, 1e-300, 0.5, 1.0, 2.0, f64::INFINITY] {
            assert!(!s.temperature(adc).is_nan(), "{adc}");
        }
    }
}
