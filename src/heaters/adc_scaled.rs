//! `[adc_scaled NAME]` on a live printer: the MCU's two reference inputs (`vref_pin`,
//! `vssa_pin`) are sampled like any sensor, each reading smoothed over `smooth_time` (Klipper's
//! smoothing), and the readings of the chip's pins are rescaled between them, as Klipper does:
//! `fraction = (reading − vssa) / (vref − vssa)`, every value an ADC fraction of full scale.
//! This cancels the ADC's offset and gain error (its references drift with the board's supply).

use links::mcu::McuLink;

use super::control::Smoothed;
use super::objects::REPORT_TIME;

/// One reference input's loop state.
#[derive(Debug)]
struct Reference {
    oid: u8,
    last_count: u16,
    smooth: Smoothed,
    value: Option<f64>,
}

impl Reference {
    fn new(oid: u8, smooth_time: f64) -> Reference {
        Reference {
            oid,
            last_count: 0,
            smooth: Smoothed::new(smooth_time),
            value: None,
        }
    }

    /// Takes the input's new report, if any.
    fn update(&mut self, link: &McuLink, freq: f64, full_scale: f64, now_sys: f64) {
        let Some((count, next_clock, value)) = link.analog_report(self.oid) else {
            return;
        };
        if count == self.last_count {
            return;
        }
        self.last_count = count;
        let read_clock = link
            .clock()
            .extend(next_clock, now_sys)
            .saturating_sub((REPORT_TIME * freq) as u64);
        let time = read_clock as f64 / freq;
        self.value = Some(self.smooth.update(time, f64::from(value) / full_scale));
    }
}

/// One `[adc_scaled]` chip's references on its MCU.
#[derive(Debug)]
pub struct ScaledRefs {
    /// The MCU's index in the printer's MCU list.
    pub link_index: usize,
    full_scale: f64,
    vref: Option<Reference>,
    vssa: Option<Reference>,
}

impl ScaledRefs {
    /// The chip of MCU `link_index`, whose reports sum readings to `full_scale`.
    pub fn new(link_index: usize, full_scale: f64) -> ScaledRefs {
        ScaledRefs {
            link_index,
            full_scale,
            vref: None,
            vssa: None,
        }
    }

    /// `vref_pin`'s analog input is object `oid`.
    pub fn set_vref(&mut self, oid: u8, smooth_time: f64) {
        self.vref = Some(Reference::new(oid, smooth_time));
    }

    /// `vssa_pin`'s analog input is object `oid`.
    pub fn set_vssa(&mut self, oid: u8, smooth_time: f64) {
        self.vssa = Some(Reference::new(oid, smooth_time));
    }

    /// Takes the references' new reports, if any.
    pub fn update(&mut self, link: &McuLink, freq: f64, now_sys: f64) {
        for r in [self.vref.as_mut(), self.vssa.as_mut()].into_iter().flatten() {
            r.update(link, freq, self.full_scale, now_sys);
        }
    }

    /// `fraction` (of full scale) rescaled between the references; `None` until both have
    /// read, or while they do not span a range.
    pub fn scale(&self, fraction: f64) -> Option<f64> {
        let vref = self.vref.as_ref()?.value?;
        let vssa = self.vssa.as_ref()?.value?;
        scale(fraction, vref, vssa)
    }
}

/// `(fraction − vssa) / (vref − vssa)`; `None` when `vref` is not above `vssa`.
pub fn scale(fraction: f64, vref: f64, vssa: f64) -> Option<f64> {
    (vref > vssa).then(|| (fraction - vssa) / (vref - vssa))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rescales_between_the_references() {
        assert_eq!(scale(0.5, 1.0, 0.0), Some(0.5));
        // An ADC reading 2 % high with a 1 % offset reads true once scaled.
        let (gain, offset) = (0.98, 0.01);
        let raw = |x: f64| offset + x * gain;
        let got = scale(raw(0.3), raw(1.0), raw(0.0)).unwrap();
        assert!((got - 0.3).abs() < 1e-12, "{got}");
        assert_eq!(scale(0.5, 0.2, 0.2), None);
    }
}
