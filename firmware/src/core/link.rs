//! The MCU end of the link: receive framing with sequence checks, and response blocks.
//!
//! Receive: bytes collect in a fixed buffer (more than one maximal block, so
//! [`find_block`] always reaches a verdict on a full buffer). A good block whose sequence is the
//! expected one advances the sequence and is handed out; a corrupt block, or a good block out of
//! order, is dropped and answered with a NAK: an empty block carrying the expected sequence.
//! As in Klipper, after a NAK no further NAK is sent until a block with a valid CRC arrives, so
//! a burst of line noise costs one NAK.
//!
//! Transmit: one response per block, as Klipper's MCU sends them: a response waits in the
//! pending payload until the next response (which writes it first) or [`Link::flush`].
//! Klipper's host parses exactly one response per MCU block and drops the rest of the block
//! ("Extra data at end of message"), so packing `config` and `clock` into one block left it in
//! `startup`. Every block carries the next expected receive sequence, so every response also
//! acks. After each received block the caller calls
//! [`Link::ack`], which flushes the responses and then always sends an empty ack block, as
//! Klipper's MCU does: the host tracks acks from empty blocks only, so that an empty block that
//! repeats the last ack is recognised as a NAK.

use super::board::Board;
use links::proto::block::{block_payload, encode_block, find_block, Frame};
use links::proto::{MESSAGE_MAX, MESSAGE_PAYLOAD_MAX};

/// Receive buffer size: at least two maximal blocks.
pub const RX_CAPACITY: usize = 4 * MESSAGE_MAX;

/// Framing and sequence state of the MCU side of the link.
#[derive(Debug, Clone)]
pub struct Link {
    rx: [u8; RX_CAPACITY],
    rx_len: usize,
    /// Next expected receive sequence (4 bits).
    rx_seq: u8,
    /// A NAK was sent; stay quiet until a block with a valid CRC arrives.
    need_valid: bool,
    tx: [u8; MESSAGE_PAYLOAD_MAX],
    tx_len: usize,
}

impl Default for Link {
    fn default() -> Self {
        Self::new()
    }
}

impl Link {
    /// A link expecting sequence 0.
    pub const fn new() -> Link {
        Link {
            rx: [0; RX_CAPACITY],
            rx_len: 0,
            rx_seq: 0,
            need_valid: false,
            tx: [0; MESSAGE_PAYLOAD_MAX],
            tx_len: 0,
        }
    }

    /// The next sequence number expected from the host.
    pub const fn rx_seq(&self) -> u8 {
        self.rx_seq
    }

    /// Buffers as many of `data` as fit; returns how many were taken.
    pub fn push_rx(&mut self, data: &[u8]) -> usize {
        let n = data.len().min(RX_CAPACITY - self.rx_len);
        self.rx[self.rx_len..self.rx_len + n].copy_from_slice(&data[..n]);
        self.rx_len += n;
        if n == 0 && !data.is_empty() && self.rx_len == RX_CAPACITY {
            // Unreachable while next_block drains the buffer (it always decides on a full
            // buffer); dropping keeps progress guaranteed anyway.
            self.rx_len = 0;
        }
        n
    }

    fn consume(&mut self, n: usize) {
        let n = n.min(self.rx_len);
        self.rx.copy_within(n..self.rx_len, 0);
        self.rx_len -= n;
    }

    /// Finds the next in-order block in the receive buffer, copies its payload into `out` and
    /// returns the payload length. NAKs bad and out-of-order blocks on the way. `None` when
    /// more bytes are needed.
    pub fn next_block<B: Board>(
        &mut self,
        out: &mut [u8; MESSAGE_PAYLOAD_MAX],
        board: &mut B,
    ) -> Option<usize> {
        loop {
            match find_block(&self.rx[..self.rx_len]) {
                Frame::Incomplete => return None,
                Frame::Skip(n) => self.consume(n),
                Frame::Bad(n) => {
                    self.consume(n);
                    if !self.need_valid {
                        self.need_valid = true;
                        self.nak(board);
                    }
                }
                Frame::Block { len, seq } => {
                    self.need_valid = false;
                    if seq != self.rx_seq {
                        self.consume(len);
                        self.need_valid = true;
                        self.nak(board);
                        continue;
                    }
                    let payload = block_payload(&self.rx[..len]);
                    let n = payload.len().min(MESSAGE_PAYLOAD_MAX);
                    out[..n].copy_from_slice(&payload[..n]);
                    self.consume(len);
                    self.rx_seq = (self.rx_seq + 1) & 0x0F;
                    return Some(n);
                }
            }
        }
    }

    fn nak<B: Board>(&mut self, board: &mut B) {
        self.flush(board);
        self.write_block(&[], board);
    }

    fn write_block<B: Board>(&mut self, payload: &[u8], board: &mut B) {
        let mut block = [0u8; MESSAGE_MAX];
        if let Some(n) = encode_block(self.rx_seq, payload, &mut block) {
            board.write(&block[..n]);
        }
    }

    /// Queues one encoded message for the host in a block of its own (dropped if longer than a
    /// block payload); a response still pending is written first.
    pub fn send<B: Board>(&mut self, msg: &[u8], board: &mut B) {
        if msg.len() > MESSAGE_PAYLOAD_MAX {
            debug_assert!(false, "message longer than a block");
            return;
        }
        self.flush(board);
        self.tx[self.tx_len..self.tx_len + msg.len()].copy_from_slice(msg);
        self.tx_len += msg.len();
    }

    /// Writes the pending response block, if any.
    pub fn flush<B: Board>(&mut self, board: &mut B) {
        if self.tx_len > 0 {
            let tx = self.tx;
            let n = self.tx_len;
            self.tx_len = 0;
            self.write_block(&tx[..n], board);
        }
    }

    /// Call after a received block was dispatched: flushes responses, then sends the empty
    /// ack block.
    pub fn ack<B: Board>(&mut self, board: &mut B) {
        self.flush(board);
        self.write_block(&[], board);
    }
}
