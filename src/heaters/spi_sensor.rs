//! SPI temperature chips on the host: a chip's raw `thermocouple_result` value ↔ °C, the
//! range the MCU checks, the configuration bytes sent at start-up, and the names of its fault
//! bits.
//!
//! Conversions (the datasheets' formats):
//! - MAX6675: bits 14..3, 0.25 °C per count, unsigned.
//! - MAX31855: bits 31..18, 0.25 °C per count, 14-bit two's complement.
//! - MAX31856: bits 23..5, 2^-7 °C per count, 19-bit two's complement.
//! - MAX31865: bits 15..1 the RTD's resistance as a fraction of `rtd_reference_r` (2^15 full
//!   scale); `R / R0 = 1 + A·T + B·T²` (Callendar–Van Dusen above 0 °C) solved for T:
//!   `T = (−A + √(A² − 4B(1 − R/R0))) / 2B`.
//!
//! The range check is of raw values, so for the thermocouples (whose raw value grows with
//! the temperature only below the sign bit) the limits are clamped at 0 as Klipper does.

use links::dict::{DictError, Dictionary};
use links::mcu::{LinkError, McuLink};
use sysconfig::printer::{SpiChip, SpiSensorSection};

/// Invalid reads in a row after which the MCU shuts down (Klipper's).
pub const MAX_INVALID_COUNT: u8 = 3;

/// Callendar–Van Dusen A of platinum.
const CVD_A: f64 = 3.9083e-3;
/// Callendar–Van Dusen B of platinum.
const CVD_B: f64 = -5.775e-7;
/// MAX31865 full scale.
const MAX31865_ADC_MAX: f64 = 32768.0;
/// Platinum's melting point (°C): the highest temperature an RTD value stands for.
const PLATINUM_MELTS_C: f64 = 1768.3;

/// MAX31865 configuration: bias on, automatic conversion, fault status clear.
const MAX31865_CONFIG: u8 = 0x80 | 0x40 | 0x02;
/// MAX31865 configuration: 50 Hz filter.
const MAX31865_FILT50HZ: u8 = 0x01;
/// MAX31865 configuration: 3-wire RTD.
const MAX31865_3WIRE: u8 = 0x10;
/// MAX31856 CR0: automatic conversion.
const MAX31856_AUTOCONVERT: u8 = 0x80;
/// MAX31856 CR0: 50 Hz filter.
const MAX31856_FILT50HZ: u8 = 0x01;
/// MAX31856 MASK: report only over/under-voltage and open thermocouple.
const MAX31856_MASK: u8 = 0x02 | 0x01;
/// A register write: the register's address with bit 7 set.
const WRITE: u8 = 0x80;

/// One chip's conversion.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpiTemp {
    /// The chip.
    pub chip: SpiChip,
    /// MAX31865: ohms per count over `rtd_nominal_r`.
    rtd_scale: f64,
}

/// A two's complement field of `bits` bits as a signed number.
fn signed(v: u32, bits: u32) -> i64 {
    let v = i64::from(v & ((1 << bits) - 1));
    if v >= 1 << (bits - 1) {
        v - (1 << bits)
    } else {
        v
    }
}

impl SpiTemp {
    /// The conversion of `cfg`'s chip.
    pub fn new(cfg: &SpiSensorSection) -> SpiTemp {
        SpiTemp {
            chip: cfg.chip,
            rtd_scale: cfg.rtd_reference_r / MAX31865_ADC_MAX / cfg.rtd_nominal_r,
        }
    }

    /// °C of raw value `v`.
    pub fn temperature(&self, v: u32) -> f64 {
        match self.chip {
            SpiChip::Max6675 => 0.25 * ((v >> 3) & 0x1FFF) as f64,
            SpiChip::Max31855 => 0.25 * signed(v >> 18, 14) as f64,
            SpiChip::Max31856 => 0.007_812_5 * signed(v >> 5, 19) as f64,
            SpiChip::Max31865 => {
                let r = f64::from(v >> 1) * self.rtd_scale;
                let d = (CVD_A * CVD_A - 4.0 * CVD_B * (1.0 - r)).max(0.0).sqrt();
                (-CVD_A + d) / (2.0 * CVD_B)
            }
        }
    }

    /// The raw value of `temp` °C (clamped to what the chip reports; negative thermocouple
    /// temperatures to 0).
    pub fn value(&self, temp: f64) -> u32 {
        let counts = |per: f64, max: f64| (temp / per + 0.5).floor().clamp(0.0, max) as u32;
        match self.chip {
            SpiChip::Max6675 => counts(0.25, 8191.0) << 3,
            SpiChip::Max31855 => counts(0.25, 8191.0) << 18,
            SpiChip::Max31856 => counts(0.007_812_5, 262_143.0) << 5,
            SpiChip::Max31865 => {
                let t = temp.min(PLATINUM_MELTS_C);
                let r = 1.0 + CVD_A * t + CVD_B * t * t;
                let adc = (r / self.rtd_scale + 0.5)
                    .floor()
                    .clamp(0.0, MAX31865_ADC_MAX - 1.0) as u32;
                adc << 1
            }
        }
    }

    /// `query_thermocouple`'s `(min_value, max_value)` for `min_temp..=max_temp`.
    pub fn range(&self, min_temp: f64, max_temp: f64) -> (u32, u32) {
        let (a, b) = (self.value(min_temp), self.value(max_temp));
        (a.min(b), a.max(b))
    }

    /// The fault bits' meanings (each set bit of `fault`).
    pub fn fault_text(&self, fault: u8) -> String {
        let bits: &[(u8, &str)] = match self.chip {
            SpiChip::Max6675 => &[(0x02, "Device ID error"), (0x04, "Thermocouple Open Fault")],
            SpiChip::Max31855 => &[
                (0x01, "Open Circuit"),
                (0x02, "Short to GND"),
                (0x04, "Short to Vcc"),
            ],
            SpiChip::Max31856 => &[
                (0x80, "Cold Junction Range Fault"),
                (0x40, "Thermocouple Range Fault"),
                (0x20, "Cold Junction High Fault"),
                (0x10, "Cold Junction Low Fault"),
                (0x08, "Thermocouple High Fault"),
                (0x04, "Thermocouple Low Fault"),
                (0x02, "Over/Under Voltage Fault"),
                (0x01, "Thermocouple Open Fault"),
            ],
            SpiChip::Max31865 => &[
                (0x80, "RTD input is disconnected"),
                (0x40, "RTD input is shorted"),
                (0x20, "VREF- is greater than 0.85 * VBIAS, FORCE- open"),
                (0x10, "VREF- is less than 0.85 * VBIAS, FORCE- open"),
                (0x08, "VRTD- is less than 0.85 * VBIAS, FORCE- open"),
                (0x04, "Overvoltage or undervoltage fault"),
            ],
        };
        let mut parts: Vec<&str> = bits
            .iter()
            .filter(|(b, _)| fault & b != 0)
            .map(|&(_, t)| t)
            .collect();
        if parts.is_empty() {
            parts.push("Unspecified error");
        }
        format!("{}: {}", self.chip.name(), parts.join(", "))
    }
}

/// Why a chip's reports could not be started.
#[derive(Debug, thiserror::Error)]
pub enum SpiQueryError {
    /// `query_thermocouple` does not encode.
    #[error(transparent)]
    Dictionary(#[from] DictError),
    /// The link refused it.
    #[error(transparent)]
    Link(#[from] LinkError),
}

/// A chip's reports as the heater loop reads them.
#[derive(Debug, Clone)]
pub struct SpiReader {
    /// The reader's oid.
    pub oid: u8,
    conv: SpiTemp,
    last_serial: u64,
}

impl SpiReader {
    /// Starts reader `oid`'s reports (every `report_time` s of MCU time from clock `start`,
    /// checked by the MCU against `min_temp..=max_temp`).
    #[allow(clippy::too_many_arguments)]
    pub fn start(
        link: &McuLink,
        dict: &Dictionary,
        cfg: &SpiSensorSection,
        oid: u8,
        start: f64,
        freq: f64,
        report_time: f64,
        (min_temp, max_temp): (f64, f64),
    ) -> Result<SpiReader, SpiQueryError> {
        let conv = SpiTemp::new(cfg);
        let (lo, hi) = conv.range(min_temp, max_temp);
        let cmd = dict.encode(
            "query_thermocouple",
            &[
                i64::from(oid),
                (start as u64 & 0xFFFF_FFFF) as i64,
                (report_time * freq).round() as i64,
                i64::from(lo),
                i64::from(hi),
                i64::from(MAX_INVALID_COUNT),
            ],
        )?;
        link.send(cmd)?;
        Ok(SpiReader {
            oid,
            conv,
            last_serial: 0,
        })
    }

    /// The newest report not seen yet: `(next_clock, °C)`; a report with fault bits gives no
    /// temperature: its text goes to `fault` (Klipper logs it; the MCU shuts down after
    /// [`MAX_INVALID_COUNT`] in a row).
    pub fn poll(&mut self, link: &McuLink, fault: impl FnOnce(String)) -> Option<(u32, f64)> {
        let r = link.thermocouple_report(self.oid)?;
        if r.serial == self.last_serial {
            return None;
        }
        self.last_serial = r.serial;
        if r.fault != 0 {
            fault(self.conv.fault_text(r.fault));
            return None;
        }
        Some((r.next_clock, self.conv.temperature(r.value)))
    }
}

/// The bytes written to the chip at start-up (`spi_send`), if it needs any: the MAX31865's
/// configuration register; the MAX31856's CR0, CR1 and fault mask.
pub fn init_bytes(cfg: &SpiSensorSection) -> Option<Vec<u8>> {
    match cfg.chip {
        SpiChip::Max31865 => {
            let mut c = MAX31865_CONFIG;
            if cfg.rtd_use_50hz_filter {
                c |= MAX31865_FILT50HZ;
            }
            if cfg.rtd_num_of_wires == 3 {
                c |= MAX31865_3WIRE;
            }
            Some(vec![WRITE, c])
        }
        SpiChip::Max31856 => {
            let mut cr0 = MAX31856_AUTOCONVERT;
            if cfg.tc_use_50hz_filter {
                cr0 |= MAX31856_FILT50HZ;
            }
            // CR1: averaging (log2 of the count) in bits 6..4, the type in bits 3..0.
            let avg = match cfg.tc_averaging_count {
                2 => 0x10,
                4 => 0x20,
                8 => 0x30,
                16 => 0x40,
                _ => 0x00,
            };
            Some(vec![WRITE, cr0, avg | cfg.tc_type, MAX31856_MASK])
        }
        SpiChip::Max6675 | SpiChip::Max31855 => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use firmware::sim::spi_sensor::{SpiSensor, SpiSensorSpec};
    use sysconfig::printer::{PinRef, SpiBus};

    fn cfg(chip: SpiChip) -> SpiSensorSection {
        SpiSensorSection {
            chip,
            bus: SpiBus {
                cs_pin: PinRef {
                    mcu: "mcu".into(),
                    pin: "PA4".into(),
                    invert: false,
                    pullup: false,
                    pulldown: false,
                },
                speed: 4_000_000,
                bus: None,
                software: None,
            },
            rtd_nominal_r: 100.0,
            rtd_reference_r: 430.0,
            rtd_num_of_wires: 2,
            rtd_use_50hz_filter: false,
            tc_type: 3,
            tc_use_50hz_filter: false,
            tc_averaging_count: 1,
        }
    }

    /// The host reads back what the simulated chip (made from the datasheet) reports.
    #[test]
    fn the_simulated_chips_read_back_within_their_resolution() {
        let chips = [
            (
                SpiChip::Max6675,
                firmware::core::thermocouple::Chip::Max6675,
                0.25,
            ),
            (
                SpiChip::Max31855,
                firmware::core::thermocouple::Chip::Max31855,
                0.25,
            ),
            (
                SpiChip::Max31856,
                firmware::core::thermocouple::Chip::Max31856,
                0.01,
            ),
            (
                SpiChip::Max31865,
                firmware::core::thermocouple::Chip::Max31865,
                0.05,
            ),
        ];
        for (host, sim, tol) in chips {
            let conv = SpiTemp::new(&cfg(host));
            let mut chip = SpiSensor::new(SpiSensorSpec {
                cs_pin: 4,
                chip: sim,
                rtd: (100.0, 430.0),
            });
            let mut board = OneChip(&mut chip, 0.0);
            for t in [20.0, 25.0, 99.9, 210.0, 300.0] {
                board.1 = t;
                let (v, fault) = sim.read(&mut board, 4);
                assert_eq!(fault, 0, "{host:?}");
                let back = conv.temperature(v);
                assert!((back - t).abs() <= tol, "{host:?} {t} → {back}");
                // calc_adc's inverse agrees with the chip's own encoding.
                assert!((conv.temperature(conv.value(t)) - t).abs() <= tol, "{host:?} {t}");
            }
        }
    }

    struct OneChip<'a>(&'a mut SpiSensor, f64);
    impl firmware::core::Board for OneChip<'_> {
        fn step(&mut self, _: u8, _: bool, _: rt_core::WireClock) {}
        fn write(&mut self, _: &[u8]) {}
        fn spi_transfer(&mut self, _cs: u8, data: &mut [u8]) {
            self.0.transfer(data, self.1, false);
        }
    }

    #[test]
    fn ranges_faults_and_init() {
        let c = SpiTemp::new(&cfg(SpiChip::Max31855));
        let (lo, hi) = c.range(0.0, 250.0);
        assert_eq!((lo, hi), (0, 1000 << 18));
        assert_eq!(c.temperature(0x3FFF << 18), -0.25);
        assert_eq!(c.fault_text(0x01), "MAX31855: Open Circuit");
        assert_eq!(
            SpiTemp::new(&cfg(SpiChip::Max31865)).fault_text(0x01),
            "MAX31865: Unspecified error"
        );
        let mut m = cfg(SpiChip::Max31865);
        m.rtd_use_50hz_filter = true;
        assert_eq!(init_bytes(&m), Some(vec![0x80, 0xC3]));
        let mut t = cfg(SpiChip::Max31856);
        t.tc_averaging_count = 4;
        assert_eq!(init_bytes(&t), Some(vec![0x80, 0x80, 0x23, 0x03]));
        assert_eq!(init_bytes(&cfg(SpiChip::Max6675)), None);
    }
}
