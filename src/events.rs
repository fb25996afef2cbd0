//! What a running printer tells its users: typed [`Event`]s (state changes, homing and probing
//! results, G-code warnings) and the [`Status`] snapshot, plus the state the printer's threads
//! share to publish them ([`SessionShared`]). The planner thread publishes without blocking or
//! allocating: events go through a bounded channel with `try_send` (a full channel drops the
//! event and counts it), the motion status through a sequence lock (it never waits).

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::SyncSender;
use std::sync::Mutex;

use crate::homing::HomingReport;

/// What the printer is doing.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PrinterState {
    /// MCUs connected and configured; no G-code waiting.
    Ready,
    /// Planning and streaming G-code.
    Printing,
    /// Stopped for good: an error, `stop()`, `emergency_stop()` or the end of the session.
    Shutdown { reason: String },
}

/// An event of a running printer.
#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    /// The state changed.
    State(PrinterState),
    /// A G28 homed with motion (per axis: passes, trigger MCU, overshoot, position).
    Homed(HomingReport),
    /// What a probing command reported (`PROBE`, `PROBE_ACCURACY`, `QUERY_PROBE`), one line
    /// each, or a homing command's detail (a communication timeout's cause).
    Response(String),
    /// A warning about the G-code (an unsupported command skipped, heat asked of a real board).
    Warning(String),
}

/// A snapshot of the printer's state.
#[derive(Debug, Clone, PartialEq)]
pub struct Status {
    pub state: PrinterState,
    /// Toolhead position X, Y, Z, E (mm) as planned so far.
    pub position: [f64; 4],
    /// Which of X, Y, Z are homed.
    pub homed: [bool; 3],
    /// Print time (s) up to which moves are planned.
    pub planned_until: f64,
    /// The main MCU's print time now (s).
    pub print_time: f64,
    /// Each MCU's link statistics (bytes, retransmits, round-trip time, lead margin).
    pub mcus: Vec<(String, links::mcu::LinkStats)>,
    /// Events dropped because nobody read them fast enough.
    pub events_dropped: u64,
    /// Each heater (`extruder`, `heater_bed`, `[heater_generic]`s) while a print runs.
    pub heaters: Vec<HeaterStatus>,
    /// Each fan (`fan`, `[heater_fan]`s, `[controller_fan]`s, `[fan_generic]`s,
    /// `[temperature_fan]`s) while a print runs.
    pub fans: Vec<FanStatus>,
    /// Each `[temperature_sensor]` while a print runs.
    pub sensors: Vec<SensorStatus>,
    /// What SAVE_CONFIG would write now (PID_CALIBRATE results…; empty when nothing is
    /// pending): Klipper's `configfile` `save_config_pending` and its items.
    pub save_config_pending: sysconfig::autosave::Changes,
    /// `[bed_mesh]`: the mesh in use and the profiles (`None` without the section).
    pub bed_mesh: Option<BedMeshStatus>,
}

/// Klipper's `bed_mesh` status object.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct BedMeshStatus {
    /// The profile in use ("" when none).
    pub profile_name: String,
    pub mesh_min: [f64; 2],
    pub mesh_max: [f64; 2],
    /// Probed heights, rows of X along Y.
    pub probed_matrix: Vec<Vec<f64>>,
    /// Interpolated heights, rows of X along Y.
    pub mesh_matrix: Vec<Vec<f64>>,
    /// Saved profile names.
    pub profiles: Vec<String>,
}

/// One heater in a [`Status`] (Klipper's `extruder`/`heater_bed` status objects).
#[derive(Debug, Clone, PartialEq)]
pub struct HeaterStatus {
    pub name: String,
    /// Smoothed temperature (°C; NaN before the first reading).
    pub temperature: f64,
    /// Target (°C, 0 = off).
    pub target: f64,
    /// Power applied (0..=max_power).
    pub power: f64,
}

/// One fan in a [`Status`].
#[derive(Debug, Clone, PartialEq)]
pub struct FanStatus {
    pub name: String,
    /// Klipper's object kind: `fan`, `heater_fan`, `controller_fan`, `fan_generic`,
    /// `temperature_fan` (the object is `fan` or `KIND NAME`).
    pub kind: &'static str,
    /// Speed (0..=1).
    pub speed: f64,
    /// A temperature fan's sensor temperature and target (°C), `None` for other fans.
    pub temperature: Option<f64>,
    pub target: Option<f64>,
    /// The tachometer's speed (rev/min), `None` without one.
    pub rpm: Option<f64>,
}

/// One `[temperature_sensor]` in a [`Status`].
#[derive(Debug, Clone, PartialEq)]
pub struct SensorStatus {
    pub name: String,
    /// Smoothed temperature (°C; NaN before the first reading).
    pub temperature: f64,
    /// Lowest and highest temperature seen.
    pub measured_min_temp: f64,
    pub measured_max_temp: f64,
}

/// What the planner thread publishes about the motion (a `Copy` record: no allocation).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct MotionStatus {
    pub position: [f64; 4],
    pub homed: [bool; 3],
    pub planned_until: f64,
    pub busy: bool,
}

/// The latest [`MotionStatus`] behind a sequence lock: one writer (the planner thread) never
/// waits or skips an update; a reader retries while a write is under way. (A `try_lock` that
/// skipped the update when a reader held the lock left the status stale once the printer went
/// idle: a service's query right after a command saw the position before it.)
#[derive(Debug, Default)]
struct MotionCell {
    /// Odd while a write is under way.
    seq: AtomicU64,
    /// x, y, z, e, planned_until (f64 bits), then flags (homed x/y/z, busy).
    words: [AtomicU64; 6],
}

impl MotionCell {
    fn write(&self, m: &MotionStatus) {
        let s = self.seq.load(Ordering::Relaxed);
        self.seq.store(s.wrapping_add(1), Ordering::Relaxed);
        std::sync::atomic::fence(Ordering::Release);
        for (w, v) in self.words.iter().zip(m.position) {
            w.store(v.to_bits(), Ordering::Relaxed);
        }
        self.words[4].store(m.planned_until.to_bits(), Ordering::Relaxed);
        let flags = m
            .homed
            .iter()
            .enumerate()
            .fold(u64::from(m.busy) << 3, |f, (i, h)| f | (u64::from(*h) << i));
        self.words[5].store(flags, Ordering::Relaxed);
        self.seq.store(s.wrapping_add(2), Ordering::Release);
    }

    fn read(&self) -> MotionStatus {
        loop {
            let before = self.seq.load(Ordering::Acquire);
            if !before.is_multiple_of(2) {
                std::hint::spin_loop();
                continue;
            }
            let w: [u64; 6] = std::array::from_fn(|i| self.words[i].load(Ordering::Relaxed));
            std::sync::atomic::fence(Ordering::Acquire);
            if self.seq.load(Ordering::Relaxed) != before {
                continue;
            }
            return MotionStatus {
                position: [0, 1, 2, 3].map(|i| f64::from_bits(w[i])),
                planned_until: f64::from_bits(w[4]),
                homed: [0, 1, 2].map(|i| w[5] >> i & 1 == 1),
                busy: w[5] >> 3 & 1 == 1,
            };
        }
    }
}

/// A flag set once with the reason (the first one wins), read lock-free until it is set.
#[derive(Debug, Default)]
pub(crate) struct Latch {
    set: AtomicBool,
    reason: Mutex<Option<String>>,
}

impl Latch {
    /// Sets the flag; the reason is kept if none was before.
    pub fn set(&self, reason: String) {
        if let Ok(mut r) = self.reason.lock() {
            if r.is_none() {
                *r = Some(reason);
            }
        }
        // Release pairs with the Acquire load in `check`: the reason is written before.
        self.set.store(true, Ordering::Release);
    }

    /// The reason once set (`default` when the reason cannot be read).
    pub fn reason(&self, default: &str) -> Option<String> {
        if !self.set.load(Ordering::Acquire) {
            return None;
        }
        Some(
            self.reason
                .lock()
                .ok()
                .and_then(|r| r.clone())
                .unwrap_or_else(|| default.to_string()),
        )
    }
}

/// State shared between a printer's handle, its session thread and its planner thread.
#[derive(Debug)]
pub(crate) struct SessionShared {
    /// Set by `stop()`/`emergency_stop()`: the planner ends the session at its next check.
    stop: Latch,
    motion: MotionCell,
    /// Set once the session ended, with the reason.
    pub shutdown: Mutex<Option<String>>,
    /// The report of the last G28 with motion (taken by `Printer::home`).
    pub last_homing: Mutex<Option<HomingReport>>,
    events: Mutex<Option<SyncSender<Event>>>,
    events_dropped: AtomicU64,
    /// The heater loop's state, once the session's print started it.
    pub heaters: std::sync::OnceLock<std::sync::Arc<crate::heaters::runtime::HeaterShared>>,
    /// Set by the print's owner to end a wait in progress (see `LiveOptions::interrupt`).
    interrupt: Option<std::sync::Arc<AtomicBool>>,
    /// The planner's pending SAVE_CONFIG changes, as last published.
    save_pending: Mutex<sysconfig::autosave::Changes>,
}

impl SessionShared {
    pub fn new(events: Option<SyncSender<Event>>) -> SessionShared {
        SessionShared {
            stop: Latch::default(),
            motion: MotionCell::default(),
            shutdown: Mutex::new(None),
            last_homing: Mutex::new(None),
            events: Mutex::new(events),
            events_dropped: AtomicU64::new(0),
            heaters: std::sync::OnceLock::new(),
            interrupt: None,
            save_pending: Mutex::new(sysconfig::autosave::Changes::default()),
        }
    }

    /// Publishes the pending SAVE_CONFIG changes (the planner, after each change).
    pub fn publish_save_pending(&self, changes: &sysconfig::autosave::Changes) {
        if let Ok(mut p) = self.save_pending.lock() {
            p.clone_from(changes);
        }
    }

    /// The pending SAVE_CONFIG changes last published.
    pub fn save_pending(&self) -> sysconfig::autosave::Changes {
        self.save_pending.lock().map(|p| p.clone()).unwrap_or_default()
    }

    /// With `interrupt`: once it is set, waits end (see [`SessionShared::interrupted`]).
    pub fn with_interrupt(mut self, interrupt: Option<std::sync::Arc<AtomicBool>>) -> SessionShared {
        self.interrupt = interrupt;
        self
    }

    /// True once the print's owner asked a wait in progress to end.
    pub fn interrupted(&self) -> bool {
        self.interrupt.as_ref().is_some_and(|i| i.load(Ordering::Acquire))
    }

    /// The heaters', fans' and temperature sensors' status (empty before the print started its
    /// heater loop).
    pub fn heater_status(&self) -> (Vec<HeaterStatus>, Vec<FanStatus>, Vec<SensorStatus>) {
        let Some(h) = self.heaters.get() else {
            return (Vec::new(), Vec::new(), Vec::new());
        };
        (
            h.heaters
                .iter()
                .map(|c| HeaterStatus {
                    name: c.name.clone(),
                    temperature: c.temp.get(),
                    target: c.target.get(),
                    power: c.power.get(),
                })
                .collect(),
            h.fans
                .iter()
                .map(|f| {
                    let sensor = f.sensor.and_then(|i| h.sensors.get(i));
                    FanStatus {
                        name: f.name.clone(),
                        kind: f.kind,
                        speed: f.speed.get(),
                        temperature: sensor.map(|s| s.temp.get()),
                        target: sensor.map(|_| f.target.get()),
                        rpm: Some(f.rpm.get()).filter(|r| !r.is_nan()),
                    }
                })
                .collect(),
            h.sensors
                .iter()
                .filter(|s| s.kind == "temperature_sensor")
                .map(|s| SensorStatus {
                    name: s.name.clone(),
                    temperature: s.temp.get(),
                    measured_min_temp: s.min_seen.get(),
                    measured_max_temp: s.max_seen.get(),
                })
                .collect(),
        )
    }

    /// Publishes an event without blocking: dropped (and counted) when the channel is full,
    /// the lock is held elsewhere or nobody listens.
    pub fn emit(&self, event: Event) {
        let sent = match self.events.try_lock() {
            Ok(guard) => match guard.as_ref() {
                Some(tx) => tx.try_send(event).is_ok(),
                None => return,
            },
            Err(_) => false,
        };
        if !sent {
            self.events_dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// True when someone takes the events (a printer session; a plain print has none).
    pub fn listening(&self) -> bool {
        self.events.lock().is_ok_and(|e| e.is_some())
    }

    pub fn events_dropped(&self) -> u64 {
        self.events_dropped.load(Ordering::Relaxed)
    }

    /// Asks the planner to stop, with the reason it reports.
    pub fn request_stop(&self, reason: &str) {
        self.stop.set(reason.to_string());
    }

    /// The reason once a stop was requested.
    pub fn stop_reason(&self) -> Option<String> {
        self.stop.reason("stopped by the host")
    }

    /// Updates the motion record (lock-free: readers retry, the planner never waits).
    pub fn publish_motion(&self, m: MotionStatus) {
        self.motion.write(&m);
    }

    pub fn motion(&self) -> MotionStatus {
        self.motion.read()
    }

    /// Records the end of the session (the first reason wins) and tells the listeners.
    pub fn set_shutdown(&self, reason: String) {
        if let Ok(mut s) = self.shutdown.lock() {
            if s.is_none() {
                *s = Some(reason.clone());
                self.emit(Event::State(PrinterState::Shutdown { reason }));
            }
        }
    }

    pub fn shutdown_reason(&self) -> Option<String> {
        self.shutdown.lock().ok().and_then(|s| s.clone())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_motion_cell_reads_what_was_written_whole() {
        let cell = std::sync::Arc::new(MotionCell::default());
        assert_eq!(cell.read(), MotionStatus::default());
        let writer = {
            let cell = std::sync::Arc::clone(&cell);
            std::thread::spawn(move || {
                for k in 1..=20_000u32 {
                    let v = f64::from(k);
                    cell.write(&MotionStatus {
                        position: [v, v, v, v],
                        homed: [k.is_multiple_of(2); 3],
                        planned_until: v,
                        busy: k.is_multiple_of(2),
                    });
                }
            })
        };
        for _ in 0..20_000 {
            let m = cell.read();
            // A torn read would mix two writes.
            assert!(m.position.iter().all(|p| *p == m.planned_until), "{m:?}");
            if m == MotionStatus::default() {
                continue; // before the first write
            }
            let even = (m.planned_until as u32).is_multiple_of(2);
            assert_eq!(m.homed, [even; 3], "{m:?}");
            assert_eq!(m.busy, even, "{m:?}");
        }
        writer.join().expect("writer");
        assert_eq!(cell.read().planned_until, 20_000.0);
    }
}
