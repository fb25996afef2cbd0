//! An SPI device's configuration commands, as Klipper's host sends them: `config_spi` (the
//! chip select, released), then the bus — `spi_set_sw_bus` for software pins (a half clock
//! period of `clock_freq / (2·speed)` ticks) or `spi_set_bus` on the MCU's first hardware bus
//! (a named `spi_bus` is the board's wiring; the simulated MCU has one bus). Shared by the TMC
//! drivers and the SPI temperature chips.

use links::dict::{Cmd, DictError, Dictionary};

/// An SPI device's pins as MCU pin numbers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SpiPins {
    /// Chip select.
    pub cs: i64,
    /// Software bus: `(miso, mosi, sclk)`; `None` for the hardware bus.
    pub software: Option<(i64, i64, i64)>,
}

/// The commands configuring SPI device `oid` with `pins`, SPI `mode` and `speed` (Hz).
pub fn config_commands(
    dict: &Dictionary,
    clock_freq: f64,
    oid: i64,
    pins: SpiPins,
    mode: i64,
    speed: u32,
) -> Result<[Cmd; 2], DictError> {
    let bus = match pins.software {
        Some((miso, mosi, sclk)) => {
            let pulse_ticks = (clock_freq / (2.0 * f64::from(speed.max(1)))).ceil() as i64;
            dict.encode("spi_set_sw_bus", &[oid, miso, mosi, sclk, mode, pulse_ticks])?
        }
        None => dict.encode("spi_set_bus", &[oid, 0, mode, i64::from(speed)])?,
    };
    Ok([dict.encode("config_spi", &[oid, pins.cs, 0])?, bus])
}
