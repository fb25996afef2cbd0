//! Message blocks: `[len][seq][payload…][crc_hi][crc_lo][0x7E]`.
//!
//! Byte offsets: `len` at 0 counts the whole block (5..=64); `seq` at 1 is `0x10 | (n & 0x0F)`;
//! the payload follows; the CRC-16 of bytes `0..len-3` sits big-endian at `len-3`; the sync
//! byte 0x7E closes the block. An empty block (len 5) is an ack or a nak.

use super::crc::crc16_ccitt;

/// Smallest block: header and trailer only.
pub const MESSAGE_MIN: usize = 5;
/// Largest block.
pub const MESSAGE_MAX: usize = 64;
/// Header bytes (len, seq).
pub const MESSAGE_HEADER_SIZE: usize = 2;
/// Trailer bytes (crc hi, crc lo, sync).
pub const MESSAGE_TRAILER_SIZE: usize = 3;
/// Largest payload in one block.
pub const MESSAGE_PAYLOAD_MAX: usize = MESSAGE_MAX - MESSAGE_MIN;
/// Offset of the sequence byte.
pub const MESSAGE_POS_SEQ: usize = 1;
/// The sync byte that ends every block.
pub const MESSAGE_SYNC: u8 = 0x7E;
/// High nibble every sequence byte carries.
pub const MESSAGE_DEST: u8 = 0x10;
/// Mask of the sequence number inside the sequence byte.
pub const MESSAGE_SEQ_MASK: u8 = 0x0F;

/// What [`find_block`] saw at the front of a receive buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Frame {
    /// Not enough bytes yet for a verdict.
    Incomplete,
    /// A valid block of `len` bytes starts the buffer; its 4-bit sequence is `seq`.
    Block { len: usize, seq: u8 },
    /// Stray sync bytes: drop `n` bytes silently.
    Skip(usize),
    /// A corrupt block: drop `n` bytes (through the next sync byte) and send one NAK.
    Bad(usize),
}

/// Classifies the front of `buf`. Never panics; never asks to drop zero bytes.
pub fn find_block(buf: &[u8]) -> Frame {
    let Some(&len_byte) = buf.first() else {
        return Frame::Incomplete;
    };
    if len_byte == MESSAGE_SYNC {
        let n = buf.iter().take_while(|&&b| b == MESSAGE_SYNC).count();
        return Frame::Skip(n);
    }
    let len = len_byte as usize;
    if !(MESSAGE_MIN..=MESSAGE_MAX).contains(&len) {
        return bad(buf);
    }
    if let Some(&seq) = buf.get(MESSAGE_POS_SEQ) {
        if seq & !MESSAGE_SEQ_MASK != MESSAGE_DEST {
            return bad(buf);
        }
    }
    if buf.len() < len {
        return Frame::Incomplete;
    }
    let seq = buf[MESSAGE_POS_SEQ];
    if buf[len - 1] != MESSAGE_SYNC {
        return bad(buf);
    }
    let crc = crc16_ccitt(&buf[..len - MESSAGE_TRAILER_SIZE]);
    let got = u16::from_be_bytes([buf[len - 3], buf[len - 2]]);
    if crc != got {
        return bad(buf);
    }
    Frame::Block {
        len,
        seq: seq & MESSAGE_SEQ_MASK,
    }
}

/// Drop through the next sync byte after position 0 (or everything if there is none yet).
fn bad(buf: &[u8]) -> Frame {
    match buf.iter().skip(1).position(|&b| b == MESSAGE_SYNC) {
        Some(p) => Frame::Bad(p + 2),
        None => Frame::Bad(buf.len().max(1)),
    }
}

/// Writes a block carrying `payload` with sequence `seq` (low 4 bits used) into `out`.
/// Returns the block length, or `None` if the payload is too long or `out` too short.
pub fn encode_block(seq: u8, payload: &[u8], out: &mut [u8]) -> Option<usize> {
    if payload.len() > MESSAGE_PAYLOAD_MAX {
        return None;
    }
    let len = payload.len() + MESSAGE_MIN;
    let dst = out.get_mut(..len)?;
    dst[0] = len as u8;
    dst[1] = MESSAGE_DEST | (seq & MESSAGE_SEQ_MASK);
    dst[2..2 + payload.len()].copy_from_slice(payload);
    let crc = crc16_ccitt(&dst[..len - MESSAGE_TRAILER_SIZE]);
    dst[len - 3..len - 1].copy_from_slice(&crc.to_be_bytes());
    dst[len - 1] = MESSAGE_SYNC;
    Some(len)
}

/// The payload of a block that [`find_block`] accepted.
pub fn block_payload(block: &[u8]) -> &[u8] {
    let len = block.len();
    if len < MESSAGE_MIN {
        return &[];
    }
    &block[MESSAGE_HEADER_SIZE..len - MESSAGE_TRAILER_SIZE]
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn ack_golden_bytes() {
        let mut out = [0u8; 64];
        let n = encode_block(1, &[], &mut out).unwrap();
        let crc = crc16_ccitt(&[0x05, 0x11]).to_be_bytes();
        assert_eq!(&out[..n], &[0x05, 0x11, crc[0], crc[1], 0x7E]);
        assert_eq!(find_block(&out[..n]), Frame::Block { len: 5, seq: 1 });
    }

    #[test]
    fn identify_golden_bytes() {
        // identify offset=0 count=40: id 1, then VLQ 0, then VLQ 40.
        let mut out = [0u8; 64];
        let n = encode_block(0, &[0x01, 0x00, 0x28], &mut out).unwrap();
        assert_eq!(&out[..5], &[0x08, 0x10, 0x01, 0x00, 0x28]);
        assert_eq!(out[n - 1], 0x7E);
        assert_eq!(block_payload(&out[..n]), &[0x01, 0x00, 0x28]);
    }

    #[test]
    fn corrupt_and_partial() {
        let mut out = [0u8; 64];
        let n = encode_block(3, &[1, 2, 3], &mut out).unwrap();
        assert_eq!(find_block(&out[..n - 1]), Frame::Incomplete);
        let mut bad_crc = out;
        bad_crc[3] ^= 0x40;
        assert_eq!(find_block(&bad_crc[..n]), Frame::Bad(n));
        assert_eq!(find_block(&[0x7E, 0x7E, 0x05]), Frame::Skip(2));
        assert_eq!(find_block(&[0x02, 0x11, 0x7E, 0x05]), Frame::Bad(3));
        assert_eq!(find_block(&[0x05, 0x21]), Frame::Bad(2));
        let too_long = [0x05, 0x10, 0, 0];
        let payload = [0u8; MESSAGE_PAYLOAD_MAX + 1];
        assert_eq!(encode_block(0, &payload, &mut out), None);
        let _ = too_long;
    }

    proptest! {
        #[test]
        fn round_trip(seq in 0u8..16, payload in proptest::collection::vec(any::<u8>(), 0..=MESSAGE_PAYLOAD_MAX)) {
            let mut out = [0u8; 64];
            let n = encode_block(seq, &payload, &mut out).unwrap();
            prop_assert_eq!(find_block(&out[..n]), Frame::Block { len: n, seq });
            prop_assert_eq!(block_payload(&out[..n]), &payload[..]);
        }

        #[test]
        fn never_panics_and_always_progresses(data in proptest::collection::vec(any::<u8>(), 0..200)) {
            let mut rest = &data[..];
            loop {
                match find_block(rest) {
                    Frame::Incomplete => break,
                    Frame::Block { len, .. } => rest = &rest[len..],
                    Frame::Skip(n) | Frame::Bad(n) => {
                        prop_assert!(n > 0 && n <= rest.len());
                        rest = &rest[n..];
                    }
                }
            }
        }
    }
}
