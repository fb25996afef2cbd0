//! A simulated TMC stepper driver: its register file, reached over the MCU's TMC UART
//! (TMC2208/2209, addressed, replies framed with CRC) or SPI (TMC2130/2240/5160, pipelined 40-bit
//! datagrams), and its DIAG output.
//!
//! Registers: every write is kept (a UART write also counts IFCNT up, modulo 256); reads return
//! what was written, except IFCNT (the count), IOIN (the model's version in bits 24..31),
//! GSTAT (`reset` set at power-on, cleared by writing 1) and DRV_STATUS (`cs_actual` = the
//! written IRUN). A request with a wrong sync nibble, address or CRC is ignored, as the chip
//! does.
//!
//! A UART behind an analog mux (a Duet's `select_pins`) reaches the driver only while the
//! MCU's select pins are at the driver's levels (the board checks that).
//!
//! DIAG (stallGuard): the motor stalls when its carriage reaches the end of travel (`COORD` at
//! or beyond `END_MM`, the `min` or `max` end). The stall is reported only when the registers
//! route it: TMC2209 `SGTHRS` > 0 and `TCOOLTHRS` > 0 in stealthChop (`en_spreadcycle` 0);
//! TMC2130/2240/5160 the pin's GCONF `diag0_stall`/`diag1_stall` set, `TCOOLTHRS` > 0, in
//! spreadCycle (`en_pwm_mode` 0), or for the TMC2240 also in stealthChop with `SG4_THRS` > 0. The TMC2209's DIAG is active high; the SPI drivers' are open
//! drain, active low, unless GCONF's push-pull bit for that pin is set.

use super::world::Coord;
use links::proto::tmc::{self as wire, Request};

/// A driver model, as `--tmc` names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Model {
    Tmc2130,
    Tmc2208,
    Tmc2209,
    Tmc2240,
    Tmc2660,
    Tmc5160,
}

impl Model {
    /// The model named `name` (`tmc2209`).
    pub fn parse(name: &str) -> Option<Model> {
        match name {
            "tmc2130" => Some(Model::Tmc2130),
            "tmc2208" => Some(Model::Tmc2208),
            "tmc2209" => Some(Model::Tmc2209),
            "tmc2240" => Some(Model::Tmc2240),
            "tmc2660" => Some(Model::Tmc2660),
            "tmc5160" => Some(Model::Tmc5160),
            _ => None,
        }
    }

    fn is_uart(self) -> bool {
        matches!(self, Model::Tmc2208 | Model::Tmc2209)
    }

    /// IOIN version field.
    fn version(self) -> u32 {
        match self {
            Model::Tmc2130 => 0x11,
            Model::Tmc2208 | Model::Tmc2209 => 0x21,
            Model::Tmc2240 => 0x40,
            Model::Tmc2660 => 0,
            Model::Tmc5160 => 0x30,
        }
    }
}

/// Register addresses the simulation gives meaning to.
mod reg {
    pub const GCONF: u8 = 0x00;
    pub const GSTAT: u8 = 0x01;
    pub const IFCNT: u8 = 0x02;
    pub const IHOLD_IRUN: u8 = 0x10;
    pub const TCOOLTHRS: u8 = 0x14;
    pub const SGTHRS: u8 = 0x40;
    pub const SG4_THRS: u8 = 0x74;
    pub const DRV_STATUS: u8 = 0x6f;
}

/// IOIN's address per model.
fn ioin(model: Model) -> u8 {
    if model.is_uart() {
        0x06
    } else {
        0x04
    }
}

/// Where DIAG is wired and when the motor stalls.
#[derive(Debug, Clone, PartialEq)]
pub struct DiagSpec {
    /// The MCU input DIAG drives.
    pub pin: u8,
    /// The carriage coordinate the motor moves.
    pub coord: Coord,
    /// The end of travel (mm).
    pub end_mm: f64,
    /// The end is at the low side (`min`).
    pub at_min: bool,
    /// DIAG0 (SPI drivers; DIAG1 otherwise).
    pub diag0: bool,
}

/// `--tmc`: one driver.
#[derive(Debug, Clone, PartialEq)]
pub struct TmcSpec {
    pub model: Model,
    /// UART receive pin, or SPI chip select.
    pub bus_pin: u8,
    /// UART address; on SPI the position in a daisy chain (1..; 0 alone on its chip select).
    pub address: u8,
    pub diag: Option<DiagSpec>,
    /// UART behind an analog mux (Klipper's `select_pins`): the driver hears the line only
    /// while each of these pins is at its level.
    pub select: Vec<(u8, bool)>,
}

/// One driver's state.
#[derive(Debug, Clone)]
pub struct TmcDriver {
    pub spec: TmcSpec,
    regs: [u32; 128],
    ifcnt: u8,
    /// SPI: the value the next datagram's answer carries.
    spi_next: u32,
    /// Register writes received (for tests and diagnostics).
    pub writes: u32,
}

impl TmcDriver {
    /// A powered-up driver (GSTAT `reset` set, every other register 0).
    pub fn new(spec: TmcSpec) -> TmcDriver {
        let mut regs = [0u32; 128];
        regs[reg::GSTAT as usize] = 1;
        TmcDriver {
            spec,
            regs,
            ifcnt: 0,
            spi_next: 0,
            writes: 0,
        }
    }

    /// The value a read of `addr` returns.
    pub fn read(&self, addr: u8) -> u32 {
        let stored = self.regs.get(addr as usize).copied().unwrap_or(0);
        match addr {
            reg::IFCNT if self.spec.model.is_uart() => u32::from(self.ifcnt),
            a if a == ioin(self.spec.model) => (self.spec.model.version() << 24) | (stored & 0x00ff_ffff),
            reg::DRV_STATUS => {
                let irun = (self.regs[reg::IHOLD_IRUN as usize] >> 8) & 0x1f;
                irun << 16
            }
            _ => stored,
        }
    }

    fn write(&mut self, addr: u8, value: u32) {
        self.writes += 1;
        let Some(slot) = self.regs.get_mut(addr as usize) else {
            return;
        };
        if addr == reg::GSTAT {
            *slot &= !value;
        } else {
            *slot = value;
        }
    }

    /// A UART request on the driver's line; the reply's line bytes when it answers.
    pub fn uart(&mut self, line: &[u8]) -> Option<[u8; wire::UART_WRITE_LINE_LEN]> {
        match wire::decode_request(line)? {
            Request::Write { addr, reg, value } if addr == self.spec.address => {
                self.write(reg, value);
                self.ifcnt = self.ifcnt.wrapping_add(1);
                None
            }
            Request::Read { addr, reg } if addr == self.spec.address => {
                Some(wire::encode_reply(reg, self.read(reg)))
            }
            _ => None,
        }
    }

    /// One SPI transaction: each 5-byte datagram is answered with the status byte and the
    /// previous access's value (a TMC2660: see [`TmcDriver::spi_2660`]).
    pub fn spi(&mut self, data: &mut [u8]) {
        if self.spec.model == Model::Tmc2660 {
            return self.spi_2660(data);
        }
        for d in data.chunks_mut(5) {
            let [addr, a, b, c, e] = *d else {
                d.fill(0);
                continue;
            };
            let status = (self.regs[reg::GSTAT as usize] & 1) as u8;
            let reply = self.spi_next.to_be_bytes();
            let reg = addr & !wire::WRITE_BIT;
            if addr & wire::WRITE_BIT != 0 {
                let v = u32::from_be_bytes([a, b, c, e]);
                self.write(reg, v);
                self.spi_next = v;
            } else {
                self.spi_next = self.read(reg);
            }
            d.copy_from_slice(&[status, reply[0], reply[1], reply[2], reply[3]]);
        }
    }

    /// A TMC2660 transaction: the last 20 bits clocked in are the datagram (selector in bits
    /// 19..17, DRVCTRL when bit 19 is 0), kept under its selector `0x0`, `0x8`, `0xa`, `0xc`,
    /// `0xe` (the datagram's bits 19..16); the answer is the status DRVCONF's `rdsel` chose, as
    /// 24 bits (20 status bits, then 4): standstill (bit 7 of the status) always, and with
    /// `rdsel` 2 the coolStep current (`se`, bits 14..10) at the configured CS.
    fn spi_2660(&mut self, data: &mut [u8]) {
        let w = data.iter().fold(0u32, |w, &b| (w << 8) | u32::from(b)) & 0xf_ffff;
        let sel = if w & (1 << 19) == 0 {
            0
        } else {
            ((w >> 16) & 0xe) as u8
        };
        let drvconf = self.regs[0xe];
        let status = match (drvconf >> 4) & 3 {
            2 => ((self.regs[0xc] & 0x1f) << 10) | (1 << 7),
            _ => 1 << 7,
        };
        self.write(sel, w & 0x1_ffff);
        let answer = (status << 4).to_be_bytes();
        let n = data.len().min(3);
        let at = data.len() - n;
        data.fill(0);
        data[at..].copy_from_slice(&answer[4 - n..]);
    }

    /// The registers route a stall to the DIAG pin.
    pub fn stall_reported(&self) -> bool {
        let gconf = self.regs[reg::GCONF as usize];
        let tcoolthrs = self.regs[reg::TCOOLTHRS as usize];
        match self.spec.model {
            Model::Tmc2209 => {
                self.regs[reg::SGTHRS as usize] & 0xff != 0 && tcoolthrs != 0 && gconf & (1 << 2) == 0
            }
            Model::Tmc2208 | Model::Tmc2660 => false,
            Model::Tmc2130 | Model::Tmc2240 | Model::Tmc5160 => {
                let diag0 = self.spec.diag.as_ref().is_some_and(|d| d.diag0);
                let routed = if diag0 { gconf & (1 << 7) } else { gconf & (1 << 8) };
                let stealth = gconf & (1 << 2) != 0;
                // The TMC2240 also detects stalls in stealthChop (stallGuard4, SG4_THRS > 0).
                let sg4 = self.spec.model == Model::Tmc2240 && self.regs[reg::SG4_THRS as usize] & 0xff != 0;
                routed != 0 && tcoolthrs != 0 && (!stealth || sg4)
            }
        }
    }

    /// The DIAG pin's level with the carriage at `pos` (mm).
    pub fn diag_level(&self, pos: f64) -> bool {
        let Some(d) = &self.spec.diag else {
            return false;
        };
        let at_end = if d.at_min {
            pos <= d.end_mm
        } else {
            pos >= d.end_mm
        };
        let stalled = at_end && self.stall_reported();
        let gconf = self.regs[reg::GCONF as usize];
        let active_high = match self.spec.model {
            Model::Tmc2209 | Model::Tmc2208 | Model::Tmc2660 => true,
            _ if d.diag0 => gconf & (1 << 12) != 0,
            _ => gconf & (1 << 13) != 0,
        };
        stalled == active_high
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn driver(model: Model, diag0: bool) -> TmcDriver {
        TmcDriver::new(TmcSpec {
            model,
            bus_pin: 3,
            address: 1,
            diag: Some(DiagSpec {
                pin: 4,
                coord: Coord::axis("x"),
                end_mm: 0.0,
                at_min: true,
                diag0,
            }),
            select: Vec::new(),
        })
    }

    #[test]
    fn uart_writes_count_and_reads_answer_with_crc() {
        let mut d = driver(Model::Tmc2209, false);
        assert_eq!(
            d.uart(&wire::encode_read(1, reg::IFCNT)),
            Some(wire::encode_reply(2, 0))
        );
        assert_eq!(d.uart(&wire::encode_write(1, 0x10, 0x0008_1008)), None);
        // Another address: ignored.
        assert_eq!(d.uart(&wire::encode_write(0, 0x10, 5)), None);
        assert_eq!(d.uart(&wire::encode_read(0, 0x10)), None);
        let reply = d.uart(&wire::encode_read(1, 0x10)).unwrap();
        assert_eq!(wire::decode_reply(0x10, &reply), Some(0x0008_1008));
        let reply = d.uart(&wire::encode_read(1, reg::IFCNT)).unwrap();
        assert_eq!(wire::decode_reply(reg::IFCNT, &reply), Some(1));
        let mut bad = wire::encode_write(1, 0x10, 7);
        bad[9] ^= 0x01;
        assert_eq!(d.uart(&bad), None);
        assert_eq!(d.read(0x10), 0x0008_1008);
        assert_eq!(d.read(0x06) >> 24, 0x21);
    }

    #[test]
    fn spi_answers_the_previous_access() {
        let mut d = driver(Model::Tmc2130, false);
        let mut w = wire::spi_datagram(0x6c | wire::WRITE_BIT, 0x1234_5678);
        d.spi(&mut w);
        assert_eq!(w, [1, 0, 0, 0, 0]);
        let mut r = wire::spi_datagram(0, 0);
        d.spi(&mut r);
        assert_eq!(r, [1, 0x12, 0x34, 0x56, 0x78]);
        let mut r1 = wire::spi_datagram(0x6c, 0);
        d.spi(&mut r1);
        let mut r2 = wire::spi_datagram(0x6c, 0);
        d.spi(&mut r2);
        assert_eq!(&r2[1..], &0x1234_5678u32.to_be_bytes());
    }

    #[test]
    fn a_tmc2660_keeps_its_datagrams_and_answers_the_chosen_status() {
        let mut d = driver(Model::Tmc2660, false);
        // SGCSCONF (selector 110): CS 17.
        let mut m = [0x0c, 0x00, 0x11];
        d.spi(&mut m);
        assert_eq!(d.regs[0xc], 17);
        // DRVCONF with rdsel 2, then again: the answer carries se = CS.
        let mut m = [0x0e, 0x00, 0x20];
        d.spi(&mut m);
        let mut m = [0x0e, 0x00, 0x20];
        d.spi(&mut m);
        let status = u32::from_be_bytes([0, m[0], m[1], m[2]]);
        assert_eq!((status >> 14) & 0x1f, 17, "{status:x}");
        assert_eq!(status & (1 << 11), 1 << 11, "standstill");
        // DRVCTRL (bit 19 clear): mres 4.
        let mut m = [0x00, 0x02, 0x04];
        d.spi(&mut m);
        assert_eq!(d.regs[0], 0x204);
    }

    #[test]
    fn a_tmc2240_reports_stalls_in_stealthchop_with_sg4_thrs() {
        let mut d = driver(Model::Tmc2240, true);
        d.write(reg::GCONF, (1 << 7) | (1 << 2) | (1 << 12));
        d.write(reg::TCOOLTHRS, 0xfffff);
        assert!(!d.diag_level(-1.0), "stealthChop without SG4_THRS");
        d.write(reg::SG4_THRS, 20);
        assert!(d.diag_level(-1.0) && !d.diag_level(0.5));
        assert_eq!(d.read(0x04) >> 24, 0x40);
    }

    #[test]
    fn diag_needs_the_stall_routed() {
        let mut d = driver(Model::Tmc2209, false);
        assert!(!d.diag_level(-1.0));
        d.write(reg::SGTHRS, 100);
        assert!(!d.diag_level(-1.0), "TCOOLTHRS 0");
        d.write(reg::TCOOLTHRS, 0xfffff);
        assert!(d.diag_level(-1.0) && d.diag_level(0.0) && !d.diag_level(0.1));
        d.write(reg::GCONF, 1 << 2);
        assert!(!d.diag_level(-1.0), "spreadCycle");
        let mut s = driver(Model::Tmc5160, false);
        s.write(reg::TCOOLTHRS, 0xfffff);
        assert!(s.diag_level(-1.0), "open drain, idle high");
        s.write(reg::GCONF, 1 << 8);
        assert!(!s.diag_level(-1.0) && s.diag_level(1.0), "active low");
        s.write(reg::GCONF, (1 << 8) | (1 << 13));
        assert!(s.diag_level(-1.0) && !s.diag_level(1.0), "push-pull, active high");
    }
}
