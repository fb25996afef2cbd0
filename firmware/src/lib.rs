//! The Cadence MCU firmware.
//!
//! Layers:
//! - [`core`] (`no_std`, no allocation): scheduler, steppers, the message table, the link
//!   (framing, sequence, NAK/ack) and the dispatcher, generic over a [`core::Board`].
//! - with `std`: [`dict`] builds the data dictionary (JSON, zlib) from the core's tables;
//!   [`trace`] reads and writes step trace files; [`sim`] is the Linux-process target
//!   `cadence-mcu` (pty, `CLOCK_MONOTONIC` scaled by `--time-scale`, step trace).
#![cfg_attr(not(any(feature = "std", test)), no_std)]

pub mod core;

#[cfg(feature = "std")]
pub mod dict;
#[cfg(feature = "std")]
pub mod sim;
#[cfg(feature = "std")]
pub mod trace;

#[cfg(feature = "std")]
pub use dict::dictionary_bytes;
