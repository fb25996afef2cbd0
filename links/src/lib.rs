//! The host side of Cadence's MCU connection, byte-compatible with Klipper's protocol.
//!
//! Layers (bottom up):
//! - [`pinmap`] (`no_std`): the simulated MCU's pin names of every board family and their numbers.
//! - [`proto`] (`no_std`, no allocation, shared with the firmware): CRC-16, VLQ integers,
//!   message blocks, message format strings and parameter encode/decode.
//! - with `std`:
//!   - [`dict`]: the MCU's data dictionary (ids, formats, enumerations, constants), encoding
//!     commands by name into fixed-size [`dict::Cmd`]s and decoding payloads;
//!   - [`transport`]: the byte pipe to an MCU (pty, serial port, in-memory, fault-injecting);
//!   - [`serialqueue`]: the reliable transport state machine (sequence numbers, ack/nak,
//!     retransmit, flow control, scheduling by MCU clock), time passed in as an argument;
//!   - [`clocksync`]: the regression from system time to MCU clock, published lock-free;
//!   - [`mcu`]: the per-MCU IO thread tying them together, and its handle [`mcu::McuLink`];
//!   - [`trsync`]: homing trigger groups across MCUs, relayed by the IO threads.
//!
//! Guarantees: nothing in this crate panics on bytes from the wire; every wait in [`mcu`] is
//! bounded; the IO thread's steady-state loop allocates only to decode rare responses.
#![cfg_attr(not(feature = "std"), no_std)]

pub mod pinmap;
pub mod proto;

#[cfg(feature = "std")]
pub mod clocksync;
#[cfg(feature = "std")]
pub mod dict;
#[cfg(feature = "std")]
pub mod mcu;
#[cfg(feature = "std")]
pub mod serialqueue;
#[cfg(feature = "std")]
pub mod transport;
#[cfg(feature = "std")]
pub mod trsync;
