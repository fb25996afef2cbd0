//! Cadence's leaf crate.
//!
//! Layers:
//! - [`time`]: one type per kind of time (system time, print time, 64-bit host MCU clock,
//!   32-bit wire/MCU clock) and the only place where 32-bit clocks are compared or extended.
//!
//! The crate is `no_std` unless the `std` feature is on (the firmware core uses it bare).
#![cfg_attr(not(feature = "std"), no_std)]

pub mod time;

pub use time::{McuClock, PrintTime, SystemTime, WireClock};
