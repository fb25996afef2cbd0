//! Register reads and writes of one TMC driver through its MCU, as Klipper's host does them.
//!
//! UART: a read is `tmcuart_send` of the 4-byte request (line bits) asking for 10 line bytes
//! back, the reply checked bit for bit (start/stop bits, sync, register, CRC); a write is
//! `tmcuart_send` of the 8-byte request with nothing to read (its empty answer awaited, so
//! every answer belongs to the request waiting for it), confirmed by IFCNT having counted up by
//! one (IFCNT read before the first write). Each is tried up to 5 times, then "Unable to
//! read/write tmc uart 'NAME' register REG".
//!
//! Behind an analog mux (`select_pins`), the select outputs are set to the driver's levels
//! (`update_digital_out`) before each UART transfer, as Klipper does.
//!
//! An SPI daisy chain (`chain_length`, `chain_position`) clocks one datagram per driver of the
//! chain: this driver's in its place, zeros for the others, and its answer is taken from the
//! same place.
//!
//! SPI: a read is `spi_send` of the request then `spi_transfer` of it again, whose answer
//! carries the value; a write is `spi_send` of the write then `spi_transfer` of a dummy read,
//! whose answer must be the value written (5 tries, then "Unable to write tmc spi …").

use std::time::Duration;

use links::mcu::McuLink;
use links::proto::format::Value;
use links::proto::tmc as wire;
use sysconfig::printer::{TmcBus, TmcModel};

use super::{TmcError, TmcOut};

/// `datagram` as a daisy chain `(length, position)` clocks it (Klipper's framing): zeros for the
/// drivers after this one in the chain, the datagram, zeros for those before it, since the
/// first bytes shift furthest.
fn chained(chain: Option<(u8, u8)>, datagram: [u8; 5]) -> Vec<u8> {
    let Some((len, pos)) = chain else {
        return datagram.to_vec();
    };
    let (len, pos) = (usize::from(len), usize::from(pos));
    let mut out = vec![0u8; len * 5];
    let at = len.saturating_sub(pos) * 5;
    if let Some(slot) = out.get_mut(at..at + 5) {
        slot.copy_from_slice(&datagram);
    }
    out
}

/// This driver's 5 bytes of a chain's answer (the whole answer without a chain).
fn own_answer(chain: Option<(u8, u8)>, answer: &[u8]) -> Option<&[u8]> {
    match chain {
        None => Some(answer),
        Some((len, pos)) => {
            let at = usize::from(len).saturating_sub(usize::from(pos)) * 5;
            answer.get(at..at + 5)
        }
    }
}

/// Tries of one read or write.
const TRIES: usize = 5;
/// Wait for one answer (wall time).
const TIMEOUT: Duration = Duration::from_secs(1);

/// A driver and the link and oid of its bus.
#[derive(Debug, Clone)]
pub struct TmcIo<'a> {
    pub link: &'a McuLink,
    /// Oid of its bus object.
    pub oid: u8,
    pub drv: &'a TmcOut,
    /// Behind an analog mux (`select_pins`): each select output's oid and the level that
    /// selects this driver, set before each transfer.
    pub mux: Vec<(u8, bool)>,
}

/// A TMC2660 datagram: register selector `addr` (datagram bits 19..16) and `value`, in the
/// 3 bytes SPI clocks out.
fn datagram_2660(addr: u8, value: u32) -> [u8; 3] {
    let w = (u32::from(addr) << 16) | (value & 0x1_ffff);
    [(w >> 16) as u8, (w >> 8) as u8, w as u8]
}

impl TmcIo<'_> {
    fn addr(&self, reg: &str) -> Result<u8, TmcError> {
        self.drv
            .cfg
            .model
            .register_addr(reg)
            .ok_or_else(|| TmcError::UnknownRegister { reg: reg.to_string() })
    }

    fn send(&self, name: &str, args: &[Value<'_>]) -> Result<(), TmcError> {
        let cmd = self.link.dictionary().encode_values(name, args)?;
        Ok(self.link.send(cmd)?)
    }

    fn query(
        &self,
        name: &str,
        args: &[Value<'_>],
        response: &str,
    ) -> Result<links::dict::Message, TmcError> {
        let cmd = self.link.dictionary().encode_values(name, args)?;
        Ok(self
            .link
            .query(cmd, response, Some(("oid", i64::from(self.oid))), TIMEOUT)?)
    }

    /// The bus kind for messages: `uart` or `spi`.
    fn bus(&self) -> &'static str {
        if self.drv.cfg.model.is_uart() {
            "uart"
        } else {
            "spi"
        }
    }

    /// Selects this driver on its mux (Klipper sets the select outputs before each transfer).
    fn select(&self) -> Result<(), TmcError> {
        for &(oid, level) in &self.mux {
            self.send(
                "update_digital_out",
                &[Value::Int(i64::from(oid)), Value::Int(i64::from(level))],
            )?;
        }
        Ok(())
    }

    fn stepper(&self) -> &str {
        &self.drv.cfg.stepper
    }

    /// Reads register `reg`.
    pub fn read(&self, reg: &str) -> Result<u32, TmcError> {
        if self.drv.cfg.model == TmcModel::Tmc2660 {
            return self.read_2660(reg);
        }
        let addr = self.addr(reg)?;
        let oid = Value::Int(i64::from(self.oid));
        for _ in 0..TRIES {
            match &self.drv.cfg.bus {
                TmcBus::Uart { address, .. } => {
                    self.select()?;
                    let req = wire::encode_read(*address, addr);
                    let r = self.query(
                        "tmcuart_send",
                        &[
                            oid,
                            Value::Bytes(&req),
                            Value::Int(wire::UART_WRITE_LINE_LEN as i64),
                        ],
                        "tmcuart_response",
                    )?;
                    if let Some(v) = r.bytes("read").and_then(|b| wire::decode_reply(addr, b)) {
                        return Ok(v);
                    }
                }
                TmcBus::Spi { chain, .. } => {
                    let req = chained(*chain, wire::spi_datagram(addr, 0));
                    self.send("spi_send", &[oid, Value::Bytes(&req)])?;
                    let r = self.query(
                        "spi_transfer",
                        &[oid, Value::Bytes(&req)],
                        "spi_transfer_response",
                    )?;
                    if let Some(&[_, a, b, c, d]) = r.bytes("response").and_then(|b| own_answer(*chain, b)) {
                        return Ok(u32::from_be_bytes([a, b, c, d]));
                    }
                }
            }
        }
        Err(TmcError::Read {
            bus: self.bus(),
            stepper: self.stepper().to_string(),
            reg: reg.to_string(),
        })
    }

    /// Writes `value` to register `reg` and checks that the driver took it (a TMC2660 answers
    /// with its status, not an echo: its writes are sent once, as Klipper sends them).
    pub fn write(&self, reg: &str, value: u32) -> Result<(), TmcError> {
        let addr = self.addr(reg)?;
        if self.drv.cfg.model == TmcModel::Tmc2660 {
            let oid = Value::Int(i64::from(self.oid));
            return self.send("spi_send", &[oid, Value::Bytes(&datagram_2660(addr, value))]);
        }
        let oid = Value::Int(i64::from(self.oid));
        match &self.drv.cfg.bus {
            TmcBus::Uart { address, .. } => {
                for _ in 0..TRIES {
                    let before = match self.drv.lock().ifcnt {
                        Some(n) => n,
                        None => self.read("IFCNT")? as u8,
                    };
                    // The MCU answers a write too (nothing read): waiting for that answer
                    // keeps it from being taken for the next read's.
                    let req = wire::encode_write(*address, addr, value);
                    self.select()?;
                    self.query(
                        "tmcuart_send",
                        &[oid, Value::Bytes(&req), Value::Int(0)],
                        "tmcuart_response",
                    )?;
                    let after = self.read("IFCNT")? as u8;
                    self.drv.lock().ifcnt = Some(after);
                    if after == before.wrapping_add(1) {
                        return Ok(());
                    }
                }
                Err(self.write_failed("uart", reg))
            }
            TmcBus::Spi { chain, .. } => {
                for _ in 0..TRIES {
                    let req = chained(*chain, wire::spi_datagram(addr | wire::WRITE_BIT, value));
                    self.send("spi_send", &[oid, Value::Bytes(&req)])?;
                    let dummy = chained(*chain, wire::spi_datagram(0, 0));
                    let r = self.query(
                        "spi_transfer",
                        &[oid, Value::Bytes(&dummy)],
                        "spi_transfer_response",
                    )?;
                    if let Some(&[_, a, b, c, d]) = r.bytes("response").and_then(|b| own_answer(*chain, b)) {
                        if u32::from_be_bytes([a, b, c, d]) == value {
                            return Ok(());
                        }
                    }
                }
                Err(self.write_failed("spi", reg))
            }
        }
    }

    /// A TMC2660 status answer `READRSP@RDSELn`: DRVCONF's `rdsel` set to `n` (sent first
    /// when it changes), then DRVCONF sent again, whose answer is that status (24 bits: the 20
    /// status bits then 4 more).
    fn read_2660(&self, reg: &str) -> Result<u32, TmcError> {
        let n = TmcModel::Tmc2660
            .readable()
            .iter()
            .position(|r| *r == reg)
            .ok_or_else(|| TmcError::UnknownRegister { reg: reg.to_string() })?;
        let drvconf = self.addr("DRVCONF")?;
        let (changed, value) = {
            let mut st = self.drv.lock();
            let old = st.fields.get("rdsel");
            let set = st.fields.set("rdsel", n as i64);
            (old != Some(n as i64), set.map_or(0, |(_, v)| v))
        };
        let msg = datagram_2660(drvconf, value);
        let oid = Value::Int(i64::from(self.oid));
        if changed {
            self.send("spi_send", &[oid, Value::Bytes(&msg)])?;
        }
        let r = self.query(
            "spi_transfer",
            &[oid, Value::Bytes(&msg)],
            "spi_transfer_response",
        )?;
        match r.bytes("response") {
            Some(&[a, b, c]) => Ok(u32::from_be_bytes([0, a, b, c])),
            _ => Err(TmcError::Read {
                bus: self.bus(),
                stepper: self.stepper().to_string(),
                reg: reg.to_string(),
            }),
        }
    }

    /// Every try of a write of `reg` on a `bus` (`uart` or `spi`) failed.
    fn write_failed(&self, bus: &'static str, reg: &str) -> TmcError {
        TmcError::Write {
            bus,
            stepper: self.stepper().to_string(),
            reg: reg.to_string(),
        }
    }

    /// Writes every register as configured (or as last set), in order: `INIT_TMC`, and the
    /// start-up.
    pub fn init(&self) -> Result<(), TmcError> {
        let regs = self.drv.lock().fields.registers().to_vec();
        for (reg, value) in regs {
            self.write(reg, value)?;
        }
        Ok(())
    }
}
