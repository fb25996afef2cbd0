//! The firmware core: `no_std`, no allocation, fixed capacities, time as an argument.
//!
//! Layers (bottom up):
//! - [`sched`]: one timer per oid on the wrapping 32-bit clock;
//! - [`moves`] and [`stepper`]: the shared move pool and the `queue_step` replay;
//! - [`endstop`], [`trsync`], [`digital_out`], [`pwm_out`], [`analog_in`], [`counter`]: the other oid objects, each a
//!   state machine that returns what to do; `objects` wires them to commands and timers;
//! - [`buses`]: the TMC UART lines and SPI devices (`tmcuart_send`, `spi_transfer`);
//! - [`thermocouple`]: SPI temperature chips read periodically over an SPI device;
//! - [`commands`] and [`constants`]: the message table and the dictionary's static data,
//!   declared once (the dispatcher and the dictionary generator both read them);
//! - [`link`]: block framing, sequence checks, NAK and ack, response blocks;
//! - [`mcu`] and `dispatch`: the state machine the platform drives through
//!   [`Mcu::receive`], [`Mcu::run_timers`] and [`Mcu::next_wake`];
//! - [`board`]: the [`Board`] trait, the only way out to hardware.
//!
//! Guarantees: no input makes the core panic (faults end in [`Mcu::shutdown`]); nothing
//! allocates; the core never reads a clock.

pub mod analog_in;
pub mod board;
pub mod buses;
pub mod commands;
pub mod constants;
pub mod counter;
pub mod digital_out;
mod dispatch;
pub mod endstop;
pub mod link;
pub mod mcu;
pub mod moves;
mod objects;
pub mod pwm_out;
pub mod sched;
pub mod stepper;
pub mod thermocouple;
pub mod trsync;

pub use board::{Board, Lateness, TriggerSource};
pub use commands::{Cmd, Kind, MessageDef, MESSAGES};
pub use constants::{reason, static_string_id, ConstValue, CONSTANTS, SHUTDOWN_REASONS};
pub use dispatch::IDENTIFY_CHUNK_MAX;
pub use mcu::{Mcu, McuConfig};
pub use sched::Scheduler;
pub use stepper::{Stepper, StepperConfig, StepperError};
