//! The host side of Cadence's MCU connection, byte-compatible with Klipper's protocol.
//!
//! Layers (bottom up):
//! - [`proto`] (`no_std`, no allocation, shared with the firmware): CRC-16, VLQ integers,
//!   message blocks, message format strings and parameter encode/decode.
//! - with `std`: the data dictionary, transports (pty/serial/in-memory), the reliable
//!   transport (ack/nak/retransmit), clock sync and the per-MCU IO thread.
#![cfg_attr(not(feature = "std"), no_std)]

pub mod proto;
