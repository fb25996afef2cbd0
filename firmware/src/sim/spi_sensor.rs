//! Simulated SPI temperature chips (`--spi-sensor CS_PIN=CHIP[,RTD_NOMINAL,RTD_REFERENCE]`):
//! each answers a transaction on its chip select with the temperature it measures (a heater's
//! when a `--heater` names CS_PIN as its sensor, else ambient) in its datasheet's format.
//!
//! - MAX6675: 16 bits, D14..D3 the temperature in 0.25 °C, D2 set when the thermocouple is open.
//! - MAX31855: 32 bits, D31..D18 the signed temperature in 0.25 °C, D16 any fault, D15..D4 the
//!   cold junction in 0.0625 °C, D0 open circuit.
//! - MAX31856: registers; 0x0C..0x0E the signed temperature in 2^-7 °C shifted left 5, 0x0F
//!   the fault status (bit 0 open thermocouple). A transaction's first byte is the register
//!   (bit 7 set: a write of the following bytes), the next bytes read or write from it on.
//! - MAX31865: registers; 0x01..0x02 the RTD's resistance as a 15-bit fraction of the
//!   reference resistor shifted left 1 (bit 0 any fault), 0x07 the fault status (bit 7: RTD
//!   open, high threshold). The resistance is Callendar–Van Dusen's
//!   `R = R0 (1 + A·T + B·T²)` with A = 3.9083e-3, B = −5.775e-7 (T ≥ 0 °C).
//!
//! An open sensor (a `--heater-fault HEATER_PIN=open@S` of its heater) sets the chip's open
//! fault bit.

use crate::core::thermocouple::{Chip, CHIP_NAMES, MAX31856_LTCBH_REG, MAX31856_SR_REG};
use crate::core::thermocouple::{MAX31865_FAULTSTAT_REG, MAX31865_RTDMSB_REG};

/// Callendar–Van Dusen A of platinum (IEC 60751).
pub const CVD_A: f64 = 3.9083e-3;
/// Callendar–Van Dusen B of platinum (IEC 60751).
pub const CVD_B: f64 = -5.775e-7;

/// `--spi-sensor`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpiSensorSpec {
    /// Chip select.
    pub cs_pin: u8,
    /// The chip.
    pub chip: Chip,
    /// MAX31865: the RTD's resistance at 0 °C and the reference resistor (Ω).
    pub rtd: (f64, f64),
}

impl SpiSensorSpec {
    /// Parses `CS_PIN=CHIP[,RTD_NOMINAL,RTD_REFERENCE]` (defaults 100 Ω and 430 Ω).
    pub fn parse(s: &str) -> Result<SpiSensorSpec, String> {
        let (pin, rest) = s
            .split_once('=')
            .ok_or("expected CS_PIN=CHIP[,RTD_NOMINAL,RTD_REFERENCE]")?;
        let mut parts = rest.split(',');
        let name = parts.next().unwrap_or_default().trim();
        let chip = CHIP_NAMES
            .iter()
            .find(|(n, _)| n.eq_ignore_ascii_case(name))
            .and_then(|&(_, v)| Chip::from_number(i64::from(v)))
            .ok_or_else(|| format!("`{name}` is not MAX6675, MAX31855, MAX31856 or MAX31865"))?;
        let mut num = |what: &str, default: f64| -> Result<f64, String> {
            match parts.next() {
                None => Ok(default),
                Some(v) => match v.trim().parse::<f64>() {
                    Ok(x) if x > 0.0 && x.is_finite() => Ok(x),
                    _ => Err(format!("{what} `{v}` is not a positive number")),
                },
            }
        };
        let rtd = (num("RTD_NOMINAL", 100.0)?, num("RTD_REFERENCE", 430.0)?);
        Ok(SpiSensorSpec {
            cs_pin: super::cli::parse_pin(pin)?,
            chip,
            rtd,
        })
    }
}

/// One simulated chip with its register file.
#[derive(Debug, Clone, PartialEq)]
pub struct SpiSensor {
    /// What it is.
    pub spec: SpiSensorSpec,
    regs: [u8; 16],
}

impl SpiSensor {
    /// A chip with cleared registers.
    pub fn new(spec: SpiSensorSpec) -> SpiSensor {
        SpiSensor { spec, regs: [0; 16] }
    }

    /// The value of the configuration register 0 (written by the host at start-up).
    pub fn config_register(&self) -> u8 {
        self.regs[0]
    }

    /// One transaction: `data` out, replaced by what the chip shifts back, measuring `temp_c`
    /// (`open`: the sensor is disconnected).
    pub fn transfer(&mut self, data: &mut [u8], temp_c: f64, open: bool) {
        match self.spec.chip {
            Chip::Max6675 => {
                let raw = (temp_c / 0.25).round().clamp(0.0, 4095.0) as u16;
                let word = (raw << 3) | if open { 0x04 } else { 0 };
                shift_out(data, &word.to_be_bytes());
            }
            Chip::Max31855 => {
                let raw = ((temp_c / 0.25).round().clamp(-8192.0, 8191.0) as i32 as u32) & 0x3FFF;
                let cold = ((25.0f64 / 0.0625).round() as u32) & 0xFFF;
                let fault = if open { 0x0001_0001 } else { 0 };
                let word = (raw << 18) | (cold << 4) | fault;
                shift_out(data, &word.to_be_bytes());
            }
            Chip::Max31856 => {
                let raw = ((temp_c / 0.0078125).round().clamp(-262_144.0, 262_143.0) as i32 as u32) & 0x7FFFF;
                let b = (raw << 5).to_be_bytes();
                let at = usize::from(MAX31856_LTCBH_REG);
                self.regs[at..at + 3].copy_from_slice(&b[1..4]);
                self.regs[usize::from(MAX31856_SR_REG)] = u8::from(open);
                self.registers(data);
            }
            Chip::Max31865 => {
                let (nominal, reference) = self.spec.rtd;
                let t = temp_c.max(0.0);
                let r = nominal * (1.0 + CVD_A * t + CVD_B * t * t);
                let adc = if open {
                    0x7FFF
                } else {
                    (r / reference * 32768.0).round().clamp(0.0, 32767.0) as u16
                };
                let b = ((adc << 1) | u16::from(open)).to_be_bytes();
                let at = usize::from(MAX31865_RTDMSB_REG);
                self.regs[at..at + 2].copy_from_slice(&b);
                self.regs[usize::from(MAX31865_FAULTSTAT_REG)] = if open { 0x80 } else { 0 };
                self.registers(data);
            }
        }
    }

    /// A register transaction: byte 0 the address (bit 7: write), then data from it on.
    fn registers(&mut self, data: &mut [u8]) {
        let Some((&mut first, rest)) = data.split_first_mut() else {
            return;
        };
        let addr = usize::from(first & 0x0F);
        let write = first & 0x80 != 0;
        for (i, b) in rest.iter_mut().enumerate() {
            let r = (addr + i) & 0x0F;
            if write {
                self.regs[r] = *b;
            } else {
                *b = self.regs[r];
            }
        }
        data[0] = 0xFF;
    }
}

/// A shift register's answer: `word`'s bytes, then ones (MISO idle high).
fn shift_out(data: &mut [u8], word: &[u8]) {
    for (i, b) in data.iter_mut().enumerate() {
        *b = word.get(i).copied().unwrap_or(0xFF);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::thermocouple::Chip;

    fn chip(c: Chip) -> SpiSensor {
        SpiSensor::new(SpiSensorSpec {
            cs_pin: 4,
            chip: c,
            rtd: (100.0, 430.0),
        })
    }

    #[test]
    fn formats_follow_the_datasheets() {
        let mut m = [0u8; 2];
        chip(Chip::Max6675).transfer(&mut m, 200.0, false);
        assert_eq!(u16::from_be_bytes(m), 800 << 3);
        chip(Chip::Max6675).transfer(&mut m, 200.0, true);
        assert_eq!(u16::from_be_bytes(m) & 0x04, 0x04);
        let mut m = [0u8; 4];
        chip(Chip::Max31855).transfer(&mut m, -10.0, false);
        let w = u32::from_be_bytes(m);
        assert_eq!(w >> 18, 0x3FFF & (-40i32 as u32));
        assert_eq!(w & 7, 0);
        // MAX31856: 100 °C = 12800 × 2^-7.
        let mut c = chip(Chip::Max31856);
        let mut m = [MAX31856_LTCBH_REG, 0, 0, 0];
        c.transfer(&mut m, 100.0, false);
        assert_eq!(u32::from_be_bytes(m) & 0xFF_FFFF, 12800 << 5);
        let mut w = [0x80, 0x81];
        c.transfer(&mut w, 100.0, false);
        assert_eq!(c.config_register(), 0x81);
        // MAX31865 at 0 °C reads R0 / Rref.
        let mut c = chip(Chip::Max31865);
        let mut m = [MAX31865_RTDMSB_REG, 0, 0];
        c.transfer(&mut m, 0.0, false);
        let v = u16::from_be_bytes([m[1], m[2]]) >> 1;
        assert_eq!(v, (100.0f64 / 430.0 * 32768.0).round() as u16);
    }

    #[test]
    fn specs_parse() {
        let s = SpiSensorSpec::parse("PB2=max31865,100,400").unwrap();
        assert_eq!((s.chip, s.rtd), (Chip::Max31865, (100.0, 400.0)));
        assert_eq!(SpiSensorSpec::parse("PE3=MAX6675").unwrap().chip, Chip::Max6675);
        for bad in ["PE3", "PE3=MAX1", "PE3=MAX31865,-1", "nopin=MAX6675"] {
            assert!(SpiSensorSpec::parse(bad).is_err(), "{bad}");
        }
    }
}
