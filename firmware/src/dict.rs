//! The data dictionary: the Klipper JSON built from the core's tables, zlib-compressed.
//!
//! `commands` and `responses` map each format string of [`MESSAGES`] to its id (its position);
//! `enumerations` holds `pin` (the [`Chip`]'s ports as ranges, an STM32's `"PA0": [0, 16]`, …;
//! the simulator's every board family's names from [`links::pinmap`], `"PA0": [0, 8]`,
//! `"P1.0": [32, 32]`, …), the simulator's `spi_bus` (the hardware SPI bus names of every
//! board family, [`SIM_SPI_BUSES`]) and `static_string_id` (every shutdown reason → its id); `config`
//! holds `CLOCK_FREQ`, `MCU` plus [`CONSTANTS`]. The host reads everything from here and never
//! hard-codes ids beyond 0 and 1.

use crate::core::commands::{Kind, MESSAGES};
use crate::core::constants::{Chip, ConstValue, ADC_TEMPERATURE_PIN, CONSTANTS, SHUTDOWN_REASONS, SIM_CHIP};
use flate2::write::ZlibEncoder;
use flate2::Compression;
use serde_json::{json, Map, Value};
use std::io::Write;

/// The simulator's hardware SPI buses: the names the board families' firmware gives them
/// (STM32 `spi1`, `spi2a`, `spi2_PB14_PB15_PB13`; SAM `spi0`, `usart0`; LPC176x `ssp0`; AVR
/// `spi`; RP2040 `spi0a`; Linux `spidev0.0`), each `(first name, count)`: a count above 1 is a
/// run whose trailing number counts up, as in the `pin` enumeration. Numbered in order from 0;
/// the simulated chips answer on any of them, so a config's `spi_bus` only has to name one.
pub const SIM_SPI_BUSES: &[(&str, u32)] = &[
    ("spi1", 1),
    ("spi0", 1),
    ("spi2", 5),
    ("spi1a", 1),
    ("spi1b", 1),
    ("spi1c", 1),
    ("spi2a", 1),
    ("spi2b", 1),
    ("spi3a", 1),
    ("spi5a", 1),
    ("spi0a", 1),
    ("spi0b", 1),
    ("spi0c", 1),
    ("spi0d", 1),
    ("spi", 1),
    ("ssp0", 2),
    ("usart0", 3),
    ("spi1_PA6_PA7_PA5", 1),
    ("spi1_PB4_PB5_PB3", 1),
    ("spi2_PB14_PB15_PB13", 1),
    ("spi2_PC2_PC3_PB10", 1),
    ("spi2_PB2_PB11_PB10", 1),
    ("spi2_PA10_PA11_PF1", 1),
    ("spi2_PB6_PB7_PB8", 1),
    ("spi2_PI2_PI3_PI1", 1),
    ("spi3_PB4_PB5_PB3", 1),
    ("spi3_PC11_PC12_PC10", 1),
    ("spi4_PE13_PE14_PE12", 1),
    ("spi6_PG12_PG14_PG13", 1),
    ("spidev0.0", 16),
    ("spidev1.0", 16),
    ("spidev2.0", 16),
];

/// The simulator's dictionary as JSON, for an MCU clocked at `clock_freq` Hz.
pub fn dictionary_json(clock_freq: u32) -> Value {
    dictionary_json_for(&SIM_CHIP, clock_freq)
}

/// The dictionary of a target on `chip`, clocked at `clock_freq` Hz, as JSON.
pub fn dictionary_json_for(chip: &Chip, clock_freq: u32) -> Value {
    let mut commands = Map::new();
    let mut responses = Map::new();
    for (id, m) in MESSAGES.iter().enumerate() {
        let map = match m.kind {
            Kind::Command { .. } => &mut commands,
            Kind::Response => &mut responses,
        };
        map.insert(m.format.to_owned(), json!(id));
    }
    let mut pins = Map::new();
    let mut enumerations = Map::new();
    if chip.ports.is_empty() {
        let mut buses = Map::new();
        let mut next = 0u32;
        for &(first, count) in SIM_SPI_BUSES {
            let value = if count > 1 {
                json!([next, count])
            } else {
                json!(next)
            };
            buses.insert(first.to_owned(), value);
            next += count;
        }
        enumerations.insert("spi_bus".into(), Value::Object(buses));
        for run in links::pinmap::pin_runs() {
            pins.insert(run.first.to_string(), json!([run.value, run.count]));
        }
        pins.insert("ADC_TEMPERATURE".into(), json!(ADC_TEMPERATURE_PIN));
    }
    for (i, port) in chip.ports.iter().enumerate() {
        let first = i as u32 * chip.pins_per_port as u32;
        pins.insert(format!("P{}0", *port as char), json!([first, chip.pins_per_port]));
    }
    let reasons: Map<String, Value> = SHUTDOWN_REASONS
        .iter()
        .enumerate()
        .map(|(id, r)| ((*r).to_owned(), json!(id)))
        .collect();
    let chips: Map<String, Value> = crate::core::thermocouple::CHIP_NAMES
        .iter()
        .map(|(n, v)| ((*n).to_owned(), json!(v)))
        .collect();
    enumerations.insert("pin".into(), Value::Object(pins));
    enumerations.insert("static_string_id".into(), Value::Object(reasons));
    enumerations.insert("thermocouple_type".into(), Value::Object(chips));
    let mut config = Map::new();
    config.insert("CLOCK_FREQ".into(), json!(clock_freq));
    config.insert("MCU".into(), json!(chip.mcu));
    for (name, value) in CONSTANTS {
        let v = match *value {
            ConstValue::Int(i) => json!(i),
            ConstValue::Str(s) => json!(s),
        };
        config.insert((*name).to_owned(), v);
    }
    json!({
        "app": "Cadence",
        "license": "MIT OR Apache-2.0",
        "version": concat!("cadence-", env!("CARGO_PKG_VERSION")),
        "build_versions": "rustc",
        "commands": commands,
        "responses": responses,
        "output": {},
        "enumerations": enumerations,
        "config": config,
    })
}

/// The simulator's zlib-compressed dictionary JSON, as served through `identify`.
pub fn dictionary_bytes(clock_freq: u32) -> Vec<u8> {
    dictionary_bytes_for(&SIM_CHIP, clock_freq)
}

/// The zlib-compressed dictionary JSON of a target on `chip` clocked at `clock_freq` Hz.
pub fn dictionary_bytes_for(chip: &Chip, clock_freq: u32) -> Vec<u8> {
    let json = dictionary_json_for(chip, clock_freq).to_string();
    let mut enc = ZlibEncoder::new(Vec::new(), Compression::best());
    // Writing into a Vec cannot fail; an empty dictionary would make the host's identify fail
    // loudly rather than this process panic.
    if enc.write_all(json.as_bytes()).is_err() {
        return Vec::new();
    }
    enc.finish().unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;
    use flate2::read::ZlibDecoder;
    use std::io::Read;

    #[test]
    fn the_simulators_spi_buses_are_numbered_in_order_from_0() {
        let v = dictionary_json(50_000_000);
        let buses = v["enumerations"]["spi_bus"].as_object().unwrap();
        assert_eq!(buses["spi1"], 0);
        assert_eq!(buses["spi0"], 1);
        assert_eq!(buses["spi2"], json!([2, 5]));
        assert_eq!(buses["usart0"], json!([21, 3]));
        assert_eq!(buses["spi6_PG12_PG14_PG13"], 35);
        assert_eq!(buses["spidev2.0"], json!([68, 16]));
    }

    #[test]
    fn compressed_round_trip_and_contents() {
        let bytes = dictionary_bytes(50_000_000);
        let mut text = String::new();
        ZlibDecoder::new(&bytes[..]).read_to_string(&mut text).unwrap();
        let v: Value = serde_json::from_str(&text).unwrap();
        assert_eq!(v, dictionary_json(50_000_000));
        assert_eq!(v["commands"]["identify offset=%u count=%c"], 1);
        assert_eq!(v["responses"]["identify_response offset=%u data=%.*s"], 0);
        assert_eq!(v["config"]["CLOCK_FREQ"], 50_000_000);
        assert_eq!(v["config"]["MCU"], "linux-sim");
        assert_eq!(v["config"]["RECEIVE_WINDOW"], 192);
        assert_eq!(v["config"]["STATS_SUMSQ_BASE"], 256);
        assert_eq!(v["config"]["SERIAL_BAUD"], 250_000);
        assert_eq!(v["config"]["ADC_MAX"], 4095);
        assert_eq!(v["config"]["PWM_MAX"], 255);
        let pins = v["enumerations"]["pin"].as_object().unwrap();
        assert_eq!(pins.len(), links::pinmap::pin_runs().count() + 1);
        assert_eq!(pins["ADC_TEMPERATURE"], json!(ADC_TEMPERATURE_PIN));
        assert_eq!(pins["PA0"], json!([0, 8]));
        assert_eq!(pins["PC8"], json!([112, 8]));
        assert_eq!(pins["P1.0"], json!([32, 32]));
        assert_eq!(pins["gpio0"], json!([0, 64]));
        assert_eq!(pins["PB0"], json!([8, 8]));
        assert_eq!(pins["PL0"], json!([88, 8]));
        assert_eq!(v["enumerations"]["static_string_id"]["Timer too close"], 1);
        let n = v["commands"].as_object().unwrap().len() + v["responses"].as_object().unwrap().len();
        assert_eq!(n, MESSAGES.len());
    }

    #[test]
    fn a_chip_names_its_own_pins_and_mcu() {
        let chip = Chip {
            mcu: "stm32f405",
            ports: b"ABCDEFGHI",
            pins_per_port: 16,
        };
        let v = dictionary_json_for(&chip, 4_000_000);
        assert_eq!(v["config"]["MCU"], "stm32f405");
        assert_eq!(v["config"]["CLOCK_FREQ"], 4_000_000);
        let pins = v["enumerations"]["pin"].as_object().unwrap();
        assert_eq!(pins.len(), 9);
        assert_eq!(pins["PB0"], json!([16, 16]));
        assert_eq!(pins["PI0"], json!([128, 16]));
        // Same commands and responses as the simulator: one table.
        let sim = dictionary_json(4_000_000);
        assert_eq!(v["commands"], sim["commands"]);
        assert_eq!(v["responses"], sim["responses"]);
    }
}
