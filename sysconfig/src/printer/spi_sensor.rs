//! SPI temperature chips as a heater's or a `[temperature_sensor]`'s `sensor_type` (MAX6675,
//! MAX31855, MAX31856, MAX31865) with Klipper's options: `sensor_pin` (the chip select),
//! the bus (`spi_bus`, `spi_speed`, or `spi_software_sclk_pin` / `_mosi_pin` / `_miso_pin`),
//! and the chips' own settings (`rtd_*` of the MAX31865, `tc_*` of the MAX31856).
//!
//! [`read_spi_bus`] is the SPI device reader shared with the TMC drivers.

use super::error::ConfigError;
use super::pins::{PinKind, PinRef, PinRegistry, Share};
use super::reader::{Bounds, SectionReader};

/// An SPI temperature chip.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SpiChip {
    /// K thermocouple, 12-bit.
    Max6675,
    /// Thermocouple, 14-bit.
    Max31855,
    /// Any thermocouple type, 19-bit.
    Max31856,
    /// Platinum RTD.
    Max31865,
}

/// The chips by `sensor_type` name.
pub const SPI_CHIPS: [(&str, SpiChip); 4] = [
    ("MAX6675", SpiChip::Max6675),
    ("MAX31855", SpiChip::Max31855),
    ("MAX31856", SpiChip::Max31856),
    ("MAX31865", SpiChip::Max31865),
];

impl SpiChip {
    /// The chip of `sensor_type`, if it is one.
    pub fn of(sensor_type: &str) -> Option<SpiChip> {
        SPI_CHIPS.iter().find(|(n, _)| *n == sensor_type).map(|&(_, c)| c)
    }

    /// Its name (the MCU's `thermocouple_type`).
    pub fn name(self) -> &'static str {
        SPI_CHIPS.iter().find(|(_, c)| *c == self).map_or("", |(n, _)| n)
    }

    /// Its SPI mode (Klipper's: mode 1 for the register chips, 0 for the shift registers).
    pub fn spi_mode(self) -> u8 {
        match self {
            SpiChip::Max6675 | SpiChip::Max31855 => 0,
            SpiChip::Max31856 | SpiChip::Max31865 => 1,
        }
    }
}

/// An SPI device: its chip select and its bus.
#[derive(Debug, Clone, PartialEq)]
pub struct SpiBus {
    /// The chip select.
    pub cs_pin: PinRef,
    /// `spi_speed` (Hz).
    pub speed: u32,
    /// `spi_bus` as written (the board's hardware bus).
    pub bus: Option<String>,
    /// `spi_software_sclk_pin`, `spi_software_mosi_pin`, `spi_software_miso_pin`.
    pub software: Option<[PinRef; 3]>,
}

/// The SPI device of section `s`: chip select option `cs_option` (claimed with `share`), the
/// bus options, `spi_speed` defaulting to `default_speed`.
pub(crate) fn read_spi_bus(
    s: &SectionReader<'_>,
    pins: &mut PinRegistry,
    cs_option: &str,
    share: Share,
    default_speed: u32,
) -> Result<SpiBus, ConfigError> {
    let cs_pin = s.pin(cs_option, PinKind::Output, pins, share)?;
    let speed = s.int::<u32>("spi_speed", Some(default_speed), 100_000..=i64::from(u32::MAX))?;
    let bus = s.value("spi_bus").map(|v| v.text.clone());
    let sw = [
        "spi_software_sclk_pin",
        "spi_software_mosi_pin",
        "spi_software_miso_pin",
    ];
    let software = match s.value(sw[0]) {
        Some(_) => Some([
            s.pin(sw[0], PinKind::Output, pins, Share::SpiBus)?,
            s.pin(sw[1], PinKind::Output, pins, Share::SpiBus)?,
            s.pin(sw[2], PinKind::Input, pins, Share::SpiBus)?,
        ]),
        None => None,
    };
    Ok(SpiBus {
        cs_pin,
        speed,
        bus,
        software,
    })
}

/// An SPI temperature chip's configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct SpiSensorSection {
    /// The chip.
    pub chip: SpiChip,
    /// Its SPI device (`sensor_pin` the chip select; `spi_speed` default 4 MHz).
    pub bus: SpiBus,
    /// MAX31865: `rtd_nominal_r` (Ω at 0 °C, default 100).
    pub rtd_nominal_r: f64,
    /// MAX31865: `rtd_reference_r` (Ω, default 430).
    pub rtd_reference_r: f64,
    /// MAX31865: `rtd_num_of_wires` (2, 3 or 4; default 2).
    pub rtd_num_of_wires: u8,
    /// MAX31865: `rtd_use_50Hz_filter` (default false).
    pub rtd_use_50hz_filter: bool,
    /// MAX31856: `tc_type` (B, E, J, K, N, R, S, T; default K) as the chip's code.
    pub tc_type: u8,
    /// MAX31856: `tc_use_50Hz_filter` (default false).
    pub tc_use_50hz_filter: bool,
    /// MAX31856: `tc_averaging_count` (1, 2, 4, 8, 16; default 1).
    pub tc_averaging_count: u8,
}

/// The MAX31856's thermocouple types and their codes.
const TC_TYPES: [(&str, u8); 8] = [
    ("B", 0),
    ("E", 1),
    ("J", 2),
    ("K", 3),
    ("N", 4),
    ("R", 5),
    ("S", 6),
    ("T", 7),
];

/// Chip `chip`'s options in section `s`.
pub(crate) fn read_spi_sensor(
    s: &SectionReader<'_>,
    pins: &mut PinRegistry,
    chip: SpiChip,
) -> Result<SpiSensorSection, ConfigError> {
    let bus = read_spi_bus(s, pins, "sensor_pin", Share::Exclusive, 4_000_000)?;
    let mut out = SpiSensorSection {
        chip,
        bus,
        rtd_nominal_r: 100.0,
        rtd_reference_r: 430.0,
        rtd_num_of_wires: 2,
        rtd_use_50hz_filter: false,
        tc_type: 3,
        tc_use_50hz_filter: false,
        tc_averaging_count: 1,
    };
    match chip {
        SpiChip::Max31865 => {
            out.rtd_nominal_r = s.float_or("rtd_nominal_r", 100.0, Bounds::ANY.above(0.0))?;
            out.rtd_reference_r = s.float_or("rtd_reference_r", 430.0, Bounds::ANY.above(0.0))?;
            out.rtd_num_of_wires = s.choice("rtd_num_of_wires", &[("2", 2), ("3", 3), ("4", 4)], Some(2))?;
            out.rtd_use_50hz_filter = s.opt_bool("rtd_use_50hz_filter")?.unwrap_or(false);
        }
        SpiChip::Max31856 => {
            out.tc_type = s.choice("tc_type", &TC_TYPES, Some(3))?;
            out.tc_use_50hz_filter = s.opt_bool("tc_use_50hz_filter")?.unwrap_or(false);
            let counts = [("1", 1), ("2", 2), ("4", 4), ("8", 8), ("16", 16)];
            out.tc_averaging_count = s.choice("tc_averaging_count", &counts, Some(1))?;
        }
        SpiChip::Max6675 | SpiChip::Max31855 => {}
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ini;
    use crate::printer::reader::Reader;
    use proptest::prelude::*;
    use std::path::Path;

    fn sensor(chip: SpiChip, body: &str) -> Result<SpiSensorSection, String> {
        let text = format!("[temperature_sensor t]\n{body}");
        let file = ini::parse_str(&text, Path::new("printer.cfg")).map_err(|e| e.to_string())?;
        let reader = Reader::new(&file);
        let s = reader.section("temperature_sensor t").ok_or("no section")?;
        let out = read_spi_sensor(&s, &mut PinRegistry::new(vec!["mcu".into()]), chip)
            .map_err(|e| e.to_string())?;
        reader.finish(|_| false).map_err(|e| e.to_string())?;
        Ok(out)
    }

    #[test]
    fn rtd_options_and_defaults() {
        let s = sensor(
            SpiChip::Max31865,
            "sensor_pin: PB2\nspi_bus: usart0\nrtd_nominal_r: 100\nrtd_reference_r: 400\n\
             rtd_num_of_wires: 2\nrtd_use_50Hz_filter: True\n",
        )
        .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            (
                s.rtd_nominal_r,
                s.rtd_reference_r,
                s.rtd_num_of_wires,
                s.rtd_use_50hz_filter
            ),
            (100.0, 400.0, 2, true)
        );
        assert_eq!(s.bus.bus.as_deref(), Some("usart0"));
        assert_eq!(s.bus.speed, 4_000_000);
        let e = sensor(SpiChip::Max31865, "sensor_pin: PB2\nrtd_num_of_wires: 5\n").unwrap_err();
        assert!(
            e.contains("printer.cfg:3") && e.contains("rtd_num_of_wires"),
            "{e}"
        );
    }

    #[test]
    fn software_bus_and_thermocouple_options() {
        let s = sensor(
            SpiChip::Max6675,
            "sensor_pin: PE3\nspi_software_miso_pin: PE5\nspi_software_sclk_pin: PE2\nspi_software_mosi_pin: PA1\n",
        )
        .unwrap_or_else(|e| panic!("{e}"));
        let sw = s.bus.software.unwrap_or_else(|| panic!("no software bus"));
        assert_eq!(
            (sw[0].pin.as_str(), sw[1].pin.as_str(), sw[2].pin.as_str()),
            ("PE2", "PA1", "PE5")
        );
        let s = sensor(
            SpiChip::Max31856,
            "sensor_pin: PE3\ntc_type: J\ntc_averaging_count: 4\n",
        )
        .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((s.tc_type, s.tc_averaging_count), (2, 4));
        // Options of another chip are unknown options.
        let e = sensor(SpiChip::Max6675, "sensor_pin: PE3\ntc_type: J\n").unwrap_err();
        assert!(e.contains("tc_type"), "{e}");
        assert!(sensor(SpiChip::Max6675, "sensor_pin: PE3\nspi_speed: 10\n").is_err());
    }

    proptest! {
        #[test]
        fn any_option_text_gives_a_value_or_an_error(text in "\\PC{0,12}") {
            let body = format!("sensor_pin: PE3\ntc_type: {text}\ntc_averaging_count: {text}\nspi_speed: {text}\n");
            let _ = sensor(SpiChip::Max31856, &body);
        }
    }
}
