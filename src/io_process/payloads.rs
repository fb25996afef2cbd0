//! The payloads and services between a planner process and an IO-stage process
//! (`cadence serve --role io`), on rt-core's generic shared-memory channels:
//! everything besides the step batches that must cross so the MCU connections can live in the
//! IO process while the planner compresses steps in MCU clock ticks.
//!
//! # Services (besides `cadence/<instance>/mcu/<mcu>/steps`)
//!
//! | service name | direction | payload | config |
//! |---|---|---|---|
//! | `cadence/<instance>/mcu/<mcu>/info` | IO → planner, once per MCU | [`McuInfo`] | `ChannelConfig::info` |
//! | `cadence/<instance>/mcu/<mcu>/clock` | IO → planner, ~every 20 ms | [`ClockSnapshot`] | `ChannelConfig::latest` |
//! | `cadence/<instance>/io/status` | IO → planner, on each change | [`IoStatus`] | `ChannelConfig::latest` |
//! | `cadence/<instance>/io/control` | planner → IO | [`IoControl`] | `ChannelConfig::control` |
//!
//! Each has an event service of the same name beside it (the publisher notifies after a send).
//! `info`, `clock` and `status` keep a history of one sample, so a planner that attaches after
//! the IO process published still gets them; their readers take the newest sample
//! (`rt_core::shm::ShmSubscriber::latest`). `control` is lossless like the step channels.
//!
//! # Handshake
//!
//! 1. The IO process connects and configures its MCUs (it loaded the same printer.cfg), then
//!    publishes each MCU's [`McuInfo`] (its data dictionary, `CLOCK_FREQ`, move queue size and
//!    the CRC-32 of the configuration it sent, which the planner recomputes from its own config
//!    to prove both processes mean the same oids and pins), starts publishing
//!    [`ClockSnapshot`]s, subscribes to the step and control channels, and publishes
//!    [`IoStatus`] `READY`.
//! 2. The planner waits for `READY`, reads the info, plans against the clock snapshots
//!    (print time ↔ MCU clock) and publishes step batches.
//! 3. After the last batch the planner sends [`IoControl`] `FINISH` with the number of batches
//!    and the last step clock; the IO process takes every batch, waits until the MCU executed
//!    the last step, reads the stepper positions back and publishes `DONE` with them (or
//!    `FAILED` with a message at any point); the planner answers `DONE_SEEN` and the IO process
//!    exits. `ABORT` stops the IO process early.
//!
//! # Payload layouts (`#[repr(C)]`, native endian, sizes asserted in tests)
//!
//! - [`McuInfo`] (32 + [`DICT_MAX`] bytes, align 8): `seq: u64` @0, `clock_freq: f64` @8,
//!   `move_count: u32` @16, `config_crc: u32` @20, `dict_len: u32` @24, `mcu_index: u32` @28,
//!   `dict: [u8; 65536]` @32 (the zlib-compressed data dictionary as served by `identify`).
//! - [`ClockSnapshot`] (48 bytes): `seq: u64` @0, `ref_time: f64` @8 (CLOCK_MONOTONIC s),
//!   `ref_clock: f64` @16, `freq: f64` @24 (MCU ticks per second), `residual_us: f64` @32,
//!   `valid: u32` @40, 4 bytes padding. `clock(t) = ref_clock + (t − ref_time)·freq`.
//! - [`IoControl`] (32 bytes): `seq: u64` @0, `kind: u32` @8, `mcu_index: u32` @12,
//!   `batches: u64` @16, `end_clock: u64` @24.
//! - [`IoStatus`] (304 + [`STATUS_MSG`] = 560 bytes, align 8): `seq: u64` @0, `state: u32` @8,
//!   `npos: u32` @12, `batches: u64` @16, `clocked_msgs: u64` @24,
//!   `min_lead_margin_ticks: i64` @32 (`i64::MIN` = none), `positions: [i64; 32]` @40 (the main
//!   MCU's stepper positions by oid, valid in `DONE`), `msg_len: u32` @296, `pid: u32` @300,
//!   `msg: [u8; 256]` @304 (UTF-8, the error in `FAILED`).

use iceoryx2::prelude::*;

#[cfg(test)]
use rt_core::shm::ChannelConfig;
use rt_core::shm::Sequenced;

/// Largest compressed data dictionary an [`McuInfo`] carries.
pub const DICT_MAX: usize = 65536;
/// Stepper positions in an [`IoStatus`].
pub const STATUS_POSITIONS: usize = 32;
/// Message bytes in an [`IoStatus`].
pub const STATUS_MSG: usize = 256;

/// `cadence/<instance>/mcu/<mcu>/info`.
pub fn info_service_name(instance: &str, mcu: &str) -> String {
    format!("cadence/{instance}/mcu/{mcu}/info")
}

/// `cadence/<instance>/mcu/<mcu>/clock`.
pub fn clock_service_name(instance: &str, mcu: &str) -> String {
    format!("cadence/{instance}/mcu/{mcu}/clock")
}

/// `cadence/<instance>/io/status`.
pub fn status_service_name(instance: &str) -> String {
    format!("cadence/{instance}/io/status")
}

/// `cadence/<instance>/io/control`.
pub fn control_service_name(instance: &str) -> String {
    format!("cadence/{instance}/io/control")
}

/// What the IO process tells the planner about one MCU.
#[repr(C)]
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[type_name("cadence::McuInfo.v1")]
pub struct McuInfo {
    pub seq: u64,
    /// The dictionary's nominal `CLOCK_FREQ` (print time → ticks).
    pub clock_freq: f64,
    /// Entries of the MCU's move queue (from its `config` answer).
    pub move_count: u32,
    /// CRC-32 of the configuration commands the IO process sent (the `finalize_config` value).
    pub config_crc: u32,
    /// Valid bytes in `dict`.
    pub dict_len: u32,
    /// The MCU's index in the printer config (0 = the main `[mcu]`).
    pub mcu_index: u32,
    /// The zlib-compressed data dictionary.
    pub dict: [u8; DICT_MAX],
}

impl Default for McuInfo {
    fn default() -> Self {
        McuInfo {
            seq: 0,
            clock_freq: 0.0,
            move_count: 0,
            config_crc: 0,
            dict_len: 0,
            mcu_index: 0,
            dict: [0; DICT_MAX],
        }
    }
}

impl McuInfo {
    /// Copies `dict` in; `false` if it does not fit.
    pub fn set_dict(&mut self, dict: &[u8]) -> bool {
        match self.dict.get_mut(..dict.len()) {
            Some(dst) => {
                dst.copy_from_slice(dict);
                self.dict_len = dict.len() as u32;
                true
            }
            None => false,
        }
    }

    /// The valid dictionary bytes (empty if `dict_len` is corrupt).
    pub fn dict(&self) -> &[u8] {
        self.dict.get(..self.dict_len as usize).unwrap_or(&[])
    }
}

/// One MCU's clock fit: `clock(t) = ref_clock + (t − ref_time)·freq`, `t` in seconds of the
/// host's CLOCK_MONOTONIC (the same clock in every process of the host).
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("cadence::ClockSnapshot.v1")]
pub struct ClockSnapshot {
    pub seq: u64,
    pub ref_time: f64,
    pub ref_clock: f64,
    pub freq: f64,
    pub residual_us: f64,
    /// 1 once the fit has a frequency.
    pub valid: u32,
}

/// What an [`IoControl`] asks.
pub mod control_kind {
    /// Every batch is published: take `batches` batches, wait for `end_clock`, report `DONE`.
    pub const FINISH: u32 = 1;
    /// The planner failed: stop at once.
    pub const ABORT: u32 = 2;
    /// The planner read the final status (the IO process may exit).
    pub const DONE_SEEN: u32 = 3;
}

/// A planner → IO command.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend)]
#[type_name("cadence::IoControl.v1")]
pub struct IoControl {
    pub seq: u64,
    /// One of [`control_kind`].
    pub kind: u32,
    pub mcu_index: u32,
    /// Step batches published on the MCU's steps channel (sequence numbers 0..batches).
    pub batches: u64,
    /// Clock of the last step sent.
    pub end_clock: u64,
}

/// States of an [`IoStatus`].
pub mod io_state {
    /// Connecting to the MCUs.
    pub const STARTING: u32 = 0;
    /// MCUs configured, info and clocks published, step channels subscribed.
    pub const READY: u32 = 1;
    /// The print is executed; `positions` hold the MCU's stepper positions.
    pub const DONE: u32 = 2;
    /// Something failed; `msg` says what.
    pub const FAILED: u32 = 3;
}

/// The IO process's state.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("cadence::IoStatus.v1")]
pub struct IoStatus {
    pub seq: u64,
    /// One of [`io_state`].
    pub state: u32,
    /// Valid entries in `positions`.
    pub npos: u32,
    /// Step batches taken so far (main MCU).
    pub batches: u64,
    /// Clocked messages written to the main MCU.
    pub clocked_msgs: u64,
    /// Smallest lead margin of a step message (MCU ticks); `i64::MIN` before the first.
    pub min_lead_margin_ticks: i64,
    /// The main MCU's stepper positions by oid (MCU sign convention), in `DONE`.
    pub positions: [i64; STATUS_POSITIONS],
    /// Valid bytes in `msg`.
    pub msg_len: u32,
    /// The IO process's pid.
    pub pid: u32,
    /// UTF-8 text: the error in `FAILED`.
    pub msg: [u8; STATUS_MSG],
}

impl Default for IoStatus {
    fn default() -> Self {
        IoStatus {
            seq: 0,
            state: io_state::STARTING,
            npos: 0,
            batches: 0,
            clocked_msgs: 0,
            min_lead_margin_ticks: i64::MIN,
            positions: [0; STATUS_POSITIONS],
            msg_len: 0,
            pid: 0,
            msg: [0; STATUS_MSG],
        }
    }
}

impl IoStatus {
    /// Sets the message, cut at [`STATUS_MSG`] bytes (on a character boundary).
    pub fn set_msg(&mut self, text: &str) {
        let mut n = text.len().min(STATUS_MSG);
        while !text.is_char_boundary(n) {
            n -= 1;
        }
        self.msg[..n].copy_from_slice(&text.as_bytes()[..n]);
        self.msg_len = n as u32;
    }

    /// The message (lossy UTF-8; empty if `msg_len` is corrupt).
    pub fn msg(&self) -> String {
        String::from_utf8_lossy(self.msg.get(..self.msg_len as usize).unwrap_or(&[])).into_owned()
    }

    /// The valid positions (clamped if `npos` is corrupt).
    pub fn positions(&self) -> &[i64] {
        &self.positions[..(self.npos as usize).min(STATUS_POSITIONS)]
    }
}

macro_rules! sequenced {
    ($($t:ty),*) => {$(
        impl Sequenced for $t {
            fn seq(&self) -> u64 {
                self.seq
            }
            fn set_seq(&mut self, seq: u64) {
                self.seq = seq;
            }
        }
    )*};
}

sequenced!(McuInfo, ClockSnapshot, IoControl, IoStatus);

#[cfg(test)]
mod tests {
    use super::*;
    use rt_core::shm::{open_node, ShmPublisher, ShmSubscriber};
    use std::mem::{align_of, offset_of, size_of};
    use std::time::{Duration, Instant};

    #[test]
    fn layouts() {
        assert_eq!((size_of::<McuInfo>(), align_of::<McuInfo>()), (32 + DICT_MAX, 8));
        assert_eq!(offset_of!(McuInfo, dict), 32);
        assert_eq!(size_of::<ClockSnapshot>(), 48);
        assert_eq!(offset_of!(ClockSnapshot, valid), 40);
        assert_eq!(size_of::<IoControl>(), 32);
        assert_eq!(offset_of!(IoControl, end_clock), 24);
        assert_eq!(offset_of!(IoStatus, positions), 40);
        assert_eq!(offset_of!(IoStatus, msg_len), 296);
        assert_eq!(offset_of!(IoStatus, pid), 300);
        assert_eq!(offset_of!(IoStatus, msg), 304);
        assert_eq!(size_of::<IoStatus>(), 304 + STATUS_MSG);
    }

    #[test]
    fn status_message_is_cut_on_a_char_boundary() {
        let mut s = IoStatus::default();
        let long = "é".repeat(STATUS_MSG);
        s.set_msg(&long);
        assert!(s.msg_len as usize <= STATUS_MSG);
        assert!(s.msg().chars().all(|c| c == 'é'));
        s.msg_len = u32::MAX;
        assert_eq!(s.msg(), "");
        s.npos = u32::MAX;
        assert_eq!(s.positions().len(), STATUS_POSITIONS);
        let mut info = McuInfo::default();
        assert!(!info.set_dict(&vec![0; DICT_MAX + 1]));
        assert!(info.set_dict(&[1, 2, 3]));
        assert_eq!(info.dict(), &[1, 2, 3]);
    }

    #[test]
    fn late_subscriber_gets_the_newest_sample() {
        let instance = format!("test-{}-latest", std::process::id());
        let name = clock_service_name(&instance, "mcu");
        let (node, _) = open_node::<ipc::Service>("latest").unwrap();
        let mut p = ShmPublisher::<ipc::Service, ClockSnapshot>::open(&node, &name, &ChannelConfig::latest())
            .unwrap();
        for i in 0..20 {
            p.send_with(|c| c.ref_clock = i as f64).unwrap();
        }
        let mut s =
            ShmSubscriber::<ipc::Service, ClockSnapshot>::open(&node, &name, &ChannelConfig::latest())
                .unwrap()
                .accept_any_start();
        // History is delivered when the publisher next updates its connections.
        let start = Instant::now();
        let mut got = None;
        while got.is_none() && start.elapsed() < Duration::from_secs(30) {
            p.connect().unwrap();
            got = s.latest().unwrap();
            std::thread::sleep(Duration::from_millis(1));
        }
        assert_eq!(got.map(|c| c.ref_clock), Some(19.0));
        p.send_with(|c| c.ref_clock = 20.0).unwrap();
        p.send_with(|c| c.ref_clock = 21.0).unwrap();
        assert_eq!(s.latest().unwrap().map(|c| c.ref_clock), Some(21.0));
        assert_eq!(s.latest().unwrap(), None);
    }
}
