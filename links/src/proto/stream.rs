//! Walking a stored stream of blocks (a batch file, a captured wire log) front to back.
//!
//! [`blocks`] yields each block's payload with its byte offset, reports a corrupt block (and
//! steps over it to the next sync byte, as a receiver would), drops stray sync bytes silently,
//! and ends with [`StreamItem::Truncated`] when the stream stops inside a block. Every reader
//! of stored streams (decode, the wire checker, the stream counter) walks them through this one
//! loop, so they agree on what a stream holds and on the byte offsets their errors name.

use super::block::{block_payload, find_block, Frame};

/// One thing found walking a stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StreamItem<'a> {
    /// A valid block starting at byte `pos`, with its sequence number and payload.
    Block { pos: usize, seq: u8, payload: &'a [u8] },
    /// A corrupt block at byte `pos`; `len` bytes (through the next sync byte) were skipped.
    Bad { pos: usize, len: usize },
    /// The stream ends inside a block starting at byte `pos`, `left` bytes before the end.
    /// Always the last item.
    Truncated { pos: usize, left: usize },
}

/// The blocks of `data`, in order.
pub fn blocks(data: &[u8]) -> Blocks<'_> {
    Blocks { data, pos: 0 }
}

/// Iterator of [`blocks`]. Never panics: every slice is within `data` by `find_block`'s
/// lengths, which never exceed the buffer it was given and are never zero.
#[derive(Debug, Clone)]
pub struct Blocks<'a> {
    data: &'a [u8],
    pos: usize,
}

impl<'a> Iterator for Blocks<'a> {
    type Item = StreamItem<'a>;

    fn next(&mut self) -> Option<StreamItem<'a>> {
        loop {
            let pos = self.pos;
            let rest = self.data.get(pos..).filter(|r| !r.is_empty())?;
            match find_block(rest) {
                Frame::Skip(n) => self.pos += n,
                Frame::Block { len, seq } => {
                    self.pos += len;
                    let payload = block_payload(rest.get(..len).unwrap_or(&[]));
                    return Some(StreamItem::Block { pos, seq, payload });
                }
                Frame::Bad(len) => {
                    self.pos += len;
                    return Some(StreamItem::Bad { pos, len });
                }
                Frame::Incomplete => {
                    self.pos = self.data.len();
                    return Some(StreamItem::Truncated {
                        pos,
                        left: rest.len(),
                    });
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::proto::block::{encode_block, MESSAGE_MAX, MESSAGE_SYNC};
    use proptest::prelude::*;

    fn block(seq: u8, payload: &[u8]) -> ([u8; MESSAGE_MAX], usize) {
        let mut buf = [0u8; MESSAGE_MAX];
        let len = encode_block(seq, payload, &mut buf).expect("fits");
        (buf, len)
    }

    #[test]
    fn walks_blocks_skips_sync_and_reports_bad_and_truncated() {
        let mut data = Vec::new();
        let (a, la) = block(1, &[1, 2, 3]);
        data.extend_from_slice(&a[..la]);
        data.extend_from_slice(&[MESSAGE_SYNC, MESSAGE_SYNC]);
        let (b, lb) = block(2, &[9]);
        let mut corrupt = b[..lb].to_vec();
        corrupt[2] ^= 0xFF; // CRC no longer matches
        let bad_at = data.len();
        data.extend_from_slice(&corrupt);
        let c_at = data.len();
        data.extend_from_slice(&b[..lb]);
        let trunc_at = data.len();
        data.extend_from_slice(&a[..la - 1]);
        let items: Vec<_> = blocks(&data).collect();
        assert_eq!(
            items,
            [
                StreamItem::Block {
                    pos: 0,
                    seq: 1,
                    payload: &[1, 2, 3]
                },
                StreamItem::Bad { pos: bad_at, len: lb },
                StreamItem::Block {
                    pos: c_at,
                    seq: 2,
                    payload: &[9]
                },
                StreamItem::Truncated {
                    pos: trunc_at,
                    left: la - 1
                },
            ]
        );
        assert_eq!(blocks(&[]).count(), 0);
    }

    proptest! {
        /// Any bytes: the items never overlap, move forward, and stay within the data.
        #[test]
        fn any_bytes_walk_forward_within_the_data(data in proptest::collection::vec(any::<u8>(), 0..400)) {
            let mut next_free = 0usize;
            for item in blocks(&data) {
                let (pos, len) = match item {
                    StreamItem::Block { pos, payload, .. } => (pos, payload.len() + 5),
                    StreamItem::Bad { pos, len } => (pos, len),
                    StreamItem::Truncated { pos, left } => (pos, left),
                };
                prop_assert!(pos >= next_free && len > 0 && pos + len <= data.len());
                next_free = pos + len;
            }
        }
    }
}
