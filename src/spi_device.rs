//! An SPI device's configuration commands, as Klipper's host sends them: `config_spi` (the
//! chip select, released), then the bus — `spi_set_sw_bus` for software pins (a half clock
//! period of `clock_freq / (2·speed)` ticks) or `spi_set_bus` on a hardware bus. Shared by the
//! TMC drivers and the SPI temperature chips.
//!
//! A hardware bus is named by the MCU's dictionary (its `spi_bus` enumeration, as Klipper's
//! firmware declares it: `spi1`, `usart0`, `spidev0.1`…): `spi_bus` must be one of its names,
//! and without `spi_bus` the bus numbered 0 is used (an MCU with buses but none numbered 0
//! needs `spi_bus`). A dictionary without the enumeration takes bus 0, or a number.

use links::dict::{Cmd, DictError, Dictionary};

/// An SPI device's pins as MCU pin numbers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SpiPins {
    /// Chip select.
    pub cs: i64,
    /// Software bus: `(miso, mosi, sclk)`; `None` for the hardware bus.
    pub software: Option<(i64, i64, i64)>,
}

/// The number of hardware SPI bus `name` (`spi_bus`, `None` when not given) on the MCU whose
/// dictionary is `dict`.
pub fn hardware_bus(dict: &Dictionary, name: Option<&str>) -> Result<i64, DictError> {
    let mut symbols = dict.enumeration_symbols(SPI_BUS).peekable();
    if symbols.peek().is_none() {
        return match name {
            None => Ok(0),
            Some(n) => n
                .trim()
                .parse::<i64>()
                .map_err(|_| DictError::NoEnumeration(SPI_BUS.into())),
        };
    }
    match name {
        Some(n) => dict.enumeration(SPI_BUS, n.trim()),
        None => match symbols.find(|&(_, v)| v == 0) {
            Some(_) => Ok(0),
            None => Err(DictError::NoSymbol {
                enumeration: SPI_BUS.into(),
                symbol: "numbered 0 (the default when spi_bus is not set): set spi_bus".into(),
            }),
        },
    }
}

/// The dictionary enumeration naming the hardware SPI buses.
const SPI_BUS: &str = "spi_bus";

/// The commands configuring SPI device `oid` with `pins`, SPI `mode` and `speed` (Hz), on
/// hardware bus `bus` (`spi_bus`, read only without software pins, as on Klipper).
pub fn config_commands(
    dict: &Dictionary,
    clock_freq: f64,
    oid: i64,
    pins: SpiPins,
    bus: Option<&str>,
    mode: i64,
    speed: u32,
) -> Result<[Cmd; 2], DictError> {
    let bus = match pins.software {
        Some((miso, mosi, sclk)) => {
            let pulse_ticks = (clock_freq / (2.0 * f64::from(speed.max(1)))).ceil() as i64;
            dict.encode("spi_set_sw_bus", &[oid, miso, mosi, sclk, mode, pulse_ticks])?
        }
        None => dict.encode(
            "spi_set_bus",
            &[oid, hardware_bus(dict, bus)?, mode, i64::from(speed)],
        )?,
    };
    Ok([dict.encode("config_spi", &[oid, pins.cs, 0])?, bus])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dict(enums: &str) -> Dictionary {
        Dictionary::from_json(&format!(r#"{{"enumerations": {{{enums}}}}}"#)).expect("dictionary")
    }

    #[test]
    fn a_named_bus_is_the_dictionarys_and_the_default_is_bus_0() {
        let d = dict(r#""spi_bus": {"spi2": 0, "usart0": [1, 3]}"#);
        assert_eq!(hardware_bus(&d, Some("usart2")).unwrap(), 3);
        assert_eq!(hardware_bus(&d, Some(" spi2 ")).unwrap(), 0);
        assert_eq!(hardware_bus(&d, None).unwrap(), 0);
        let e = hardware_bus(&d, Some("spi9")).unwrap_err().to_string();
        assert_eq!(e, "MCU dictionary has no spi_bus 'spi9'");
        // Buses, but none numbered 0: the config must name one (Klipper's rule).
        let d = dict(r#""spi_bus": {"ssp1": 1}"#);
        let e = hardware_bus(&d, None).unwrap_err().to_string();
        assert!(e.contains("spi_bus") && e.contains("set spi_bus"), "{e}");
    }

    #[test]
    fn without_the_enumeration_bus_0_or_a_number() {
        let d = dict(r#""pin": {"PA0": 0}"#);
        assert_eq!(hardware_bus(&d, None).unwrap(), 0);
        assert_eq!(hardware_bus(&d, Some("2")).unwrap(), 2);
        let e = hardware_bus(&d, Some("spi1")).unwrap_err().to_string();
        assert_eq!(e, "MCU dictionary has no enumeration 'spi_bus'");
    }
}
