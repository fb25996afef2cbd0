//! A simulated ADC with measurable references (a Duet board's `vref_pin`/`vssa_pin`, read by
//! Klipper's `[adc_scaled]`): its conversions carry an offset and a gain error, and its two
//! reference inputs read the ends of its true range, so a host that rescales between them
//! reads true values and one that does not is off.
//!
//! A true fraction `x` of full scale reads `VSSA + x·(VREF − VSSA)` counts: the bottom
//! reference (`x = 0`) reads [`VSSA_COUNTS`], the top (`x = 1`) [`VREF_COUNTS`].

use super::cli::parse_pin;

/// What the bottom reference reads (the ADC's offset).
pub const VSSA_COUNTS: f64 = 20.0;
/// What the top reference reads (full scale less the gain error).
pub const VREF_COUNTS: f64 = 4040.0;

/// `--adc-ref VREF_PIN=VSSA_PIN`: the reference inputs of an ADC with offset and gain error.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AdcRefSpec {
    /// The top reference's pin.
    pub vref_pin: u8,
    /// The bottom reference's pin.
    pub vssa_pin: u8,
}

impl AdcRefSpec {
    /// Parses `VREF_PIN=VSSA_PIN`.
    pub fn parse(s: &str) -> Result<AdcRefSpec, String> {
        let (a, b) = s.split_once('=').ok_or("expected VREF_PIN=VSSA_PIN")?;
        Ok(AdcRefSpec {
            vref_pin: parse_pin(a)?,
            vssa_pin: parse_pin(b)?,
        })
    }

    /// What input `pin` reads when a perfect ADC (of `adc_max`) would read `ideal`.
    pub fn read(&self, pin: u8, ideal: u16, adc_max: f64) -> u16 {
        let counts = if pin == self.vref_pin {
            VREF_COUNTS
        } else if pin == self.vssa_pin {
            VSSA_COUNTS
        } else {
            VSSA_COUNTS + f64::from(ideal) / adc_max * (VREF_COUNTS - VSSA_COUNTS)
        };
        counts.round().clamp(0.0, adc_max) as u16
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn references_bound_the_readings() {
        let a = AdcRefSpec::parse("PA17=PA19").unwrap();
        assert_eq!(a.read(a.vref_pin, 0, 4095.0), 4040);
        assert_eq!(a.read(a.vssa_pin, 4095, 4095.0), 20);
        assert_eq!(a.read(3, 0, 4095.0), 20);
        assert_eq!(a.read(3, 4095, 4095.0), 4040);
        assert!(AdcRefSpec::parse("PA17").is_err());
    }
}
