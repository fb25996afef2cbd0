//! The simulated printer's world: axis positions shared by every `cadence-mcu` process of one
//! printer, so an endstop on one MCU sees a stepper on another.
//!
//! Model: `--axis AXIS=STEP_PIN,STEPS_PER_MM,START_MM` makes the stepper configured with that
//! step pin drive axis AXIS: `position_mm = START_MM + net_steps / STEPS_PER_MM` (dir = 1 is +).
//! `--endstop PIN=COORD,TRIGGER_MM,min|max` makes input PIN read 1 while the coordinate is at or
//! below (`min`) / at or above (`max`) TRIGGER_MM. A coordinate ([`Coord`]) is one axis (`x`) or
//! a linear combination of axes (`0.5*a+0.5*b`): on a corexy printer the steppers A and B drive
//! axes `a` and `b` and the X endstop reads x = (a + b) / 2, the Y endstop y = (a − b) / 2. A
//! coordinate naming an axis nobody drives cannot be read: its endstop reads 0.
//!
//! Sharing (with `--world ID`): iceoryx2 publish-subscribe on the service `cadence/world/ID`.
//! Each process publishes a fixed-size [`WorldUpdate`] (its pid, a sequence number and up to
//! [`MAX_AXES`] `(name, position, stamp)` triples of the axes it drives, the stamp being the due
//! time of the axis' last step in CLOCK_MONOTONIC ns) after a step due at least
//! [`PUBLISH_PERIOD`] after the last one published, plus a final flush whenever the event loop
//! goes idle; every process drains its subscriber before reading an endstop pin and keeps the
//! last [`HISTORY`] samples per axis name.
//!
//! Time: an endstop sample due at clock `c` reads the other processes' axes as they were at
//! `c` (the latest sample stamped at or before it), not as they are when its timer runs: a
//! simulator process runs late now and then (by milliseconds on a busy VM), and a real MCU,
//! which samples on time, would otherwise be modelled as reporting a trigger clock earlier
//! than the position it read. The processes agree on time because each MCU clock counts
//! CLOCK_MONOTONIC from its own start ([`TimeBase`]). A process catching up after a stall
//! publishes every step (their due times are far apart), so the history has no gaps wider
//! than [`PUBLISH_PERIOD`] of motion.
//!
//! Safe overflow is on (a slow reader loses the oldest samples) and the history is 1, so a
//! process that joins late sees the current positions. Stale resources of dead processes are
//! removed at start.

use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use std::collections::{HashMap, VecDeque};
use std::time::{Duration, Instant};

/// Axes per update (per process).
pub const MAX_AXES: usize = 8;
/// Bytes of an axis name.
pub const NAME_LEN: usize = 8;
/// Shortest wall time between two publications while stepping.
pub const PUBLISH_PERIOD: Duration = Duration::from_micros(20);

/// One axis position on the wire.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
pub struct AxisSample {
    /// Axis name, NUL padded.
    pub name: [u8; NAME_LEN],
    /// Position in mm.
    pub position_mm: f64,
    /// When the axis got there: the due time of its last step, CLOCK_MONOTONIC ns (0: unknown,
    /// the position holds at any time).
    pub stamp_ns: u64,
}

/// The payload: the axes one process drives.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
pub struct WorldUpdate {
    /// The publishing [`World`]: process id << 32 | instance number within the process.
    pub source: u64,
    /// Increases with every publication of this source.
    pub seq: u64,
    /// Valid entries of `axes`.
    pub count: u32,
    /// Padding (0).
    pub reserved: u32,
    /// The axes.
    pub axes: [AxisSample; MAX_AXES],
}

/// `--axis`: a stepper (by step pin) driving a named axis.
#[derive(Debug, Clone, PartialEq)]
pub struct AxisSpec {
    /// Axis name (≤ 8 bytes).
    pub name: String,
    /// Step pin number.
    pub step_pin: u8,
    /// Steps per mm (non-zero).
    pub steps_per_mm: f64,
    /// Position at start.
    pub start_mm: f64,
}

/// Terms of a [`Coord`] at most.
pub const MAX_TERMS: usize = 8;

/// A world coordinate: Σ coefficient · axis position over named axes.
///
/// Text form (`--endstop`): `TERM (('+' | '-') TERM)*` with `TERM = [COEF '*'] NAME`, an optional
/// sign before the first term; `COEF` a finite number (`2e-1` is one number), `NAME` 1 to
/// [`NAME_LEN`] bytes that start with a letter or `_` and hold none of `+ - * , =` or
/// whitespace. [`Coord::parse`] reads it, `Display` writes it (and `parse` reads that back to
/// the same value).
#[derive(Debug, Clone, PartialEq)]
pub struct Coord {
    /// (coefficient, axis name); at least one, at most [`MAX_TERMS`].
    pub terms: Vec<(f64, String)>,
}

/// Why a coordinate's text was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CoordError {
    #[error("coordinate `{0}` is empty")]
    Empty(String),
    #[error("coordinate `{text}`: term `{term}` is empty")]
    EmptyTerm { text: String, term: String },
    #[error("coordinate `{text}`: coefficient `{coef}` is not a finite number")]
    Coefficient { text: String, coef: String },
    #[error(
        "coordinate `{text}`: axis name `{name}` must have 1 to 8 bytes, start with a letter or `_` \
         and hold no `+ - * , =` or whitespace"
    )]
    Name { text: String, name: String },
    #[error("coordinate `{text}` has more than {max} terms", max = MAX_TERMS)]
    TooManyTerms { text: String },
}

impl Coord {
    /// The coordinate of one axis (coefficient 1).
    pub fn axis(name: &str) -> Coord {
        Coord {
            terms: vec![(1.0, name.to_owned())],
        }
    }

    /// Parses the text form (see [`Coord`]). Never panics.
    pub fn parse(text: &str) -> Result<Coord, CoordError> {
        let t = text.trim();
        if t.is_empty() {
            return Err(CoordError::Empty(text.to_owned()));
        }
        // Split before every sign that is not a number's exponent sign (`2e-1*a`).
        let mut raw: Vec<&str> = Vec::new();
        let mut start = 0;
        for (i, c) in t.char_indices() {
            if i == 0 || !(c == '+' || c == '-') {
                continue;
            }
            let term = t[start..i].trim_start_matches(['+', '-']).trim();
            let exponent = !term.contains('*')
                && term.starts_with(|d: char| d.is_ascii_digit() || d == '.')
                && term.ends_with(['e', 'E']);
            if !exponent {
                raw.push(&t[start..i]);
                start = i;
            }
        }
        raw.push(&t[start..]);
        if raw.len() > MAX_TERMS {
            return Err(CoordError::TooManyTerms {
                text: text.to_owned(),
            });
        }
        let mut terms = Vec::with_capacity(raw.len());
        for term in raw {
            let term = term.trim();
            let (sign, body) = match term.as_bytes().first() {
                Some(b'-') => (-1.0, &term[1..]),
                Some(b'+') => (1.0, &term[1..]),
                _ => (1.0, term),
            };
            let body = body.trim();
            if body.is_empty() {
                return Err(CoordError::EmptyTerm {
                    text: text.to_owned(),
                    term: term.to_owned(),
                });
            }
            let (coef, name) = match body.split_once('*') {
                Some((c, n)) => {
                    let coef = c
                        .trim()
                        .parse::<f64>()
                        .ok()
                        .filter(|v| v.is_finite())
                        .ok_or_else(|| CoordError::Coefficient {
                            text: text.to_owned(),
                            coef: c.trim().to_owned(),
                        })?;
                    (coef, n.trim())
                }
                None => (1.0, body),
            };
            let valid = (1..=NAME_LEN).contains(&name.len())
                && name.starts_with(|c: char| c.is_ascii_alphabetic() || c == '_')
                && !name.contains(|c: char| "+-*,=".contains(c) || c.is_whitespace());
            if !valid {
                return Err(CoordError::Name {
                    text: text.to_owned(),
                    name: name.to_owned(),
                });
            }
            terms.push((sign * coef, name.to_owned()));
        }
        Ok(Coord { terms })
    }
}

impl std::fmt::Display for Coord {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        for (i, (coef, name)) in self.terms.iter().enumerate() {
            if coef.is_sign_negative() {
                f.write_str("-")?;
            } else if i > 0 {
                f.write_str("+")?;
            }
            // `{}` of an f64 is its shortest exact decimal, never an exponent.
            if coef.abs() == 1.0 {
                f.write_str(name)?;
            } else {
                write!(f, "{}*{name}", coef.abs())?;
            }
        }
        Ok(())
    }
}

/// `--endstop`: an input pin driven by a world coordinate.
#[derive(Debug, Clone, PartialEq)]
pub struct EndstopSpec {
    /// Input pin number.
    pub pin: u8,
    /// The coordinate it reads.
    pub axis: Coord,
    /// Trigger coordinate.
    pub trigger_mm: f64,
    /// true: triggered at or below `trigger_mm`; false: at or above.
    pub at_min: bool,
    /// The pin reads 0 when triggered (a printer.cfg `!` endstop, wired normally closed);
    /// otherwise 1.
    pub active_low: bool,
}

/// Why the world could not be joined.
#[derive(Debug, thiserror::Error)]
#[error("world {world}: {what}: {detail}")]
pub struct WorldError {
    world: String,
    what: &'static str,
    detail: String,
}

struct Bus {
    _node: Node<ipc::Service>,
    publisher: Publisher<ipc::Service, WorldUpdate, ()>,
    subscriber: Subscriber<ipc::Service, WorldUpdate, ()>,
}

impl std::fmt::Debug for Bus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Bus(iceoryx2)")
    }
}

#[derive(Debug, Clone)]
struct LocalAxis {
    spec: AxisSpec,
    net_steps: i64,
    /// Due time of the last step (CLOCK_MONOTONIC ns; 0 before the first or without a time
    /// base).
    stamp_ns: u64,
}

/// Samples of a remote axis kept for reading it at a past time.
pub const HISTORY: usize = 512;

/// A remote axis' recent positions, oldest first, stamps non-decreasing.
#[derive(Debug, Clone, Default)]
struct AxisHistory {
    samples: VecDeque<(u64, f64)>,
}

impl AxisHistory {
    fn push(&mut self, stamp_ns: u64, position_mm: f64) {
        if self.samples.back().is_some_and(|&(t, _)| t > stamp_ns) {
            // Out of order (a restarted publisher): start over.
            self.samples.clear();
        }
        if self.samples.len() == HISTORY {
            self.samples.pop_front();
        }
        self.samples.push_back((stamp_ns, position_mm));
    }

    /// The position at `at_ns`: the latest sample stamped at or before it (the oldest kept if
    /// none is that old; the latest if `at_ns` is `None`).
    fn at(&self, at_ns: Option<u64>) -> Option<f64> {
        let Some(at) = at_ns else {
            return self.samples.back().map(|&(_, p)| p);
        };
        let k = self.samples.partition_point(|&(t, _)| t <= at);
        self.samples.get(k.saturating_sub(1)).map(|&(_, p)| p)
    }
}

/// MCU clock → CLOCK_MONOTONIC ns, for the stamps every process of a world shares.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TimeBase {
    /// CLOCK_MONOTONIC ns at tick 0.
    pub start_ns: f64,
    /// Ticks per ns (clock_freq × time_scale / 1e9).
    pub ticks_per_ns: f64,
}

impl TimeBase {
    fn ns(&self, clock: u64) -> u64 {
        let ns = self.start_ns + clock as f64 / self.ticks_per_ns;
        if ns.is_finite() && ns >= 0.0 {
            ns as u64
        } else {
            0
        }
    }
}

/// Axis positions of this process and of the others in the world.
#[derive(Debug)]
pub struct World {
    local: Vec<LocalAxis>,
    /// Stepper oid → index in `local`.
    by_oid: HashMap<u8, usize>,
    endstops: Vec<EndstopSpec>,
    remote: HashMap<[u8; NAME_LEN], AxisHistory>,
    bus: Option<Bus>,
    source: u64,
    seq: u64,
    dirty: bool,
    last_publish: Option<Instant>,
    /// The latest step stamp published.
    last_published_stamp: u64,
    time: Option<TimeBase>,
    /// Bed surfaces under probe pins (`--bed-surface`).
    surfaces: Vec<super::surface::SurfaceSpec>,
    /// Probe pins riding multi-motor gantries (`--gantry`).
    gantries: Vec<super::surface::GantrySpec>,
    /// Values this process publishes besides its axes (a heater's temperature read by
    /// another MCU's sensor), by name; they hold at any time (stamp 0).
    values: Vec<([u8; NAME_LEN], f64)>,
}

/// Worlds created in this process so far (tells two worlds of one process apart).
static INSTANCES: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);

fn name_bytes(name: &str) -> [u8; NAME_LEN] {
    let mut b = [0u8; NAME_LEN];
    for (d, s) in b.iter_mut().zip(name.bytes()) {
        *d = s;
    }
    b
}

impl World {
    /// A world of `axes` and `endstops`, shared through iceoryx2 if `world` is given.
    pub fn new(
        world: Option<&str>,
        axes: Vec<AxisSpec>,
        endstops: Vec<EndstopSpec>,
    ) -> Result<World, WorldError> {
        let bus = world.map(open_bus).transpose()?;
        Ok(World {
            bus,
            ..World::local(axes, endstops)
        })
    }

    /// A world of this process only (nothing shared).
    pub fn local(axes: Vec<AxisSpec>, endstops: Vec<EndstopSpec>) -> World {
        World {
            local: axes
                .into_iter()
                .map(|spec| LocalAxis {
                    spec,
                    net_steps: 0,
                    stamp_ns: 0,
                })
                .collect(),
            by_oid: HashMap::new(),
            endstops,
            remote: HashMap::new(),
            bus: None,
            source: (std::process::id() as u64) << 32
                | INSTANCES.fetch_add(1, std::sync::atomic::Ordering::Relaxed) as u64,
            seq: 0,
            dirty: true,
            last_publish: None,
            last_published_stamp: 0,
            time: None,
            surfaces: Vec::new(),
            gantries: Vec::new(),
            values: Vec::new(),
        }
    }

    /// Sets value `name` (published with the axes, read by other processes as an axis).
    pub fn set_value(&mut self, name: &str, value: f64) {
        let key = name_bytes(name);
        match self.values.iter_mut().find(|(n, _)| *n == key) {
            Some((_, v)) if *v == value => return,
            Some((_, v)) => *v = value,
            None => self.values.push((key, value)),
        }
        self.dirty = true;
    }

    /// Probe pins riding gantries lifted by several Z motors ([`super::surface::GantrySpec`]).
    pub fn set_gantries(&mut self, gantries: Vec<super::surface::GantrySpec>) {
        self.gantries = gantries;
    }

    /// The height of probe input `pin` at `at_ns`: the gantry's under the probe when the pin
    /// rides one, else coordinate `c`.
    fn probe_height(&self, pin: u8, c: &Coord, at_ns: Option<u64>) -> Option<f64> {
        let Some(g) = self.gantries.iter().find(|g| g.pin == pin) else {
            return self.coord_at(c, at_ns);
        };
        let x = self.coord_at(&g.x, at_ns)? + g.offset[0];
        let y = self.coord_at(&g.y, at_ns)? + g.offset[1];
        let z: Option<Vec<f64>> = g
            .motors
            .iter()
            .map(|(axis, _)| self.position_at(axis, at_ns))
            .collect();
        g.height(x, y, &z?)
    }

    /// [`Self::probe_height`] at MCU clock `clock` (refreshes remote positions first).
    pub fn probe_height_at_clock(&mut self, pin: u8, c: &Coord, clock: u64) -> Option<f64> {
        self.refresh();
        let at = self.time.map(|t| t.ns(clock));
        self.probe_height(pin, c, at)
    }

    /// Probe pins touching a tilted or warped bed ([`super::surface`]).
    pub fn set_surfaces(&mut self, surfaces: Vec<super::surface::SurfaceSpec>) {
        self.surfaces = surfaces;
    }

    /// The bed surface's height under probe input `pin` at `at_ns` (0 when the pin has no
    /// surface or the toolhead's X or Y is unknown).
    fn surface_at(&self, pin: u8, at_ns: Option<u64>) -> f64 {
        let Some(s) = self.surfaces.iter().find(|s| s.pin == pin) else {
            return 0.0;
        };
        match (self.coord_at(&s.x, at_ns), self.coord_at(&s.y, at_ns)) {
            (Some(x), Some(y)) => s.under_probe(x, y),
            _ => 0.0,
        }
    }

    /// The surface height under probe input `pin` at MCU clock `clock` (see
    /// [`Self::coord_at_clock`]).
    pub fn surface_at_clock(&mut self, pin: u8, clock: u64) -> f64 {
        self.refresh();
        let at = self.time.map(|t| t.ns(clock));
        self.surface_at(pin, at)
    }

    /// Stamps steps and reads endstops in CLOCK_MONOTONIC time through `time` (this process'
    /// MCU clock): an endstop sample then reads the other processes' axes as they were at its
    /// due time, however late its timer runs (without it: as they are now).
    pub fn set_time_base(&mut self, time: TimeBase) {
        if time.ticks_per_ns.is_finite() && time.ticks_per_ns > 0.0 && time.start_ns.is_finite() {
            self.time = Some(time);
        }
    }

    /// True if nothing is simulated (no axes, no endstops, no world).
    pub fn is_empty(&self) -> bool {
        self.local.is_empty() && self.endstops.is_empty() && self.bus.is_none()
    }

    /// `config_stepper oid step_pin`: attach the stepper to the axis with that step pin.
    pub fn config_stepper(&mut self, oid: u8, step_pin: u8) {
        if let Some(i) = self.local.iter().position(|a| a.spec.step_pin == step_pin) {
            self.by_oid.insert(oid, i);
        }
    }

    /// Stepper `oid` stepped, due at MCU clock `clock`; publishes when the step is due
    /// [`PUBLISH_PERIOD`] after the last one published (a late process catching up publishes
    /// every step, so readers can look back in time), or, without a time base, when that much
    /// wall time has passed.
    pub fn step(&mut self, oid: u8, dir: bool, clock: u64) {
        let Some(&i) = self.by_oid.get(&oid) else {
            return;
        };
        let stamp = self.time.map_or(0, |t| t.ns(clock));
        let a = &mut self.local[i];
        a.net_steps += if dir { 1 } else { -1 };
        a.stamp_ns = stamp;
        self.dirty = true;
        let due = match self.time {
            Some(_) => {
                self.last_publish.is_none()
                    || stamp.saturating_sub(self.last_published_stamp) >= PUBLISH_PERIOD.as_nanos() as u64
            }
            None => self.last_publish.is_none_or(|t| t.elapsed() >= PUBLISH_PERIOD),
        };
        if due {
            self.publish();
        }
    }

    /// Publishes the local axes if they changed and [`PUBLISH_PERIOD`] has passed.
    pub fn flush_due(&mut self) {
        if self.dirty && self.last_publish.is_none_or(|t| t.elapsed() >= PUBLISH_PERIOD) {
            self.publish();
        }
    }

    /// Publishes the local axes if they changed since the last publication.
    pub fn flush(&mut self) {
        if self.dirty {
            self.publish();
        }
    }

    fn publish(&mut self) {
        self.dirty = false;
        self.last_publish = Some(Instant::now());
        let Some(bus) = &self.bus else {
            return;
        };
        self.seq += 1;
        let mut u = WorldUpdate {
            source: self.source,
            seq: self.seq,
            count: 0,
            reserved: 0,
            axes: [AxisSample {
                name: [0; NAME_LEN],
                position_mm: 0.0,
                stamp_ns: 0,
            }; MAX_AXES],
        };
        for (slot, a) in u.axes.iter_mut().zip(&self.local) {
            *slot = AxisSample {
                name: name_bytes(&a.spec.name),
                position_mm: position(a),
                stamp_ns: a.stamp_ns,
            };
            u.count += 1;
            self.last_published_stamp = self.last_published_stamp.max(a.stamp_ns);
        }
        let free = MAX_AXES - u.count as usize;
        for (slot, &(name, value)) in u.axes[u.count as usize..]
            .iter_mut()
            .zip(self.values.iter().take(free))
        {
            *slot = AxisSample {
                name,
                position_mm: value,
                stamp_ns: 0,
            };
            u.count += 1;
        }
        // A full or vanished peer must not stop the MCU: the next step publishes again.
        let _ = bus.publisher.send_copy(u);
    }

    /// Drains the subscriber: the latest remote position of every axis.
    pub fn refresh(&mut self) {
        let Some(bus) = &self.bus else {
            return;
        };
        while let Ok(Some(sample)) = bus.subscriber.receive() {
            let u: &WorldUpdate = &sample;
            if u.source == self.source {
                continue;
            }
            for a in u.axes.iter().take((u.count as usize).min(MAX_AXES)) {
                self.remote
                    .entry(a.name)
                    .or_default()
                    .push(a.stamp_ns, a.position_mm);
            }
        }
    }

    /// Position of axis `name`: driven here, else the latest published by another process.
    pub fn position(&self, name: &str) -> Option<f64> {
        self.position_at(name, None)
    }

    /// Position of axis `name` at CLOCK_MONOTONIC `at_ns`: driven here, its position now (this
    /// process runs its timers in due order, so every local step due by then has been taken
    /// and none due later); else the latest published by another process with a step due at or
    /// before `at_ns` (`None`: the latest).
    fn position_at(&self, name: &str, at_ns: Option<u64>) -> Option<f64> {
        let key = name_bytes(name);
        match self.local.iter().find(|a| a.spec.name == name) {
            Some(a) => Some(position(a)),
            None => match self.values.iter().find(|(n, _)| *n == key) {
                Some(&(_, v)) => Some(v),
                None => self.remote.get(&key)?.at(at_ns),
            },
        }
    }

    /// Value of coordinate `c`: `None` while one of its axes is unknown.
    pub fn coord(&self, c: &Coord) -> Option<f64> {
        self.coord_at(c, None)
    }

    fn coord_at(&self, c: &Coord, at_ns: Option<u64>) -> Option<f64> {
        c.terms.iter().try_fold(0.0, |sum, (coef, name)| {
            Some(sum + coef * self.position_at(name, at_ns)?)
        })
    }

    /// Value of coordinate `c` at MCU clock `clock` (refreshes remote positions first; with a
    /// time base the other processes' axes as they were then), `None` while an axis is unknown.
    pub fn coord_at_clock(&mut self, c: &Coord, clock: u64) -> Option<f64> {
        self.refresh();
        let at = self.time.map(|t| t.ns(clock));
        self.coord_at(c, at)
    }

    /// Level of input `pin`, sampled at MCU clock `clock`, if it is a simulated endstop
    /// (refreshes remote positions first). With a time base the other processes' axes are
    /// read as they were at `clock`, as a real MCU sampling on time would see them.
    pub fn read_endstop(&mut self, pin: u8, clock: u64) -> Option<bool> {
        let i = self.endstops.iter().position(|e| e.pin == pin)?;
        self.refresh();
        let at = self.time.map(|t| t.ns(clock));
        let e = &self.endstops[i];
        let pos = self.probe_height(pin, &e.axis, at)?;
        let trigger_mm = e.trigger_mm + self.surface_at(pin, at);
        let triggered = if e.at_min {
            pos <= trigger_mm
        } else {
            pos >= trigger_mm
        };
        Some(triggered != e.active_low)
    }
}

fn position(a: &LocalAxis) -> f64 {
    a.spec.start_mm + a.net_steps as f64 / a.spec.steps_per_mm
}

fn open_bus(world: &str) -> Result<Bus, WorldError> {
    let err = |what: &'static str| {
        let world = world.to_owned();
        move |e: &dyn std::fmt::Debug| WorldError {
            world,
            what,
            detail: format!("{e:?}"),
        }
    };
    set_log_level(LogLevel::Error);
    rt_core::shm::stale::ensure_sweeper();
    remove_stale_nodes();
    let name: ServiceName = format!("cadence/world/{world}")
        .as_str()
        .try_into()
        .map_err(|e| err("service name")(&e))?;
    let node = NodeBuilder::new().create::<ipc::Service>().map_err(|e| {
        let root = std::path::Path::new(rt_core::shm::ICEORYX2_ROOT);
        match rt_core::shm::access_hint(root) {
            Some(hint) => err("node")(&format_args!("{e:?} ({hint})")),
            None => err("node")(&e),
        }
    })?;
    let service = node
        .service_builder(&name)
        .publish_subscribe::<WorldUpdate>()
        .max_publishers(8)
        .max_subscribers(8)
        .subscriber_max_buffer_size(HISTORY)
        .history_size(1)
        .enable_safe_overflow(true)
        .open_or_create()
        .map_err(|e| err("service")(&e))?;
    let publisher = service
        .publisher_builder()
        .create()
        .map_err(|e| err("publisher")(&e))?;
    let subscriber = service
        .subscriber_builder()
        .create()
        .map_err(|e| err("subscriber")(&e))?;
    Ok(Bus {
        _node: node,
        publisher,
        subscriber,
    })
}

/// Removes what crashed `cadence-mcu` (or other iceoryx2) processes left behind.
fn remove_stale_nodes() {
    let _ = Node::<ipc::Service>::list(Config::global_config(), |state| {
        if let NodeState::Dead(view) = state {
            let _ = view.try_remove_stale_resources();
        }
        CallbackProgression::Continue
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    fn axis(name: &str, step_pin: u8) -> AxisSpec {
        AxisSpec {
            name: name.into(),
            step_pin,
            steps_per_mm: 100.0,
            start_mm: 10.0,
        }
    }

    #[test]
    fn local_axis_drives_its_endstops() {
        let endstops = vec![
            EndstopSpec {
                pin: 5,
                axis: Coord::axis("x"),
                trigger_mm: 9.95,
                at_min: true,
                active_low: false,
            },
            EndstopSpec {
                pin: 6,
                axis: Coord::axis("x"),
                trigger_mm: 10.02,
                at_min: false,
                active_low: false,
            },
            EndstopSpec {
                pin: 7,
                axis: Coord::axis("nobody"),
                trigger_mm: 0.0,
                at_min: true,
                active_low: false,
            },
        ];
        let mut w = World::new(None, vec![axis("x", 3)], endstops).unwrap();
        w.config_stepper(0, 3);
        w.step(1, true, 0); // not an axis stepper
        assert_eq!(w.position("x"), Some(10.0));
        assert_eq!(w.read_endstop(5, 0), Some(false));
        for _ in 0..5 {
            w.step(0, false, 0);
        }
        assert_eq!(w.read_endstop(5, 0), Some(true), "9.95 is at the trigger");
        for _ in 0..7 {
            w.step(0, true, 0);
        }
        assert_eq!(w.read_endstop(5, 0), Some(false));
        assert_eq!(w.read_endstop(6, 0), Some(true));
        assert_eq!(w.read_endstop(7, 0), None);
        assert_eq!(w.read_endstop(8, 0), None);
    }

    #[test]
    fn two_worlds_share_positions_across_ports() {
        let id = format!("unit-{}", std::process::id());
        let endstop = EndstopSpec {
            pin: 1,
            axis: Coord::axis("z"),
            trigger_mm: 10.5,
            at_min: false,
            active_low: false,
        };
        let mut stepper = World::new(Some(&id), vec![axis("z", 2)], vec![]).unwrap();
        let mut probe = World::new(Some(&id), vec![], vec![endstop]).unwrap();
        stepper.config_stepper(4, 2);
        assert_eq!(probe.read_endstop(1, 0), None, "nothing published yet");
        for _ in 0..50 {
            stepper.step(4, true, 0);
        }
        stepper.flush();
        assert_eq!(probe.read_endstop(1, 0), Some(true));
        assert_eq!(probe.position("z"), Some(10.5));
    }

    #[test]
    fn a_late_sample_reads_remote_axes_as_they_were_at_its_due_time() {
        let id = format!("unit-time-{}", std::process::id());
        let endstop = EndstopSpec {
            pin: 1,
            axis: Coord::axis("z"),
            trigger_mm: 10.2,
            at_min: false,
            active_low: false,
        };
        // Both processes count 1 tick per ns from CLOCK_MONOTONIC 1 s.
        let time = TimeBase {
            start_ns: 1e9,
            ticks_per_ns: 1.0,
        };
        let mut stepper = World::new(Some(&id), vec![axis("z", 2)], vec![]).unwrap();
        let mut probe = World::new(Some(&id), vec![], vec![endstop]).unwrap();
        stepper.set_time_base(time);
        probe.set_time_base(time);
        stepper.config_stepper(4, 2);
        // A step every 250 µs of due time, all taken at once (a process catching up): each
        // one is published.
        for k in 1..=50u64 {
            stepper.step(4, true, k * 250_000);
        }
        stepper.flush();
        // z = 10 + k / 100 after step k: 10.2 is reached by step 20, due at 5 ms.
        assert_eq!(
            probe.read_endstop(1, 4_999_999),
            Some(false),
            "step 19: z = 10.19"
        );
        assert_eq!(probe.read_endstop(1, 5_000_000), Some(true), "step 20: z = 10.2");
        assert_eq!(probe.position("z"), Some(10.5), "now: all 50 steps");
        // Before the oldest sample kept: the oldest is the best guess.
        assert_eq!(probe.read_endstop(1, 0), Some(false));
    }

    #[test]
    fn history_keeps_the_latest_samples_in_order() {
        let mut h = AxisHistory::default();
        assert_eq!(h.at(None), None);
        for k in 0..(HISTORY as u64 + 10) {
            h.push(100 + k, k as f64);
        }
        assert_eq!(h.samples.len(), HISTORY);
        assert_eq!(h.at(Some(0)), Some(10.0), "older than kept: the oldest");
        assert_eq!(h.at(Some(150)), Some(50.0));
        assert_eq!(h.at(None), Some((HISTORY + 9) as f64));
        h.push(5, -1.0);
        assert_eq!(h.samples.len(), 1, "out of order: starts over");
        assert_eq!(h.at(Some(1)), Some(-1.0));
    }

    #[test]
    fn corexy_endstops_read_combinations_of_the_two_axes() {
        let x = Coord::parse("0.5*a+0.5*b").unwrap();
        let y = Coord::parse("0.5*a-0.5*b").unwrap();
        let endstops = vec![
            EndstopSpec {
                pin: 1,
                axis: x.clone(),
                trigger_mm: 9.0,
                at_min: true,
                active_low: false,
            },
            EndstopSpec {
                pin: 2,
                axis: y.clone(),
                trigger_mm: -1.0,
                at_min: true,
                active_low: false,
            },
            // X's endstop again, wired normally closed: reads 0 when triggered.
            EndstopSpec {
                pin: 5,
                axis: x.clone(),
                trigger_mm: 9.0,
                at_min: true,
                active_low: true,
            },
        ];
        // a = x + y = 12, b = x − y = 8: x = 10, y = 2.
        let spec = |name: &str, pin: u8, start_mm: f64| AxisSpec {
            name: name.into(),
            step_pin: pin,
            steps_per_mm: 100.0,
            start_mm,
        };
        let mut w = World::new(None, vec![spec("a", 3, 12.0), spec("b", 4, 8.0)], endstops).unwrap();
        w.config_stepper(0, 3);
        w.config_stepper(1, 4);
        assert_eq!((w.coord(&x), w.coord(&y)), (Some(10.0), Some(2.0)));
        assert_eq!(
            (w.read_endstop(1, 0), w.read_endstop(5, 0)),
            (Some(false), Some(true))
        );
        // X − 1 mm: both A and B back by 100 steps; Y keeps its place.
        for _ in 0..100 {
            w.step(0, false, 0);
            w.step(1, false, 0);
        }
        assert_eq!(w.read_endstop(1, 0), Some(true));
        assert_eq!(w.read_endstop(5, 0), Some(false), "active low: 0 when triggered");
        assert_eq!(w.read_endstop(2, 0), Some(false));
        // Y − 3 mm: A back 300 steps, B forward 300.
        for _ in 0..300 {
            w.step(0, false, 0);
            w.step(1, true, 0);
        }
        assert!((w.coord(&y).unwrap() + 1.0).abs() < 1e-9);
        assert_eq!(w.read_endstop(2, 0), Some(true));
        assert!((w.coord(&x).unwrap() - 9.0).abs() < 1e-9);
        assert_eq!(
            w.coord(&Coord::parse("a+c").unwrap()),
            None,
            "c is driven by nobody"
        );
    }

    #[test]
    fn coordinates_parse_and_print() {
        let c = |t: &str| Coord::parse(t).map(|c| c.terms);
        let t = |v: &[(f64, &str)]| Ok(v.iter().map(|&(k, n)| (k, n.to_string())).collect());
        assert_eq!(c("x"), t(&[(1.0, "x")]));
        assert_eq!(c(" 0.5*a + 0.5 * b "), t(&[(0.5, "a"), (0.5, "b")]));
        assert_eq!(c("-a-2e-1*b+_c1"), t(&[(-1.0, "a"), (-0.2, "b"), (1.0, "_c1")]));
        assert_eq!(c("+1E+1*e"), t(&[(10.0, "e")]));
        let shown: Vec<String> = ["x", "0.5*a-0.5*b", "-a+2*z", "-0.125*b"]
            .iter()
            .map(|s| Coord::parse(s).unwrap().to_string())
            .collect();
        assert_eq!(shown, ["x", "0.5*a-0.5*b", "-a+2*z", "-0.125*b"]);
        let err = |t: &str| Coord::parse(t).unwrap_err().to_string();
        assert_eq!(err(" "), "coordinate ` ` is empty");
        assert_eq!(err("a+"), "coordinate `a+`: term `+` is empty");
        assert_eq!(
            err("x*a"),
            "coordinate `x*a`: coefficient `x` is not a finite number"
        );
        assert_eq!(
            err("inf*a"),
            "coordinate `inf*a`: coefficient `inf` is not a finite number"
        );
        assert!(err("2a").contains("axis name `2a` must"));
        assert!(err("averylongname").contains("axis name `averylongname`"));
        assert!(err("a*b*c").contains("coefficient `a`"));
        assert!(err("a+b+c+d+e+f+g+h+i").contains("more than 8 terms"));
    }

    proptest::proptest! {
        /// Whatever `Display` writes, `parse` reads back to the same coordinate; no text makes
        /// `parse` panic.
        #[test]
        fn coordinates_round_trip(
            terms in proptest::collection::vec((-1e6f64..1e6, "[a-z_][a-z0-9_]{0,7}"), 1..=MAX_TERMS),
            text in ".{0,40}",
        ) {
            let c = Coord { terms };
            proptest::prop_assert_eq!(Coord::parse(&c.to_string()), Ok(c));
            let _ = Coord::parse(&text);
        }
    }
}
