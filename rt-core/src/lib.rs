//! Cadence's leaf crate.
//!
//! Layers:
//! - [`time`]: one type per kind of time (system time, print time, 64-bit host MCU clock,
//!   32-bit wire/MCU clock) and the only place where 32-bit clocks are compared or extended.
//! - `std` only:
//!   - [`os`]: the thread runtime (pinning, SCHED_FIFO, mlockall, stack prefault,
//!     `/dev/cpu_dma_latency`) with a process-wide report of refused guarantees.
//!   - [`alloc_count`]: a counting global allocator for tests that prove "no allocation in RT
//!     loops".
//!   - [`handoff`]: the bounded queue between threads of different real-time priorities that
//!     never waits on the other side (crossbeam's `ArrayQueue` spins on a half-done push or
//!     pop: a livelock under SCHED_FIFO on a shared core).
//!   - [`hist`]: fixed-bound latency/margin histograms (hdrhistogram), summaries, interval logs.
//!   - [`host_check`]: is this host fit for hard timing (`cadence doctor`; the host facts
//!     `cadence bench` prints).
//!   - [`logger`]: the logger thread; other threads push fixed-size records, never block.
//!   - [`shm`]: iceoryx2 services for step batches and telemetry (fixed-size `#[repr(C)]`
//!     payloads, no loss, sequence-checked), and the generic channel settings the `cadence`
//!     library's IO-process services use.
//!   - [`wakeup`]: the machine's timing noise floor (a cyclictest-like sleeper), to judge
//!     measured tails as ratios within one run.
//!
//! The crate is `no_std` unless the `std` feature is on (the firmware core uses it bare).
//! `unsafe` is denied everywhere except the OS layer (`os::sys`, `alloc_count`, and the
//! pooled iceoryx2 service variant `shm::pooled`).
#![cfg_attr(not(feature = "std"), no_std)]

pub mod time;

#[cfg(feature = "std")]
pub mod alloc_count;
#[cfg(feature = "std")]
pub mod handoff;
#[cfg(feature = "std")]
pub mod hist;
#[cfg(feature = "std")]
pub mod host_check;
#[cfg(feature = "std")]
pub mod logger;
#[cfg(feature = "std")]
pub mod os;
#[cfg(feature = "std")]
pub mod shm;
#[cfg(feature = "std")]
pub mod wakeup;

pub use time::{McuClock, PrintTime, SystemTime, WireClock};
