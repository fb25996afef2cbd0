//! `[adc_scaled NAME]`: an MCU's ADC readings corrected by its measured reference voltages
//! (Duet boards). The section's `vref_pin` reads the ADC's top reference and `vssa_pin` its
//! bottom; analog pins named `NAME:PIN` are PIN of the same MCU, whose readings the host scales
//! as Klipper does: `(value − vssa) / (vref − vssa)`, with vref and vssa smoothed over
//! `smooth_time`.
//!
//! Only analog pins may be named through the chip (`adc_scaled only supports adc pins`).

use super::error::{ConfigError, ValueProblem};
use super::pins::{PinKind, PinRef, PinRegistry, Share};
use super::reader::{Bounds, Reader};

/// `[adc_scaled NAME]`.
#[derive(Debug, Clone, PartialEq)]
pub struct AdcScaledSection {
    /// NAME: the chip name of its pins (`NAME:PC29`).
    pub name: String,
    /// `vref_pin`: the ADC's top reference.
    pub vref_pin: PinRef,
    /// `vssa_pin`: the ADC's bottom reference (same MCU).
    pub vssa_pin: PinRef,
    /// `smooth_time` (s, default 2).
    pub smooth_time: f64,
}

/// Reads every `[adc_scaled NAME]` and declares its chip to `pins` (so that later sections may
/// name `NAME:PIN`).
pub(crate) fn read_adc_scaled(
    reader: &Reader<'_>,
    pins: &mut PinRegistry,
) -> Result<Vec<AdcScaledSection>, ConfigError> {
    let mut out = Vec::new();
    for s in reader.sections_with_arg("adc_scaled") {
        let name = s.arg().unwrap_or_default().to_string();
        let vref_pin = s.pin("vref_pin", PinKind::Analog, pins, Share::Exclusive)?;
        let vssa_pin = s.pin("vssa_pin", PinKind::Analog, pins, Share::Exclusive)?;
        if vref_pin.mcu != vssa_pin.mcu {
            let v = s.required("vssa_pin")?;
            return Err(s.bad(
                "vssa_pin",
                v,
                ValueProblem::Invalid("vref and vssa must be on same mcu".to_string()),
            ));
        }
        let smooth_time = s.float_or("smooth_time", 2.0, Bounds::ANY.above(0.0))?;
        pins.add_scaled_chip(&name, &vref_pin.mcu);
        out.push(AdcScaledSection {
            name,
            vref_pin,
            vssa_pin,
            smooth_time,
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use crate::printer::{parse_str, SIMULATED_PRINTER_CFG as BASE};
    use std::path::Path;

    #[test]
    fn a_scaled_pin_is_an_adc_pin_of_the_chips_mcu() {
        let text = format!(
            "{}\n[adc_scaled vref_scaled]\nvref_pin: PK0\nvssa_pin: PK1\n\n[temperature_sensor board]\n\
             sensor_type: Generic 3950\nsensor_pin: vref_scaled:PK2\n",
            BASE
        );
        let cfg = parse_str(&text, Path::new("printer.cfg")).unwrap_or_else(|e| panic!("{e}"));
        let a = &cfg.thermal.adc_scaled[0];
        assert_eq!(
            (a.name.as_str(), a.vref_pin.pin.as_str(), a.vssa_pin.pin.as_str()),
            ("vref_scaled", "PK0", "PK1")
        );
        assert_eq!(a.smooth_time, 2.0);
        let err = |extra: &str| {
            parse_str(
                &format!("{BASE}\n[adc_scaled vref_scaled]\nvref_pin: PK0\nvssa_pin: PK1\n{extra}"),
                Path::new("printer.cfg"),
            )
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default()
        };
        // Not an output, and one pin once.
        let e = err("\n[fan_generic f]\npin: vref_scaled:PK3\n");
        assert!(e.contains("adc_scaled only supports adc pins"), "{e}");
        let e = err("\n[temperature_sensor a]\nsensor_type: Generic 3950\nsensor_pin: vref_scaled:PK0\n");
        assert!(
            e.contains("also used by [adc_scaled vref_scaled] vref_pin"),
            "{e}"
        );
        let e = err("smooth_time: 0\n");
        assert!(
            e.contains("[adc_scaled vref_scaled] smooth_time: must be above 0"),
            "{e}"
        );
    }
}
