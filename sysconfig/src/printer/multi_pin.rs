//! `[multi_pin NAME]`: several output pins driven as one (`pins: PB4, PB5, PB0`), named
//! `multi_pin:NAME` by a heater or fan; each pin gets the same commands, as Klipper's
//! multi_pin does. The group's pins are claimed by the section that names the group.

use super::error::{ConfigError, ValueProblem};
use super::pins::{PinKind, PinRef, PinRegistry};
use super::reader::Reader;

/// The chip name of the groups' pins (`multi_pin:NAME`).
pub const MULTI_PIN_CHIP: &str = "multi_pin";

/// `[multi_pin NAME]`.
#[derive(Debug, Clone, PartialEq)]
pub struct MultiPinSection {
    /// NAME.
    pub name: String,
    /// `pins`, in order (at least one; on one MCU).
    pub pins: Vec<PinRef>,
}

/// Reads every `[multi_pin NAME]` and declares its group to `pins`.
pub(crate) fn read_multi_pins(
    reader: &Reader<'_>,
    pins: &mut PinRegistry,
) -> Result<Vec<MultiPinSection>, ConfigError> {
    let mut out = Vec::new();
    for s in reader.sections_with_arg("multi_pin") {
        let name = s.arg().unwrap_or_default().to_string();
        let v = s.required("pins")?;
        let mut group = Vec::new();
        for text in v.text.split(',').map(str::trim).filter(|t| !t.is_empty()) {
            let pin = PinRef::parse(text, PinKind::Output).map_err(|problem| {
                s.bad(
                    "pins",
                    v,
                    ValueProblem::BadPin {
                        pin: text.to_string(),
                        problem,
                    },
                )
            })?;
            let pin = pins.resolve(pin).map_err(|p| s.bad("pins", v, p))?;
            if pin.mcu == MULTI_PIN_CHIP {
                let why = format!("pin '{pin}': a multi_pin can not name another multi_pin");
                return Err(s.bad("pins", v, ValueProblem::Invalid(why)));
            }
            group.push(pin);
        }
        if group.is_empty() {
            return Err(s.bad("pins", v, ValueProblem::Invalid("names no pin".to_string())));
        }
        if group.iter().any(|p| p.mcu != group[0].mcu) {
            let why = "the pins of a multi_pin must be on one MCU in Cadence".to_string();
            return Err(s.bad("pins", v, ValueProblem::Invalid(why)));
        }
        pins.add_multi_pin(&name, group.clone());
        out.push(MultiPinSection { name, pins: group });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use crate::printer::{parse_str, SIMULATED_PRINTER_CFG as BASE};
    use std::path::Path;

    fn load(extra: &str) -> Result<crate::printer::PrinterConfig, String> {
        parse_str(&format!("{BASE}\n{extra}"), Path::new("printer.cfg")).map_err(|e| e.to_string())
    }

    #[test]
    fn a_group_is_claimed_by_the_section_naming_it() {
        let cfg = load("[multi_pin fans]\npins: PE6, !PE7\n\n[fan_generic both]\npin: multi_pin:fans\n")
            .unwrap_or_else(|e| panic!("{e}"));
        let g = &cfg.thermal.multi_pins[0];
        assert_eq!(g.name, "fans");
        assert_eq!(
            g.pins
                .iter()
                .map(|p| (p.pin.as_str(), p.invert))
                .collect::<Vec<_>>(),
            [("PE6", false), ("PE7", true)]
        );
        let e = load("[multi_pin fans]\npins: PE6, PE7\n\n[fan_generic a]\npin: multi_pin:fans\n[fan_generic b]\npin: PE7\n")
            .unwrap_err();
        assert!(e.contains("pin 'PE7' is also used by [fan_generic a] pin"), "{e}");
        let e = load("[fan_generic a]\npin: multi_pin:nope\n").unwrap_err();
        assert!(e.contains("there is no [multi_pin nope]"), "{e}");
        let e = load("[multi_pin fans]\npins: PE6\n\n[temperature_sensor t]\nsensor_type: Generic 3950\nsensor_pin: multi_pin:fans\n")
            .unwrap_err();
        assert!(e.contains("multi_pin only supports output pins"), "{e}");
    }
}
