//! SPI temperature chips read periodically (`config_thermocouple`, `query_thermocouple` →
//! `thermocouple_result`), as Klipper's MCU reads them.
//!
//! `query_thermocouple clock rest_ticks min_value max_value max_invalid_count`: from `clock`
//! on, every `rest_ticks`, read the chip over its SPI device and report the raw `value` and
//! the chip's `fault` bits with `next_clock` (the next read). A read with a fault, or a value
//! outside `[min_value, max_value]`, counts as invalid; `max_invalid_count` invalid reads in a
//! row shut the MCU down ("Thermocouple reader fault"). `rest_ticks = 0` stops reading.
//!
//! What one read clocks out and how the value and fault are taken from the answer (the chips'
//! datasheets; all big-endian):
//! - MAX31855: 4 bytes; fault = the low 3 bits (open, short to GND, short to VCC).
//! - MAX31856: register 0x0C (3 bytes of linearised temperature, 19 bits << 5), then the fault
//!   status register 0x0F.
//! - MAX31865: register 0x01 (RTD MSB, LSB; bit 0 the fault flag), then the fault status
//!   register 0x07 (its bits 7..2) with the flag as bit 0.
//! - MAX6675: 2 bytes; fault = bits 2 (open thermocouple) and 1 (device id, always 0).

use super::board::Board;
use rt_core::WireClock;

/// The chips, numbered as the `thermocouple_type` enumeration (Klipper's order).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Chip {
    /// Thermocouple to digital, 14-bit.
    Max31855,
    /// Thermocouple to digital, 19-bit, any type.
    Max31856,
    /// Platinum RTD to digital, 15-bit.
    Max31865,
    /// K thermocouple to digital, 12-bit.
    Max6675,
}

/// The `thermocouple_type` enumeration: (name, value).
pub const CHIP_NAMES: [(&str, u8); 4] = [("MAX31855", 0), ("MAX31856", 1), ("MAX31865", 2), ("MAX6675", 3)];

/// MAX31856 register holding the linearised temperature's high byte.
pub const MAX31856_LTCBH_REG: u8 = 0x0C;
/// MAX31856 fault status register.
pub const MAX31856_SR_REG: u8 = 0x0F;
/// MAX31865 register holding the RTD value's high byte.
pub const MAX31865_RTDMSB_REG: u8 = 0x01;
/// MAX31865 fault status register.
pub const MAX31865_FAULTSTAT_REG: u8 = 0x07;

impl Chip {
    /// The chip numbered `n`, if any.
    pub fn from_number(n: i64) -> Option<Chip> {
        match n {
            0 => Some(Chip::Max31855),
            1 => Some(Chip::Max31856),
            2 => Some(Chip::Max31865),
            3 => Some(Chip::Max6675),
            _ => None,
        }
    }

    /// One read over the SPI device with chip select `cs_pin`: `(value, fault)`.
    pub fn read<B: Board>(self, board: &mut B, cs_pin: u8) -> (u32, u8) {
        match self {
            Chip::Max31855 => {
                let mut m = [0u8; 4];
                board.spi_transfer(cs_pin, &mut m);
                let v = u32::from_be_bytes(m);
                (v, (v & 0x07) as u8)
            }
            Chip::Max31856 => {
                let mut m = [MAX31856_LTCBH_REG, 0, 0, 0];
                board.spi_transfer(cs_pin, &mut m);
                let v = u32::from_be_bytes(m) & 0x00ff_ffff;
                let mut f = [MAX31856_SR_REG, 0];
                board.spi_transfer(cs_pin, &mut f);
                (v, f[1])
            }
            Chip::Max31865 => {
                let mut m = [MAX31865_RTDMSB_REG, 0, 0];
                board.spi_transfer(cs_pin, &mut m);
                let v = u32::from(u16::from_be_bytes([m[1], m[2]]));
                let mut f = [MAX31865_FAULTSTAT_REG, 0];
                board.spi_transfer(cs_pin, &mut f);
                (v, (f[1] & !0x03) | (v & 1) as u8)
            }
            Chip::Max6675 => {
                let mut m = [0u8; 2];
                board.spi_transfer(cs_pin, &mut m);
                let v = u16::from_be_bytes(m);
                (u32::from(v), (v & 0x06) as u8)
            }
        }
    }
}

/// `query_thermocouple` parameters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ThermocoupleQuery {
    /// The first read.
    pub clock: WireClock,
    /// Ticks between reads (0: stop).
    pub rest_ticks: u32,
    /// Smallest valid value.
    pub min_value: u32,
    /// Largest valid value.
    pub max_value: u32,
    /// Invalid reads in a row that shut down.
    pub max_invalid_count: u8,
}

/// What a read produced.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ThermocoupleEvent {
    /// Report `value` and `fault`; read again at `next_clock`.
    Report {
        /// The next read.
        next_clock: WireClock,
        /// The raw value.
        value: u32,
        /// The chip's fault bits.
        fault: u8,
    },
    /// Reported (as in `Report`), then too many invalid reads in a row: shut down.
    Fault {
        /// The next read (reported).
        next_clock: WireClock,
        /// The raw value.
        value: u32,
        /// The chip's fault bits.
        fault: u8,
    },
    /// Not reading.
    Idle,
}

/// One SPI temperature chip.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Thermocouple {
    /// The oid of its SPI device.
    pub spi_oid: u8,
    /// The chip.
    pub chip: Chip,
    q: ThermocoupleQuery,
    next: WireClock,
    invalid: u8,
}

impl Thermocouple {
    /// `config_thermocouple`.
    pub const fn new(spi_oid: u8, chip: Chip) -> Thermocouple {
        Thermocouple {
            spi_oid,
            chip,
            q: ThermocoupleQuery {
                clock: WireClock(0),
                rest_ticks: 0,
                min_value: 0,
                max_value: 0,
                max_invalid_count: 0,
            },
            next: WireClock(0),
            invalid: 0,
        }
    }

    /// `query_thermocouple`: the clock to arm at, or `None` if reading stopped.
    pub fn query(&mut self, q: ThermocoupleQuery) -> Option<WireClock> {
        self.q = q;
        self.next = q.clock;
        self.invalid = 0;
        (q.rest_ticks > 0).then_some(q.clock)
    }

    /// The timer fired and the chip read `(value, fault)`.
    pub fn event(&mut self, value: u32, fault: u8) -> ThermocoupleEvent {
        if self.q.rest_ticks == 0 {
            return ThermocoupleEvent::Idle;
        }
        self.next = self.next.add(self.q.rest_ticks);
        let next_clock = self.next;
        if fault != 0 || value < self.q.min_value || value > self.q.max_value {
            self.invalid = self.invalid.saturating_add(1);
            if self.invalid >= self.q.max_invalid_count {
                self.q.rest_ticks = 0;
                return ThermocoupleEvent::Fault {
                    next_clock,
                    value,
                    fault,
                };
            }
        } else {
            self.invalid = 0;
        }
        ThermocoupleEvent::Report {
            next_clock,
            value,
            fault,
        }
    }

    /// Shutdown: stop reading.
    pub fn halt(&mut self) {
        self.q.rest_ticks = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn query(max_invalid_count: u8) -> ThermocoupleQuery {
        ThermocoupleQuery {
            clock: WireClock(1000),
            rest_ticks: 300,
            min_value: 10,
            max_value: 100,
            max_invalid_count,
        }
    }

    #[test]
    fn reports_and_counts_invalid_reads_in_a_row() {
        let mut t = Thermocouple::new(1, Chip::Max6675);
        assert_eq!(t.query(query(3)), Some(WireClock(1000)));
        let report = |next: u32, value, fault| ThermocoupleEvent::Report {
            next_clock: WireClock(next),
            value,
            fault,
        };
        assert_eq!(t.event(50, 0), report(1300, 50, 0));
        assert_eq!(t.event(50, 4), report(1600, 50, 4));
        assert_eq!(t.event(500, 0), report(1900, 500, 0));
        // A good read resets the count.
        assert_eq!(t.event(50, 0), report(2200, 50, 0));
        assert_eq!(t.event(5, 0), report(2500, 5, 0));
        assert_eq!(t.event(50, 1), report(2800, 50, 1));
        assert_eq!(
            t.event(50, 2),
            ThermocoupleEvent::Fault {
                next_clock: WireClock(3100),
                value: 50,
                fault: 2
            }
        );
        assert_eq!(t.event(50, 0), ThermocoupleEvent::Idle);
    }

    #[test]
    fn zero_rest_ticks_stops() {
        let mut t = Thermocouple::new(1, Chip::Max31855);
        let q = ThermocoupleQuery {
            rest_ticks: 0,
            ..query(3)
        };
        assert_eq!(t.query(q), None);
        assert_eq!(t.event(50, 0), ThermocoupleEvent::Idle);
    }

    /// A board whose SPI device answers fixed bytes per first byte sent (the register).
    struct Regs;
    impl Board for Regs {
        fn step(&mut self, _: u8, _: bool, _: WireClock) {}
        fn write(&mut self, _: &[u8]) {}
        fn spi_transfer(&mut self, _cs: u8, data: &mut [u8]) {
            let answer: &[u8] = match data[0] {
                MAX31865_RTDMSB_REG => &[0xff, 0x12, 0x35],
                MAX31865_FAULTSTAT_REG => &[0xff, 0x87],
                MAX31856_LTCBH_REG => &[0xff, 0x01, 0x02, 0x03],
                _ => &[0xab, 0xcd, 0xef, 0x07],
            };
            let n = data.len().min(answer.len());
            data[..n].copy_from_slice(&answer[..n]);
        }
    }

    #[test]
    fn chips_take_value_and_fault_from_their_registers() {
        assert_eq!(Chip::Max31865.read(&mut Regs, 0), (0x1235, 0x85));
        assert_eq!(Chip::Max31855.read(&mut Regs, 0), (0xabcd_ef07, 7));
        assert_eq!(Chip::Max6675.read(&mut Regs, 0), (0xabcd, 0x04));
        // MAX31856: the temperature bytes, then SR (whose answer's byte 1 is 0xcd here).
        assert_eq!(Chip::Max31856.read(&mut Regs, 0), (0x0001_0203, 0xcd));
        assert_eq!(Chip::from_number(3), Some(Chip::Max6675));
        assert_eq!(Chip::from_number(4), None);
    }
}
