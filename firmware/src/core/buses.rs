//! The serial buses of stepper drivers: TMC UART lines (`config_tmcuart`, `tmcuart_send` →
//! `tmcuart_response`) and SPI devices (`config_spi`, `spi_set_bus`, `spi_set_sw_bus`,
//! `spi_transfer` → `spi_transfer_response`, `spi_send`), with Klipper's commands and framing.
//!
//! The core keeps each line's pins and bit time and hands the exchange to the board
//! ([`Board::tmcuart_transfer`], [`Board::spi_transfer`]), which drives the pins; the answer
//! is reported at once. A UART exchange carries at most [`TMCUART_DATA_MAX`] bytes of line bits
//! each way (a register write: 8 bytes × 10 bits), as on Klipper's MCU ("tmcuart data too
//! large" otherwise); an SPI transaction at most [`SPI_DATA_MAX`] bytes.

use super::board::Board;
use super::commands::*;
use super::constants::reason;
use super::mcu::{Mcu, Object};
use links::proto::format::Value;
use rt_core::WireClock;

/// Largest `write` or `read` of a `tmcuart_send` (bytes of line bits).
pub const TMCUART_DATA_MAX: usize = 10;
/// Largest `data` of an SPI transaction.
pub const SPI_DATA_MAX: usize = 48;

/// A TMC UART line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TmcUart {
    pub rx_pin: u8,
    pub tx_pin: u8,
    pub pull_up: bool,
    /// Ticks per bit.
    pub bit_time: u32,
}

/// An SPI device: its chip select and its bus settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SpiDevice {
    pub cs_pin: u8,
    pub cs_active_high: bool,
    /// SPI mode 0..=3 (from `spi_set_bus` / `spi_set_sw_bus`).
    pub mode: u8,
    /// Hardware bus rate (Hz), or 0 on a software bus.
    pub rate: u32,
}

impl<B: Board, const OIDS: usize, const MOVES: usize> Mcu<B, OIDS, MOVES> {
    /// Runs one command of the buses.
    pub(super) fn handle_bus(&mut self, cmd: Cmd, args: &[Value<'_>], now: WireClock) {
        let arg = |i: usize| args.get(i).map_or(0, Value::int);
        let bytes = |i: usize| match args.get(i) {
            Some(Value::Bytes(b)) => *b,
            _ => &[][..],
        };
        let oid = arg(0);
        match cmd {
            Cmd::ConfigTmcuart => {
                let uart = TmcUart {
                    rx_pin: arg(1) as u8,
                    pull_up: arg(2) != 0,
                    tx_pin: arg(3) as u8,
                    bit_time: arg(4) as u32,
                };
                self.board.config_input(uart.rx_pin, uart.pull_up);
                if self.config_object(oid, Object::TmcUart(uart), now) {
                    self.board.set_pin(uart.tx_pin, true, now);
                }
            }
            Cmd::TmcuartSend => {
                let Some(Object::TmcUart(uart)) = self.object(oid).cloned() else {
                    return self.shutdown(reason::INVALID_OID, now);
                };
                let (write, read_len) = (bytes(1), arg(2) as usize);
                if write.len() > TMCUART_DATA_MAX || read_len > TMCUART_DATA_MAX {
                    return self.shutdown(reason::TMCUART_TOO_LARGE, now);
                }
                let mut read = [0u8; TMCUART_DATA_MAX];
                let read = &mut read[..read_len];
                self.board
                    .tmcuart_transfer(uart.rx_pin, uart.tx_pin, uart.bit_time, write, read);
                let args = [Value::Int(oid), Value::Bytes(read)];
                self.respond(ID_TMCUART_RESPONSE, FMT_TMCUART_RESPONSE, &args);
            }
            Cmd::ConfigSpi => {
                let dev = SpiDevice {
                    cs_pin: arg(1) as u8,
                    cs_active_high: arg(2) != 0,
                    mode: 0,
                    rate: 0,
                };
                if self.config_object(oid, Object::Spi(dev), now) {
                    // Chip select released.
                    self.board.set_pin(dev.cs_pin, !dev.cs_active_high, now);
                }
            }
            Cmd::SpiSetBus | Cmd::SpiSetSwBus => {
                let (mode, rate) = match cmd {
                    Cmd::SpiSetBus => (arg(2) as u8, arg(3) as u32),
                    _ => (arg(4) as u8, 0),
                };
                match self.object(oid) {
                    Some(Object::Spi(d)) => {
                        d.mode = mode;
                        d.rate = rate;
                    }
                    _ => self.shutdown(reason::INVALID_OID, now),
                }
            }
            Cmd::SpiTransfer | Cmd::SpiSend => {
                let Some(Object::Spi(dev)) = self.object(oid).cloned() else {
                    return self.shutdown(reason::INVALID_OID, now);
                };
                let data = bytes(1);
                if data.len() > SPI_DATA_MAX {
                    return self.shutdown(reason::SPI_TOO_LARGE, now);
                }
                let mut buf = [0u8; SPI_DATA_MAX];
                let buf = &mut buf[..data.len()];
                buf.copy_from_slice(data);
                self.board.spi_transfer(dev.cs_pin, buf);
                if cmd == Cmd::SpiTransfer {
                    let args = [Value::Int(oid), Value::Bytes(buf)];
                    self.respond(ID_SPI_TRANSFER_RESPONSE, FMT_SPI_TRANSFER_RESPONSE, &args);
                }
            }
            _ => {}
        }
    }
}
