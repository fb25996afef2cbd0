//! The Cadence MCU firmware.
//!
//! Layers:
//! - [`core`] (`no_std`, no allocation): scheduler, steppers, the message table, the link
//!   (framing, sequence, NAK/ack) and the dispatcher, generic over a [`core::Board`].
//! - with `std` (or only `dict`, for a board's build script): [`dict`] builds the data
//!   dictionary (JSON, zlib) from the core's tables;
//! - with `std`: [`trace`] reads and writes step trace files; [`sim`] is the Linux-process target
//!   `cadence-mcu` (pty, `CLOCK_MONOTONIC` scaled by `--time-scale`, step trace).
#![cfg_attr(not(any(feature = "std", feature = "dict", test)), no_std)]

pub mod core;

#[cfg(feature = "dict")]
pub mod dict;
#[cfg(feature = "std")]
pub mod sim;
#[cfg(feature = "std")]
pub mod trace;

#[cfg(feature = "dict")]
pub use dict::dictionary_bytes;
