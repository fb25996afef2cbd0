//! Klipper's wire format, `no_std` and allocation-free: shared by the host and the firmware.
//!
//! Every function here takes bytes from the wire and must not panic on any input: it returns
//! an error or a "need more bytes" answer instead.

pub mod block;
pub mod crc;
pub mod format;
pub mod stream;
pub mod tmc;
pub mod vlq;

pub use block::{
    encode_block, find_block, Frame, MESSAGE_MAX, MESSAGE_MIN, MESSAGE_PAYLOAD_MAX, MESSAGE_SYNC,
};
pub use format::{decode_params, encode_message, FormatError, ParamType, Params, Value};
pub use stream::{blocks, StreamItem};

/// Message id of `identify_response offset=%u data=%.*s` (fixed in every build).
pub const ID_IDENTIFY_RESPONSE: u32 = 0;
/// Message id of `identify offset=%u count=%c` (fixed in every build).
pub const ID_IDENTIFY: u32 = 1;
/// Format of the fixed identify response.
pub const FMT_IDENTIFY_RESPONSE: &str = "identify_response offset=%u data=%.*s";
/// Format of the fixed identify command.
pub const FMT_IDENTIFY: &str = "identify offset=%u count=%c";
