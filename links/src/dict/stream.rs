//! Decoding a captured byte stream (a sequence of blocks) for humans: the `cadence decode`
//! tool prints host → MCU traffic one message per line.
//!
//! Blocks are found with [`crate::proto::find_block`], so the stream resynchronises on garbage
//! the same way the MCU does (drop through the next sync byte).

use std::fmt;

use super::{Dictionary, Message};
use crate::proto::block::block_payload;
use crate::proto::{find_block, Frame, MESSAGE_MIN};

/// One item of a decoded stream.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum StreamItem {
    /// A block and its messages.
    Block { seq: u8, messages: Vec<Message> },
    /// An empty block (ack or nak).
    Ack { seq: u8 },
    /// A valid block whose payload did not decode with this dictionary.
    Undecodable {
        seq: u8,
        payload: Vec<u8>,
        error: String,
    },
    /// Bytes that were not a valid block.
    Garbage { len: usize },
    /// Bytes at the end that do not make a whole block.
    Partial { len: usize },
}

/// One message per line; non-message items as `#` comments.
impl fmt::Display for StreamItem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            StreamItem::Block { messages, .. } => {
                for (i, m) in messages.iter().enumerate() {
                    if i > 0 {
                        writeln!(f)?;
                    }
                    write!(f, "{m}")?;
                }
                Ok(())
            }
            StreamItem::Ack { seq } => write!(f, "# ack/nak seq={seq}"),
            StreamItem::Undecodable { seq, payload, error } => {
                write!(f, "# undecodable block seq={seq} ({error}): {payload:02x?}")
            }
            StreamItem::Garbage { len } => write!(f, "# {len} invalid bytes"),
            StreamItem::Partial { len } => write!(f, "# {len} bytes of an incomplete block"),
        }
    }
}

impl Dictionary {
    /// Decodes a stream of blocks. With `commands_only`, payloads must hold commands (host →
    /// MCU direction); otherwise any message kind is accepted.
    pub fn decode_stream(&self, stream: &[u8], commands_only: bool) -> Vec<StreamItem> {
        let mut items = Vec::new();
        let mut rest = stream;
        while !rest.is_empty() {
            match find_block(rest) {
                Frame::Incomplete => {
                    items.push(StreamItem::Partial { len: rest.len() });
                    break;
                }
                Frame::Skip(n) => rest = &rest[n.min(rest.len())..],
                Frame::Bad(n) => {
                    items.push(StreamItem::Garbage { len: n });
                    rest = &rest[n.min(rest.len())..];
                }
                Frame::Block { len, seq } => {
                    let payload = block_payload(&rest[..len]);
                    let decoded = if commands_only {
                        self.decode_command(payload)
                    } else {
                        self.decode(payload)
                    };
                    items.push(match decoded {
                        _ if len == MESSAGE_MIN => StreamItem::Ack { seq },
                        Ok(messages) => StreamItem::Block { seq, messages },
                        Err(e) => StreamItem::Undecodable {
                            seq,
                            payload: payload.to_vec(),
                            error: e.to_string(),
                        },
                    });
                    rest = &rest[len..];
                }
            }
        }
        items
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::test_dict;
    use crate::proto::encode_block;
    use proptest::prelude::*;

    #[test]
    fn stream_of_blocks() {
        let d = test_dict();
        let mut stream = vec![0x7E, 0x01, 0x02, 0x7E];
        let mut buf = [0u8; 64];
        let mut payload = Vec::new();
        payload.extend_from_slice(d.encode("queue_step", &[1, 100, 2, 0]).unwrap().as_bytes());
        payload.extend_from_slice(d.encode("get_clock", &[]).unwrap().as_bytes());
        let n = encode_block(3, &payload, &mut buf).unwrap();
        stream.extend_from_slice(&buf[..n]);
        let n = encode_block(4, &[], &mut buf).unwrap();
        stream.extend_from_slice(&buf[..n]);
        let n = encode_block(5, &[250], &mut buf).unwrap();
        stream.extend_from_slice(&buf[..n]);
        stream.extend_from_slice(&[0x09, 0x10]);
        let items = d.decode_stream(&stream, true);
        let text: Vec<String> = items.iter().map(|i| i.to_string()).collect();
        assert_eq!(text[0], "# 3 invalid bytes");
        assert_eq!(text[1], "queue_step oid=1 interval=100 count=2 add=0\nget_clock");
        assert_eq!(text[2], "# ack/nak seq=4");
        assert!(text[3].starts_with("# undecodable block seq=5"));
        assert_eq!(text[4], "# 2 bytes of an incomplete block");
        assert_eq!(items.len(), 5);
    }

    proptest! {
        #[test]
        fn never_panics(data in proptest::collection::vec(any::<u8>(), 0..200)) {
            let d = test_dict();
            let _ = d.decode_stream(&data, true);
            let _ = d.decode_stream(&data, false);
        }
    }
}
