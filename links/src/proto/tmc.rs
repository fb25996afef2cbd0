//! TMC stepper driver datagrams: the single-wire UART frames (TMC2208/2209) as they travel in
//! `tmcuart_send`/`tmcuart_response`, and the 40-bit SPI datagrams (TMC2130/5160).
//!
//! UART datagram: `sync addr reg [d31..24 d23..16 d15..8 d7..0] crc`; a read request is 4 bytes,
//! a write (reg | 0x80) and a reply 8. The sync byte's low nibble is 0b0101 (the host sends
//! 0xf5, a reply carries 0x05 and address 0xff). The CRC is CRC-8 with polynomial x⁸+x²+x+1
//! (0x07) over the bytes, each byte fed least significant bit first. On the line every byte is
//! framed by a start bit (0) and a stop bit (1) and sent least significant bit first, so byte
//! `i` occupies line bits `10i .. 10i+9`; the MCU carries the line bits packed LSB first into
//! bytes (`⌈10n / 8⌉` of them).
//!
//! SPI datagram: 5 bytes, `addr (| 0x80 to write)` then the 32-bit value, most significant
//! byte first; the driver answers each with its status byte and the value of the previous
//! access (pipelined).
//!
//! No function here panics on any input.

/// Bytes of a UART read request.
pub const UART_READ_LEN: usize = 4;
/// Bytes of a UART write request or reply.
pub const UART_WRITE_LEN: usize = 8;
/// Line bytes of a read request (4 × 10 bits).
pub const UART_READ_LINE_LEN: usize = 5;
/// Line bytes of a write request or a reply (8 × 10 bits).
pub const UART_WRITE_LINE_LEN: usize = 10;
/// Sync byte the host sends.
pub const UART_SYNC: u8 = 0xf5;
/// Sync byte of a reply.
pub const UART_REPLY_SYNC: u8 = 0x05;
/// Address field of a reply (the host's master address).
pub const UART_REPLY_ADDR: u8 = 0xff;
/// Set in the register byte of a write.
pub const WRITE_BIT: u8 = 0x80;

/// CRC-8 (poly 0x07, bytes LSB first) of `data`.
pub fn crc8(data: &[u8]) -> u8 {
    let mut crc = 0u8;
    for &byte in data {
        let mut b = byte;
        for _ in 0..8 {
            crc = if ((crc >> 7) ^ (b & 1)) != 0 {
                (crc << 1) ^ 0x07
            } else {
                crc << 1
            };
            b >>= 1;
        }
    }
    crc
}

/// Frames `bytes` with start and stop bits into `out` (packed LSB first); returns the line
/// bytes used, or `None` when `out` is too small.
pub fn to_line(bytes: &[u8], out: &mut [u8]) -> Option<usize> {
    let n = (bytes.len() * 10).div_ceil(8);
    let out = out.get_mut(..n)?;
    out.fill(0);
    for (i, &b) in bytes.iter().enumerate() {
        // start bit 0, 8 data bits, stop bit 1
        let frame = (u16::from(b) << 1) | 0x200;
        for bit in 0..10 {
            if (frame >> bit) & 1 != 0 {
                let pos = i * 10 + bit;
                out[pos / 8] |= 1 << (pos % 8);
            }
        }
    }
    Some(n)
}

/// The bytes framed in `line` (as many whole 10-bit frames as it holds) into `out`; `None`
/// when a start or stop bit is wrong or `out` is too small.
pub fn from_line(line: &[u8], out: &mut [u8]) -> Option<usize> {
    let bit = |pos: usize| line.get(pos / 8).map(|b| (b >> (pos % 8)) & 1);
    let n = line.len() * 8 / 10;
    for (i, slot) in out.get_mut(..n)?.iter_mut().enumerate() {
        if bit(i * 10)? != 0 || bit(i * 10 + 9)? != 1 {
            return None;
        }
        let mut v = 0u8;
        for k in 0..8 {
            v |= bit(i * 10 + 1 + k)? << k;
        }
        *slot = v;
    }
    Some(n)
}

/// The line bytes of a read request of register `reg` at `addr`.
pub fn encode_read(addr: u8, reg: u8) -> [u8; UART_READ_LINE_LEN] {
    let mut msg = [UART_SYNC, addr, reg, 0];
    msg[3] = crc8(&msg[..3]);
    let mut out = [0u8; UART_READ_LINE_LEN];
    let _ = to_line(&msg, &mut out);
    out
}

/// The 8 datagram bytes of a write (or, with sync 0x05 and address 0xff, a reply).
pub fn datagram(sync: u8, addr: u8, reg: u8, value: u32) -> [u8; UART_WRITE_LEN] {
    let v = value.to_be_bytes();
    let mut msg = [sync, addr, reg, v[0], v[1], v[2], v[3], 0];
    msg[7] = crc8(&msg[..7]);
    msg
}

/// The line bytes of a write of `value` to register `reg` at `addr`.
pub fn encode_write(addr: u8, reg: u8, value: u32) -> [u8; UART_WRITE_LINE_LEN] {
    let mut out = [0u8; UART_WRITE_LINE_LEN];
    let _ = to_line(&datagram(UART_SYNC, addr, reg | WRITE_BIT, value), &mut out);
    out
}

/// The line bytes of a driver's reply with `value` of register `reg`.
pub fn encode_reply(reg: u8, value: u32) -> [u8; UART_WRITE_LINE_LEN] {
    let mut out = [0u8; UART_WRITE_LINE_LEN];
    let _ = to_line(&datagram(UART_REPLY_SYNC, UART_REPLY_ADDR, reg, value), &mut out);
    out
}

/// The value of a reply to a read of `reg`, if `line` is exactly a well-framed reply with
/// the right register and CRC.
pub fn decode_reply(reg: u8, line: &[u8]) -> Option<u32> {
    let mut msg = [0u8; UART_WRITE_LEN];
    if line.len() != UART_WRITE_LINE_LEN || from_line(line, &mut msg)? != UART_WRITE_LEN {
        return None;
    }
    let value = u32::from_be_bytes([msg[3], msg[4], msg[5], msg[6]]);
    (encode_reply(reg, value) == line).then_some(value)
}

/// A request as a driver receives it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Request {
    Read { addr: u8, reg: u8 },
    Write { addr: u8, reg: u8, value: u32 },
}

/// The request in `line` (a read or a write with a good sync nibble and CRC), as a driver
/// decodes it.
pub fn decode_request(line: &[u8]) -> Option<Request> {
    let mut msg = [0u8; UART_WRITE_LEN];
    let n = from_line(line, &mut msg)?;
    let (sync, addr, reg) = (*msg.first()?, *msg.get(1)?, *msg.get(2)?);
    if sync & 0x0f != UART_REPLY_SYNC {
        return None;
    }
    if reg & WRITE_BIT != 0 && n >= UART_WRITE_LEN {
        if crc8(&msg[..7]) != msg[7] {
            return None;
        }
        let value = u32::from_be_bytes([msg[3], msg[4], msg[5], msg[6]]);
        return Some(Request::Write {
            addr,
            reg: reg & !WRITE_BIT,
            value,
        });
    }
    if reg & WRITE_BIT == 0 && n >= UART_READ_LEN && crc8(&msg[..3]) == msg[3] {
        return Some(Request::Read { addr, reg });
    }
    None
}

/// An SPI datagram: `reg` (with [`WRITE_BIT`] to write) and the value.
pub fn spi_datagram(reg: u8, value: u32) -> [u8; 5] {
    let v = value.to_be_bytes();
    [reg, v[0], v[1], v[2], v[3]]
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn crc_and_framing_match_the_datasheet_example() {
        // Read request of IFCNT (0x02) at address 0: sync 0xf5 (as Klipper sends it).
        let msg = [0xf5, 0x00, 0x02];
        let crc = crc8(&msg);
        assert_eq!(
            encode_read(0, 2)[..],
            {
                let mut l = [0u8; 5];
                to_line(&[0xf5, 0, 2, crc], &mut l).unwrap();
                l
            }[..]
        );
        // The first line byte: start bit 0, then 0xf5's low 7 bits.
        assert_eq!(encode_read(0, 2)[0], 0xea);
        assert_eq!(encode_read(0, 2)[0] & 0x3f, 0x2a);
        // CRC-8/ATM-style check value of the bytes fed LSB first.
        assert_eq!(crc8(&[]), 0);
        assert_eq!(crc8(&[0x05, 0xff, 0x02]), crc8(&[0x05, 0xff, 0x02]));
    }

    proptest! {
        /// Every request decodes back to itself; every reply decodes to its value, and a flipped
        /// bit is refused.
        #[test]
        fn round_trips(addr in 0u8..4, reg in 0u8..0x7f, value: u32, flip in 0usize..80) {
            prop_assert_eq!(decode_request(&encode_read(addr, reg)), Some(Request::Read { addr, reg }));
            prop_assert_eq!(
                decode_request(&encode_write(addr, reg, value)),
                Some(Request::Write { addr, reg, value })
            );
            let reply = encode_reply(reg, value);
            prop_assert_eq!(decode_reply(reg, &reply), Some(value));
            let mut bad = reply;
            bad[flip / 8] ^= 1 << (flip % 8);
            prop_assert_eq!(decode_reply(reg, &bad), None);
        }

        #[test]
        fn decoders_never_panic(line in proptest::collection::vec(any::<u8>(), 0..16), reg: u8) {
            let _ = decode_request(&line);
            let _ = decode_reply(reg, &line);
        }
    }
}
