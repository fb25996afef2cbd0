//! Modal G-code state applied to a [`Toolhead`]: absolute/relative coordinates (G90/G91),
//! absolute/relative extrusion (M82/M83), G92 offsets, the feedrate and the homed axes.
//!
//! Coordinates (Klipper's G-code move semantics): the toolhead position of an axis is the
//! G-code value plus that axis's G92 offset (`base`). In relative mode a value adds to the last
//! commanded position. E is relative when either G91 or M83 is in force. G92 sets `base` so the
//! current position reads as the given value (no argument: every axis reads 0). Feedrate F is in
//! mm/min; the toolhead gets mm/s, times the M220 speed factor. M221 scales E like Klipper (the
//! E offset is rebased so the current position keeps reading the same). G28 does no motion
//! yet: it declares the named axes (all if none) homed at the configured `home_position`.
//!
//! Arcs (G2/G3, XY plane, centre offset I/J): split into chords like Klipper's `[gcode_arcs]`
//! with its `resolution` (default 1 mm): n = max(1, ⌊hypot(angle·r, Δz) / resolution⌋)
//! segments, Z and E spread evenly. Firmware retraction (G10/G11) moves E by `retract_length` (+ the unretract extra) at
//! the retract/unretract speeds, like Klipper's `[firmware_retraction]` (defaults: length 0,
//! speeds 20 and 10 mm/s; SET_RETRACTION changes them). SET_INPUT_SHAPER (only with an
//! `[input_shaper]` section, as on Klipper) takes SHAPER_TYPE, SHAPER_TYPE_X/Y,
//! SHAPER_FREQ_X/Y and DAMPING_RATIO_X/Y, and answers with the settings (Klipper's report);
//! the pipeline applies them from the next move. SAVE_GCODE_STATE / RESTORE_GCODE_STATE
//! (`NAME`, default `default`; `MOVE=1`, `MOVE_SPEED`) keep and restore the modes, G92
//! offsets, speed and M220/M221 factors as Klipper's `gcode_move` does. Heaters, fans, motors off, M114 and
//! M117 are returned to the caller as [`Applied`] values. Unknown commands are
//! [`Applied::Unsupported`] (the caller warns), or errors with [`GcodeState::set_unknown_is_error`].

use crate::extruders::{ExtruderEvent, Extruders};
use crate::gcode::exclude::{ExcludeObjects, EXCLUDE_COMMANDS};
use crate::gcode::{Command, CommandName, CommandText, GcodeErrorKind, GcodeLine, OtherParams, TextBuilder};
use crate::shaper::{InputShaper, ShaperType};
use crate::toolhead::{MoveError, Toolhead, AXIS_NAMES};
use std::fmt::Write as _;

/// Speed before any F word (mm/s), as Klipper.
const DEFAULT_SPEED: f64 = 25.0;
/// Slowest feedrate accepted (mm/s): anything slower is a broken file, not a print.
const MIN_SPEED: f64 = 0.01;
/// Arc chord length (mm), Klipper's `[gcode_arcs] resolution` default.
pub const ARC_RESOLUTION: f64 = 1.0;
/// Most chords one arc may be split into.
const MAX_ARC_SEGMENTS: f64 = 1e6;

/// The [`Command::Other`] commands [`GcodeState::apply`] implements (besides M117 and, with an
/// input shaper, SET_INPUT_SHAPER); a test keeps it equal to the commands handled.
const KNOWN_OTHER: [&str; 27] = [
    "ACTIVATE_EXTRUDER",
    "G10",
    "G11",
    "G17",
    "G18",
    "G19",
    "G20",
    "G21",
    "M104",
    "M106",
    "M107",
    "M109",
    "M114",
    "M140",
    "M18",
    "M190",
    "M204",
    "M220",
    "M221",
    "M84",
    "RESTORE_GCODE_STATE",
    "SAVE_GCODE_STATE",
    "SET_EXTRUDER_ROTATION_DISTANCE",
    "SET_PRESSURE_ADVANCE",
    "SET_RETRACTION",
    "SET_VELOCITY_LIMIT",
    "SYNC_EXTRUDER_MOTION",
];

/// Which heater a temperature command addresses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HeaterId {
    /// Extruder k's heater (`extruder`, `extruder1`…).
    Extruder(usize),
    Bed,
}

impl HeaterId {
    /// The heater's name (`extruder`, `extruder1`…, `heater_bed`).
    pub fn name(self) -> &'static str {
        match self {
            HeaterId::Extruder(k) => crate::extruders::EXTRUDER_NAMES
                .get(k)
                .copied()
                .unwrap_or("extruder"),
            HeaterId::Bed => "heater_bed",
        }
    }
}

/// What [`GcodeState::apply`] did with a line.
#[derive(Debug, Clone, PartialEq)]
pub enum Applied {
    Done,
    /// A well-formed command the planner does not implement; the caller warns once per name.
    /// (Inline text: returning it does not allocate for names up to 47 bytes.)
    Unsupported(CommandName),
    /// M104/M109 (extruder) and M140/M190 (bed): new target in °C (0 = off); `wait` for
    /// M109/M190 (the caller waits for the temperature before going on).
    Heater {
        heater: HeaterId,
        target: f64,
        wait: bool,
    },
    /// M106/M107: part-cooling fan speed in 0 ..= 1.
    Fan {
        speed: f64,
    },
    /// SET_PRESSURE_ADVANCE with a new ADVANCE or SMOOTH_TIME: it applies from the next move
    /// on (the pipeline hands it to the extruder's step generation; smoothing makes a new
    /// advance gradual over `smooth_time`; a new smooth_time first brings the toolhead to rest).
    PressureAdvance {
        advance: f64,
        smooth_time: f64,
    },
    /// ACTIVATE_EXTRUDER, SYNC_EXTRUDER_MOTION, SET_PRESSURE_ADVANCE,
    /// SET_EXTRUDER_ROTATION_DISTANCE: what changes in step generation (the pipeline applies
    /// it from the next move and answers with `said`, Klipper's text, as a report).
    Extruder {
        event: ExtruderEvent,
        said: CommandText,
    },
    /// M84/M18: steppers off; every axis must be homed again before moving.
    MotorsOff,
    /// M114: the position report, Klipper's text (`X:… Y:… Z:… E:…`).
    Report(CommandText),
    /// M117: a display message.
    Message(CommandText),
}

/// A G-code line the planner refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("line {line}: {kind}")]
pub struct PlanError {
    pub line: usize,
    pub kind: PlanErrorKind,
}

/// Why a line was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlanErrorKind {
    #[error(transparent)]
    Move(#[from] MoveError),
    #[error("Must home axis first: {axis} (G28)")]
    NotHomed { axis: char },
    #[error("Invalid speed F{0} (must be > 0)")]
    BadFeedrate(f64),
    #[error("G20 (inches) is not supported: use millimeters (G21)")]
    Inches,
    #[error("Unknown command:\"{0}\"")]
    UnknownCommand(String),
    #[error("{0}")]
    BadParameter(String),
    #[error("bad arc: {0}")]
    BadArc(String),
    #[error("invalid configuration: {0}")]
    Config(String),
}

/// Modal state of the G-code interpreter.
#[derive(Debug, Clone)]
pub struct GcodeState {
    absolute_coord: bool,
    absolute_extrude: bool,
    /// G92 offsets: toolhead position = G-code value + base.
    base: [f64; 4],
    /// Last commanded toolhead position.
    last: [f64; 4],
    /// Feedrate in mm/s.
    speed: f64,
    homed: [bool; 3],
    home_position: [f64; 3],
    /// M220 factor on feedrates.
    speed_factor: f64,
    /// M221 factor on E.
    extrude_factor: f64,
    unknown_is_error: bool,
    retract: Retraction,
    retracted: bool,
    /// The extruders: the active one, their E positions, the steppers' motion queues and
    /// pressure advance.
    extruders: Extruders,
    /// Arc chord length (mm).
    arc_resolution: f64,
    /// `[input_shaper]` settings (`None`: no such section, SET_INPUT_SHAPER is unknown).
    input_shaper: Option<InputShaper>,
    /// `[exclude_object]`'s objects (`None` without the section).
    objects: Option<ExcludeObjects>,
    /// Moves of an excluded object were dropped: the toolhead is not at `last`.
    behind: bool,
    /// `SAVE_GCODE_STATE` states by name (allocated only when a macro saves one).
    saved_states: Vec<(String, SavedState)>,
    /// The bed mesh applied to moves (`last` stays in G-code space, the toolhead gets Z plus
    /// the mesh's offset, moves split along the mesh).
    bed_mesh: Option<crate::bed_mesh::split::AppliedMesh>,
    /// Scratch for a move's mesh segments (reused).
    segments: Vec<[f64; 4]>,
}

/// What `SAVE_GCODE_STATE` keeps (Klipper's `gcode_move` fields).
#[derive(Debug, Clone, Copy, PartialEq)]
struct SavedState {
    absolute_coord: bool,
    absolute_extrude: bool,
    base: [f64; 4],
    last: [f64; 4],
    speed: f64,
    speed_factor: f64,
    extrude_factor: f64,
}

/// Firmware retraction settings (Klipper's `[firmware_retraction]`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Retraction {
    pub retract_length: f64,
    pub retract_speed: f64,
    pub unretract_extra_length: f64,
    pub unretract_speed: f64,
}

impl Default for Retraction {
    fn default() -> Self {
        Retraction {
            retract_length: 0.0,
            retract_speed: 20.0,
            unretract_extra_length: 0.0,
            unretract_speed: 10.0,
        }
    }
}

impl GcodeState {
    /// Fresh state (G90, M82, no offsets, nothing homed) for a toolhead at position 0.
    pub fn new(home_position: [f64; 3]) -> GcodeState {
        GcodeState {
            absolute_coord: true,
            absolute_extrude: true,
            base: [0.0; 4],
            last: [0.0; 4],
            speed: DEFAULT_SPEED,
            homed: [false; 3],
            home_position,
            speed_factor: 1.0,
            extrude_factor: 1.0,
            unknown_is_error: false,
            retract: Retraction::default(),
            retracted: false,
            extruders: Extruders::default(),
            arc_resolution: ARC_RESOLUTION,
            input_shaper: None,
            objects: None,
            behind: false,
            saved_states: Vec::new(),
            bed_mesh: None,
            segments: Vec::new(),
        }
    }

    /// Applies `mesh` to the moves from now on (`None`: none). The G-code position is re-read
    /// from the toolhead through the new mesh (where the nozzle is stays where it is, as
    /// Klipper's `reset_last_position` does).
    pub fn set_bed_mesh(&mut self, mesh: Option<crate::bed_mesh::split::AppliedMesh>, th: &Toolhead) {
        self.bed_mesh = mesh;
        self.last = self.untransform(th.position());
        self.behind = false;
    }

    /// The bed mesh applied to moves.
    pub fn bed_mesh(&self) -> Option<&crate::bed_mesh::split::AppliedMesh> {
        self.bed_mesh.as_ref()
    }

    /// G-code-space position of toolhead position `p` (without a mesh: `p`).
    fn untransform(&self, p: [f64; 4]) -> [f64; 4] {
        match &self.bed_mesh {
            Some(m) => m.untransform(p),
            None => p,
        }
    }

    /// With `[exclude_object]` (`true`) the EXCLUDE_OBJECT commands are known and an excluded
    /// object's moves are dropped; without, they are unknown commands as on Klipper.
    pub fn set_exclude_object(&mut self, on: bool) {
        self.objects = on.then(ExcludeObjects::default);
    }

    /// The objects of `[exclude_object]` (`None` without the section).
    pub fn exclude_objects(&self) -> Option<&ExcludeObjects> {
        self.objects.as_ref()
    }

    /// The input shaper settings (`None`: the printer has no `[input_shaper]`).
    pub fn set_input_shaper(&mut self, shaper: Option<InputShaper>) {
        self.input_shaper = shaper;
    }

    /// The input shaper settings as last set (SET_INPUT_SHAPER).
    pub fn input_shaper(&self) -> Option<InputShaper> {
        self.input_shaper
    }

    /// Unknown commands become errors (`true`) or [`Applied::Unsupported`] (default).
    pub fn set_unknown_is_error(&mut self, on: bool) {
        self.unknown_is_error = on;
    }

    /// Firmware retraction settings (e.g. from a `[firmware_retraction]` section).
    pub fn set_retraction(&mut self, r: Retraction) {
        self.retract = r;
    }

    /// Arc chord length in mm (`[gcode_arcs] resolution`; default [`ARC_RESOLUTION`]). Not
    /// finite or not above 0: the default.
    pub fn set_arc_resolution(&mut self, mm: f64) {
        self.arc_resolution = if mm.is_finite() && mm > 0.0 {
            mm
        } else {
            ARC_RESOLUTION
        };
    }

    /// The printer's extruders and extruder steppers (default: one extruder, no stepper).
    pub fn set_extruders(&mut self, extruders: Extruders) {
        self.extruders = extruders;
    }

    /// The extruders as the commands left them.
    pub fn extruders(&self) -> &Extruders {
        &self.extruders
    }

    /// The active extruder's stepper's pressure advance and smooth time (0 and 0.04 s
    /// without one).
    pub fn pressure_advance(&self) -> (f64, f64) {
        let own = crate::extruders::EXTRUDER_NAMES[self.extruders.active()];
        self.extruders
            .steppers()
            .iter()
            .find(|s| s.name == own)
            .map_or((0.0, 0.04), |s| s.pressure_advance)
    }

    /// Axes homed so far (X, Y, Z).
    pub fn homed(&self) -> [bool; 3] {
        self.homed
    }

    /// Declares axes homed without a G28 (e.g. a printer without endstops, tests).
    pub fn set_homed(&mut self, homed: [bool; 3]) {
        self.homed = homed;
    }

    /// The position as G-code reads it (toolhead position minus the G92 offsets, E divided by the
    /// M221 factor).
    pub fn gcode_position(&self) -> [f64; 4] {
        let mut p = self.last;
        for (p, b) in p.iter_mut().zip(self.base) {
            *p -= b;
        }
        p[3] /= self.extrude_factor;
        p
    }

    /// Current feedrate in mm/s.
    pub fn speed(&self) -> f64 {
        self.speed
    }

    /// Applies one line to the toolhead.
    pub fn apply(&mut self, line: &GcodeLine, th: &mut Toolhead) -> Result<Applied, PlanError> {
        let err = |kind: PlanErrorKind| PlanError {
            line: line.line_no,
            kind,
        };
        match &line.cmd {
            Command::Move { x, y, z, e, f } => {
                let speed = self.feed(*f).map_err(err)?;
                let next = self.target([*x, *y, *z, *e]);
                self.move_to(next, speed, th).map_err(err)?;
                self.speed = speed;
            }
            Command::Arc {
                clockwise,
                x,
                y,
                z,
                e,
                f,
                i,
                j,
            } => {
                let speed = self.feed(*f).map_err(err)?;
                let next = self.target([*x, *y, *z, *e]);
                self.arc(next, (*i, *j), *clockwise, speed, th).map_err(err)?;
                self.speed = speed;
            }
            Command::Home { x, y, z } => {
                let mut pos = th.position();
                for (axis, on) in [x, y, z].into_iter().enumerate() {
                    if *on {
                        pos[axis] = self.home_position[axis];
                        self.homed[axis] = true;
                    }
                }
                th.set_position(pos);
                self.last = self.untransform(th.position());
            }
            Command::AbsolutePositioning => self.absolute_coord = true,
            Command::RelativePositioning => self.absolute_coord = false,
            Command::AbsoluteExtrusion => self.absolute_extrude = true,
            Command::RelativeExtrusion => self.absolute_extrude = false,
            Command::SetPosition { x, y, z, e } => {
                let given = [x, y, z, e];
                if given.iter().all(|v| v.is_none()) {
                    self.base = self.last;
                } else {
                    for (i, v) in given.into_iter().enumerate() {
                        if let Some(v) = *v {
                            let f = if i == 3 { self.extrude_factor } else { 1.0 };
                            self.base[i] = self.last[i] - v * f;
                        }
                    }
                }
            }
            Command::Dwell { seconds } => th.dwell(*seconds).map_err(|e| err(e.into()))?,
            Command::WaitMoves => th.flush(),
            Command::Other { name, raw } => return self.other(name, raw, th).map_err(err),
        }
        Ok(Applied::Done)
    }

    /// The speed (mm/s) of a move with feedrate word `f` (mm/min).
    fn feed(&self, f: Option<f64>) -> Result<f64, PlanErrorKind> {
        match f {
            Some(f) if !(f.is_finite() && f / 60.0 >= MIN_SPEED) => Err(PlanErrorKind::BadFeedrate(f)),
            Some(f) => Ok(f / 60.0),
            None => Ok(self.speed),
        }
    }

    /// The toolhead position a G1/G2/G3 with these words goes to.
    fn target(&self, words: [Option<f64>; 4]) -> [f64; 4] {
        let mut next = self.last;
        for (i, v) in words.into_iter().enumerate().take(3) {
            if let Some(v) = v {
                next[i] = if self.absolute_coord {
                    v + self.base[i]
                } else {
                    self.last[i] + v
                };
            }
        }
        if let Some(v) = words[3] {
            let v = v * self.extrude_factor;
            next[3] = if self.absolute_coord && self.absolute_extrude {
                v + self.base[3]
            } else {
                self.last[3] + v
            };
        }
        next
    }

    /// One straight move to `next` (toolhead coordinates) at `speed` mm/s (before M220).
    fn move_to(&mut self, next: [f64; 4], speed: f64, th: &mut Toolhead) -> Result<(), PlanErrorKind> {
        if next == self.last && !self.behind {
            return Ok(());
        }
        if self.objects.as_ref().is_some_and(ExcludeObjects::skipping) {
            // An excluded object's move is dropped, as Klipper's exclude_object does: the
            // G-code position follows it, E's offset takes up its extrusion (never made up),
            // and the next move kept starts from where the toolhead really is.
            self.base[3] -= next[3] - self.last[3];
            self.last = [next[0], next[1], next[2], self.last[3]];
            self.behind = true;
            return Ok(());
        }
        for axis in 0..3 {
            if next[axis] != self.last[axis] && !self.homed[axis] {
                return Err(PlanErrorKind::NotHomed {
                    axis: AXIS_NAMES[axis],
                });
            }
        }
        match &self.bed_mesh {
            None => th.move_to(next, speed * self.speed_factor)?,
            Some(mesh) => {
                let mut segs = std::mem::take(&mut self.segments);
                segs.clear();
                mesh.split(self.last, next, &mut segs);
                let r = segs
                    .iter()
                    .try_for_each(|&p| th.move_to(p, speed * self.speed_factor));
                self.segments = segs;
                r?;
            }
        }
        self.last = next;
        self.behind = false;
        Ok(())
    }

    /// G2/G3: chords from the current position to `end` around centre start + (i, j).
    fn arc(
        &mut self,
        end: [f64; 4],
        ij: (Option<f64>, Option<f64>),
        clockwise: bool,
        speed: f64,
        th: &mut Toolhead,
    ) -> Result<(), PlanErrorKind> {
        let start = self.last;
        if ij.0.is_none() && ij.1.is_none() {
            return Err(PlanErrorKind::BadArc(
                "needs I and/or J (the centre offset)".into(),
            ));
        }
        let (ci, cj) = (ij.0.unwrap_or(0.0), ij.1.unwrap_or(0.0));
        let (cx, cy) = (start[0] + ci, start[1] + cj);
        let r = ci.hypot(cj);
        if !(r.is_finite() && r > 1e-6) {
            return Err(PlanErrorKind::BadArc(format!("radius {r} is too small")));
        }
        let a0 = (start[1] - cy).atan2(start[0] - cx);
        let a1 = (end[1] - cy).atan2(end[0] - cx);
        let tau = std::f64::consts::TAU;
        let mut travel = if clockwise { a0 - a1 } else { a1 - a0 };
        if travel <= 1e-9 {
            travel += tau;
        }
        if travel > tau {
            travel -= tau;
        }
        let dz = end[2] - start[2];
        let length = (travel * r).hypot(dz);
        let n = (length / self.arc_resolution).floor().max(1.0);
        if !n.is_finite() || n > MAX_ARC_SEGMENTS {
            return Err(PlanErrorKind::BadArc(format!(
                "{length:.1} mm long: too many segments"
            )));
        }
        let n = n as usize;
        let sign = if clockwise { -1.0 } else { 1.0 };
        for k in 1..=n {
            let p = if k == n {
                end
            } else {
                let f = k as f64 / n as f64;
                let a = a0 + sign * travel * f;
                [
                    cx + r * a.cos(),
                    cy + r * a.sin(),
                    start[2] + dz * f,
                    start[3] + (end[3] - start[3]) * f,
                ]
            };
            self.move_to(p, speed, th)?;
        }
        Ok(())
    }

    /// Commands the parser leaves as [`Command::Other`].
    fn other(&mut self, name: &str, raw: &str, th: &mut Toolhead) -> Result<Applied, PlanErrorKind> {
        let bad = |e: GcodeErrorKind| PlanErrorKind::BadParameter(format!("{name}: {e}"));
        if name == "M117" {
            let text = raw.trim().get(4..).unwrap_or("").trim();
            return Ok(Applied::Message(CommandText::new(text)));
        }
        if let Some(objects) = self.objects.as_mut().filter(|_| EXCLUDE_COMMANDS.contains(&name)) {
            let rawparams = raw.trim_start().get(name.len()..).unwrap_or("");
            return match objects.command(name, rawparams) {
                Ok(Some(said)) => Ok(Applied::Report(CommandText::new(&said))),
                Ok(None) => Ok(Applied::Done),
                Err(e) => Err(PlanErrorKind::BadParameter(format!("{name}: {e}"))),
            };
        }
        let p = match OtherParams::parse(raw) {
            Ok(p) => p,
            // Klipper says an unknown command is unknown whatever its parameters
            // (`M118 layer 1`); only a known command's parameters are errors.
            Err(_) if !self.knows(name) => return self.unknown(name),
            Err(e) => return Err(bad(e)),
        };
        let num = |k: &str| p.float(k).map_err(bad);
        let non_neg = |k: &str| -> Result<Option<f64>, PlanErrorKind> {
            match num(k)? {
                Some(v) if v < 0.0 => Err(PlanErrorKind::BadParameter(format!(
                    "{name}: {k}={v} must be ≥ 0"
                ))),
                v => Ok(v),
            }
        };
        let positive = |k: &str| -> Result<Option<f64>, PlanErrorKind> {
            match num(k)? {
                Some(v) if v <= 0.0 => Err(PlanErrorKind::BadParameter(format!(
                    "{name}: {k}={v} must be > 0"
                ))),
                v => Ok(v),
            }
        };
        let limits = |e: crate::toolhead::ConfigError| PlanErrorKind::BadParameter(format!("{name}: {e}"));
        match name {
            "G21" => {}
            // Arcs are in the XY plane (`[gcode_arcs]`'s G17, what slicers write).
            "G17" => {}
            "G18" | "G19" => {
                return Err(PlanErrorKind::BadParameter(format!(
                    "{name}: only G17 (XY plane) arcs are supported"
                )))
            }
            "G20" => return Err(PlanErrorKind::Inches),
            "M104" | "M109" | "M140" | "M190" => {
                // T names an extruder (T1 = extruder1); without it the active one. Klipper
                // ignores turning off an extruder it does not have, and refuses heating one.
                let mut index = self.extruders.active();
                if matches!(name, "M104" | "M109") {
                    if let Some(t) = num("T")? {
                        let k = t as usize;
                        if t < 0.0 || t.fract() != 0.0 || k >= self.extruders.count() {
                            if non_neg("S")?.unwrap_or(0.0) <= 0.0 {
                                return Ok(Applied::Done);
                            }
                            return Err(PlanErrorKind::BadParameter(format!(
                                "{name}: T{t}: Extruder not configured"
                            )));
                        }
                        index = k;
                    }
                }
                let target = non_neg("S")?.unwrap_or(0.0);
                if target > 1000.0 {
                    return Err(PlanErrorKind::BadParameter(format!(
                        "{name}: S{target} is not a plausible temperature"
                    )));
                }
                let heater = if matches!(name, "M140" | "M190") {
                    HeaterId::Bed
                } else {
                    HeaterId::Extruder(index)
                };
                if matches!(name, "M109" | "M190") {
                    // The caller waits for the heater: moves queued so far run first.
                    th.flush();
                }
                let wait = matches!(name, "M109" | "M190");
                return Ok(Applied::Heater { heater, target, wait });
            }
            "M106" => {
                let s = non_neg("S")?.unwrap_or(255.0);
                return Ok(Applied::Fan {
                    speed: (s / 255.0).min(1.0),
                });
            }
            "M107" => return Ok(Applied::Fan { speed: 0.0 }),
            "M84" | "M18" => {
                th.flush();
                self.homed = [false; 3];
                return Ok(Applied::MotorsOff);
            }
            "M114" => {
                let p = self.gcode_position();
                let mut text = TextBuilder::new();
                // Writing to a TextBuilder cannot fail.
                let _ = write!(text, "X:{:.3} Y:{:.3} Z:{:.3} E:{:.3}", p[0], p[1], p[2], p[3]);
                return Ok(Applied::Report(text.finish()));
            }
            "M204" => {
                let accel = match (positive("S")?, positive("P")?, positive("T")?) {
                    (Some(s), _, _) => Some(s),
                    (None, Some(a), Some(b)) => Some(a.min(b)),
                    (None, a, b) => a.or(b),
                };
                let Some(accel) = accel else {
                    return Err(PlanErrorKind::BadParameter(format!(
                        "{name}: needs S, or P and T"
                    )));
                };
                th.set_limits(None, Some(accel), None, None).map_err(limits)?;
            }
            "M220" => self.speed_factor = positive("S")?.unwrap_or(100.0) / 100.0,
            "M221" => {
                let f = positive("S")?.unwrap_or(100.0) / 100.0;
                // Keep the E position reading the same under the new factor.
                let e = (self.last[3] - self.base[3]) / self.extrude_factor;
                self.base[3] = self.last[3] - e * f;
                self.extrude_factor = f;
            }
            "SET_VELOCITY_LIMIT" => {
                let accel_to_decel = positive("ACCEL_TO_DECEL")?;
                let accel = positive("ACCEL")?;
                let mut mcr = num("MINIMUM_CRUISE_RATIO")?;
                if let (None, Some(a2d)) = (mcr, accel_to_decel) {
                    let a = accel.unwrap_or(th.config().max_accel);
                    mcr = Some(1.0 - (a2d / a).min(1.0));
                }
                th.set_limits(
                    positive("VELOCITY")?,
                    accel,
                    non_neg("SQUARE_CORNER_VELOCITY")?,
                    mcr,
                )
                .map_err(limits)?;
            }
            "ACTIVATE_EXTRUDER" => {
                let Some(extruder) = p.get("EXTRUDER") else {
                    return Err(PlanErrorKind::BadParameter(format!("{name}: missing EXTRUDER")));
                };
                // Klipper flushes step generation, keeps the old extruder's E and continues
                // from the new one's; gcode_move then reads E as 0 with no M221 factor.
                th.flush();
                let (change, said) = self
                    .extruders
                    .activate(extruder, self.last[3])
                    .map_err(|e| PlanErrorKind::BadParameter(format!("{name}: {e}")))?;
                let Some((e, event)) = change else {
                    return Ok(Applied::Report(CommandText::new(&said)));
                };
                let mut pos = th.position();
                pos[3] = e;
                th.set_position(pos);
                self.last = th.position();
                self.base[3] = self.last[3];
                self.extrude_factor = 1.0;
                return Ok(Applied::Extruder {
                    event,
                    said: CommandText::new(&said),
                });
            }
            "SYNC_EXTRUDER_MOTION" | "SET_PRESSURE_ADVANCE" | "SET_EXTRUDER_ROTATION_DISTANCE" => {
                let (event, said) = self
                    .extruders
                    .command(name, &p)
                    .map_err(|e| PlanErrorKind::BadParameter(format!("{name}: {e}")))?;
                let said = CommandText::new(&said);
                return Ok(match event {
                    Some(event) => {
                        if name != "SET_PRESSURE_ADVANCE" {
                            // Klipper flushes step generation first.
                            th.flush();
                        }
                        Applied::Extruder { event, said }
                    }
                    None => Applied::Report(said),
                });
            }
            "SET_INPUT_SHAPER" if self.input_shaper.is_some() => {
                let mut s = self.input_shaper.unwrap_or_default();
                let common = p.get("SHAPER_TYPE");
                for (axis, sh) in [('X', &mut s.x), ('Y', &mut s.y)] {
                    let key = |k: &str| format!("{k}_{axis}");
                    if let Some(t) = common.or(p.get(&key("SHAPER_TYPE"))) {
                        sh.shaper_type = ShaperType::from_name(&t.to_ascii_lowercase()).ok_or_else(|| {
                            PlanErrorKind::BadParameter(format!("{name}: Unsupported shaper type: {t}"))
                        })?;
                    }
                    if let Some(z) = non_neg(&key("DAMPING_RATIO"))? {
                        sh.damping_ratio = z;
                    }
                    if let Some(f) = non_neg(&key("SHAPER_FREQ"))? {
                        sh.freq = f;
                    }
                    sh.validate()
                        .map_err(|e| PlanErrorKind::BadParameter(format!("{name}: axis {axis}: {e}")))?;
                }
                self.input_shaper = Some(s);
                return Ok(Applied::Report(CommandText::new(&s.report())));
            }
            "SET_RETRACTION" => {
                let r = &mut self.retract;
                let new = Retraction {
                    retract_length: non_neg("RETRACT_LENGTH")?.unwrap_or(r.retract_length),
                    retract_speed: positive("RETRACT_SPEED")?.unwrap_or(r.retract_speed),
                    unretract_extra_length: non_neg("UNRETRACT_EXTRA_LENGTH")?
                        .unwrap_or(r.unretract_extra_length),
                    unretract_speed: positive("UNRETRACT_SPEED")?.unwrap_or(r.unretract_speed),
                };
                self.retract = new;
            }
            "SAVE_GCODE_STATE" => {
                let state_name = p.get("NAME").unwrap_or("default");
                let state = SavedState {
                    absolute_coord: self.absolute_coord,
                    absolute_extrude: self.absolute_extrude,
                    base: self.base,
                    last: self.last,
                    speed: self.speed,
                    speed_factor: self.speed_factor,
                    extrude_factor: self.extrude_factor,
                };
                match self.saved_states.iter_mut().find(|(n, _)| n == state_name) {
                    Some((_, slot)) => *slot = state,
                    None => self.saved_states.push((state_name.to_string(), state)),
                }
            }
            "RESTORE_GCODE_STATE" => {
                // Klipper's gcode_move: the modes, G92 offsets, speed and factors come back; E
                // keeps reading as it did when saved; MOVE=1 returns to the saved X, Y, Z.
                let state_name = p.get("NAME").unwrap_or("default");
                let Some(&(_, state)) = self.saved_states.iter().find(|(n, _)| n == state_name) else {
                    return Err(PlanErrorKind::BadParameter(format!(
                        "Unknown g-code state: {state_name}"
                    )));
                };
                let move_back = num("MOVE")?.is_some_and(|m| m != 0.0);
                let move_speed = positive("MOVE_SPEED")?;
                self.absolute_coord = state.absolute_coord;
                self.absolute_extrude = state.absolute_extrude;
                self.base = state.base;
                self.base[3] += self.last[3] - state.last[3];
                self.speed = state.speed;
                self.speed_factor = state.speed_factor;
                self.extrude_factor = state.extrude_factor;
                if move_back {
                    // MOVE_SPEED is the toolhead's own speed: undo the M220 factor move_to
                    // applies (the restored G-code speed takes it, as a G1 would).
                    let speed = move_speed.map_or(self.speed, |v| v / self.speed_factor);
                    let next = [state.last[0], state.last[1], state.last[2], self.last[3]];
                    self.move_to(next, speed, th)?;
                }
            }
            "G10" | "G11" => {
                let retract = name == "G10";
                if retract != self.retracted {
                    let r = self.retract;
                    let (de, v) = if retract {
                        (-r.retract_length, r.retract_speed)
                    } else {
                        (r.retract_length + r.unretract_extra_length, r.unretract_speed)
                    };
                    let mut next = self.last;
                    next[3] += de;
                    self.move_to(next, v, th)?;
                    self.retracted = retract;
                }
            }
            _ => return self.unknown(name),
        }
        Ok(Applied::Done)
    }

    /// Whether [`Self::other`] implements `name` (`SET_INPUT_SHAPER` only with a shaper).
    fn knows(&self, name: &str) -> bool {
        KNOWN_OTHER.contains(&name) || (name == "SET_INPUT_SHAPER" && self.input_shaper.is_some())
    }

    /// An unknown command: an error in strict mode, else [`Applied::Unsupported`].
    fn unknown(&self, name: &str) -> Result<Applied, PlanErrorKind> {
        match self.unknown_is_error {
            true => Err(PlanErrorKind::UnknownCommand(name.to_string())),
            false => Ok(Applied::Unsupported(CommandName::new(name))),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gcode::parse_line;
    use crate::toolhead::{Move, ToolheadConfig};

    fn run(lines: &[&str]) -> (GcodeState, Toolhead, Vec<Result<Applied, PlanError>>) {
        let mut st = GcodeState::new([0.0, 0.0, 0.5]);
        st.set_extruders(Extruders::new(
            1,
            vec![crate::extruders::ExtruderStepper {
                name: "extruder".into(),
                queue: Some(0),
                pressure_advance: (0.0, 0.04),
                rotation_distance: 33.5,
            }],
        ));
        let mut th = Toolhead::new(ToolheadConfig::default(), 0.0);
        let mut results = Vec::new();
        for (i, l) in lines.iter().enumerate() {
            if let Some(cmd) = parse_line(i + 1, l.as_bytes()).unwrap() {
                results.push(st.apply(&GcodeLine { line_no: i + 1, cmd }, &mut th));
            }
        }
        th.flush();
        (st, th, results)
    }

    fn moves(th: &mut Toolhead) -> Vec<Move> {
        let mut v = Vec::new();
        th.take_moves(&mut v);
        v
    }

    #[test]
    fn absolute_relative_and_offsets() {
        let (st, mut th, res) = run(&[
            "G28",
            "G1 X10 Y10 Z1 F6000",
            "M83",
            "G1 X20 E1",
            "G1 X30 E1",
            "G92 E0",
            "M82",
            "G1 X40 E5",
            "G91",
            "G1 X-5 Y2 E0.5",
            "G90",
            "G92 X0",
            "G1 X10",
        ]);
        assert!(res.iter().all(|r| r == &Ok(Applied::Done)), "{res:?}");
        let m = moves(&mut th);
        let ends: Vec<[f64; 4]> = m.iter().map(|m| m.end_pos).collect();
        assert_eq!(ends[0], [10.0, 10.0, 1.0, 0.0]);
        assert_eq!(ends[1], [20.0, 10.0, 1.0, 1.0]);
        assert_eq!(ends[2], [30.0, 10.0, 1.0, 2.0]);
        assert_eq!(ends[3], [40.0, 10.0, 1.0, 7.0]);
        assert_eq!(ends[4], [35.0, 12.0, 1.0, 7.5]);
        assert_eq!(ends[5], [45.0, 12.0, 1.0, 7.5]);
        assert_eq!(st.gcode_position(), [10.0, 12.0, 1.0, 5.5]);
        assert!((m[0].cruise_v - 100.0).abs() < 1e-9);
    }

    #[test]
    fn homing_sets_position_without_motion() {
        let (st, mut th, res) = run(&["G28 X0 Y0", "G28 Z", "G1 Z5"]);
        assert!(res.iter().all(|r| r.is_ok()));
        assert_eq!(st.homed(), [true, true, true]);
        let m = moves(&mut th);
        assert_eq!(m.len(), 1);
        assert_eq!(m[0].start_pos, [0.0, 0.0, 0.5, 0.0]);
    }

    #[test]
    fn errors_and_unsupported() {
        let (_, _, res) = run(&["G1 X10", "G28", "G1 X500", "G1 F0", "M104 S200", "G20", "G21"]);
        assert_eq!(
            res[0],
            Err(PlanError {
                line: 1,
                kind: PlanErrorKind::NotHomed { axis: 'X' }
            })
        );
        assert!(matches!(
            res[2],
            Err(PlanError {
                line: 3,
                kind: PlanErrorKind::Move(MoveError::OutOfRange { .. })
            })
        ));
        assert!(matches!(
            res[3],
            Err(PlanError {
                kind: PlanErrorKind::BadFeedrate(_),
                ..
            })
        ));
        assert_eq!(
            res[4],
            Ok(Applied::Heater {
                heater: HeaterId::Extruder(0),
                target: 200.0,
                wait: false
            })
        );
        assert!(matches!(
            res[5],
            Err(PlanError {
                kind: PlanErrorKind::Inches,
                ..
            })
        ));
        assert_eq!(res[6], Ok(Applied::Done));
        let e = res[2].clone().unwrap_err();
        assert_eq!(
            e.to_string(),
            "line 3: Move out of range: X=500.000 Y=0.000 Z=0.500 [E=0.000]"
        );
    }

    #[test]
    fn extrude_only_without_homing_is_fine() {
        let (_, mut th, res) = run(&["G1 E5 F300", "G4 P100", "M400"]);
        assert!(res.iter().all(|r| r.is_ok()));
        let m = moves(&mut th);
        assert_eq!(m.len(), 1);
        assert!(m[0].cruise_v <= 5.0 + 1e-9);
    }

    #[test]
    fn arcs_follow_the_circle() {
        for (g, side) in [("G2", 1.0), ("G3", -1.0)] {
            let l = format!("{g} X30 Y10 I10 J0 F3000");
            let (_, mut th, res) = run(&["G28", "G1 X10 Y10 F6000", &l]);
            assert!(res.iter().all(|r| r == &Ok(Applied::Done)), "{res:?}");
            let m = moves(&mut th);
            // ⌊π·10 / 1 mm⌋ chords after the first line.
            assert_eq!(m.len(), 1 + 31);
            for mv in &m[1..] {
                let r = (mv.end_pos[0] - 20.0).hypot(mv.end_pos[1] - 10.0);
                assert!((r - 10.0).abs() < 1e-9);
            }
            assert_eq!(m.last().unwrap().end_pos, [30.0, 10.0, 0.5, 0.0]);
            // Clockwise from the left goes over the top (y = 20), counter-clockwise under.
            let mid = m[16].end_pos[1];
            assert!((mid - 10.0) * side > 9.0, "{g}: {mid}");
        }
        let (_, _, res) = run(&["G28", "G2 X10 Y0", "G2 X10 Y0 I0.0000001"]);
        assert!(matches!(
            res[1],
            Err(PlanError {
                kind: PlanErrorKind::BadArc(_),
                ..
            })
        ));
        assert!(matches!(
            res[2],
            Err(PlanError {
                kind: PlanErrorKind::BadArc(_),
                ..
            })
        ));
        assert!(parse_line(1, b"G2 X1 Y1 R5").is_err());
    }

    #[test]
    fn full_circle_when_end_is_start() {
        let (_, mut th, res) = run(&["G28", "G1 X50 Y50 F6000", "G3 X50 Y50 I-10 J0 E3"]);
        assert!(res.iter().all(|r| r.is_ok()));
        let m = moves(&mut th);
        assert_eq!(m.len(), 1 + 62);
        assert_eq!(m.last().unwrap().end_pos, [50.0, 50.0, 0.5, 3.0]);
    }

    #[test]
    fn firmware_retraction_and_factors() {
        let (st, mut th, res) = run(&[
            "G28",
            "SET_RETRACTION RETRACT_LENGTH=1.5 RETRACT_SPEED=30 UNRETRACT_EXTRA_LENGTH=0.1",
            "G10",
            "G10",
            "G11",
            "M220 S50",
            "G1 X10 F6000",
            "M221 S50",
            "M83",
            "G1 X20 E2",
        ]);
        assert!(res.iter().all(|r| r == &Ok(Applied::Done)), "{res:?}");
        let m = moves(&mut th);
        assert_eq!(m.len(), 4);
        assert_eq!(m[0].end_pos[3], -1.5);
        assert!((m[1].end_pos[3] - 0.1).abs() < 1e-12);
        assert!(m[2].cruise_v <= 50.0 + 1e-9);
        assert!((m[3].end_pos[3] - 1.1).abs() < 1e-12, "E scaled by M221");
        assert!((st.gcode_position()[3] - 2.1).abs() < 1e-12);
    }

    #[test]
    fn velocity_limits() {
        let (_, mut th, res) = run(&[
            "G28",
            "SET_VELOCITY_LIMIT VELOCITY=40 ACCEL=500 SQUARE_CORNER_VELOCITY=2 MINIMUM_CRUISE_RATIO=0.2",
            "G1 X100 F12000",
            "M204 S800",
            "G1 X0",
        ]);
        assert!(res.iter().all(|r| r == &Ok(Applied::Done)), "{res:?}");
        let m = moves(&mut th);
        assert!(m[0].cruise_v <= 40.0 + 1e-9);
        assert_eq!(m[0].accel, 500.0);
        assert_eq!(m[1].accel, 800.0);
        let (_, _, res) = run(&[
            "SET_VELOCITY_LIMIT VELOCITY=-1",
            "SET_VELOCITY_LIMIT ACCEL=nan",
            "SET_VELOCITY_LIMIT MINIMUM_CRUISE_RATIO=1",
            "M204",
            "G1 F0.001",
            "SET_VELOCITY_LIMIT VELOCITY",
        ]);
        assert!(res.iter().all(|r| r.is_err()), "{res:?}");
    }

    #[test]
    fn host_commands() {
        let (_, _, res) = run(&[
            "M140 S60",
            "M190 S60",
            "M109 S215",
            "M106 S127.5",
            "M107",
            "G28",
            "G1 X5 F3000",
            "M114",
            "M117 Printing benchy",
            "M84",
            "G1 X6",
            "FOO_BAR X=1",
        ]);
        let heater = |heater, target, wait| Ok(Applied::Heater { heater, target, wait });
        assert_eq!(res[0], heater(HeaterId::Bed, 60.0, false));
        assert_eq!(res[1], heater(HeaterId::Bed, 60.0, true));
        assert_eq!(res[2], heater(HeaterId::Extruder(0), 215.0, true));
        assert_eq!(res[3], Ok(Applied::Fan { speed: 0.5 }));
        assert_eq!(res[4], Ok(Applied::Fan { speed: 0.0 }));
        assert_eq!(
            res[7],
            Ok(Applied::Report("X:5.000 Y:0.000 Z:0.500 E:0.000".into()))
        );
        assert_eq!(res[8], Ok(Applied::Message("Printing benchy".into())));
        assert_eq!(res[9], Ok(Applied::MotorsOff));
        assert!(matches!(
            res[10],
            Err(PlanError {
                kind: PlanErrorKind::NotHomed { .. },
                ..
            })
        ));
        assert_eq!(res[11], Ok(Applied::Unsupported("FOO_BAR".into())));
    }

    #[test]
    fn other_extruders_are_refused() {
        let (_, _, res) = run(&[
            "G28",
            "SET_PRESSURE_ADVANCE EXTRUDER=extruder ADVANCE=0.05",
            "SET_PRESSURE_ADVANCE EXTRUDER=extruder1 ADVANCE=0.05",
            "M104 S200 T0",
            "M109 S200 T1",
            "M140 S60",
            "M104 S0 T1",
            "ACTIVATE_EXTRUDER EXTRUDER=extruder1",
            "ACTIVATE_EXTRUDER EXTRUDER=extruder",
        ]);
        assert!(res[1].is_ok() && res[3].is_ok() && res[5].is_ok(), "{res:?}");
        let err = |i: usize| res[i].as_ref().map(|_| ()).unwrap_err().to_string();
        assert_eq!(
            err(2),
            "line 3: SET_PRESSURE_ADVANCE: 'extruder1' is not a valid extruder stepper"
        );
        assert_eq!(err(4), "line 5: M109: T1: Extruder not configured");
        // Turning off an extruder the printer lacks is ignored, as on Klipper.
        assert_eq!(res[6], Ok(Applied::Done));
        assert_eq!(
            err(7),
            "line 8: ACTIVATE_EXTRUDER: The value 'extruder1' is not valid for EXTRUDER"
        );
        assert_eq!(
            res[8],
            Ok(Applied::Report(CommandText::new(
                "Extruder extruder already active"
            )))
        );
    }

    #[test]
    fn an_excluded_objects_moves_are_dropped() {
        let gcode = [
            "G28",
            "G1 X10 Y10 F6000",
            "EXCLUDE_OBJECT_DEFINE NAME=a",
            "EXCLUDE_OBJECT NAME=b",
            "EXCLUDE_OBJECT_START NAME=b",
            "G1 X50 E5",
            "G1 Y50 E10",
            "EXCLUDE_OBJECT_END NAME=b",
            "EXCLUDE_OBJECT_START NAME=a",
            "G1 X50 Y50",
            "G1 X60 E11",
            "EXCLUDE_OBJECT_END",
        ];
        let mut st = GcodeState::new([0.0, 0.0, 0.5]);
        st.set_exclude_object(true);
        let mut th = Toolhead::new(ToolheadConfig::default(), 0.0);
        for (i, l) in gcode.iter().enumerate() {
            let cmd = parse_line(i + 1, l.as_bytes()).unwrap().unwrap();
            st.apply(&GcodeLine { line_no: i + 1, cmd }, &mut th).unwrap();
        }
        th.flush();
        let ends: Vec<[f64; 4]> = moves(&mut th).iter().map(|m| m.end_pos).collect();
        // B's moves are gone; A's first move (to where B ended) is made from X10 Y10, and its
        // extrusion is only its own 1 mm.
        assert_eq!(
            ends,
            [
                [10.0, 10.0, 0.5, 0.0],
                [50.0, 50.0, 0.5, 0.0],
                [60.0, 50.0, 0.5, 1.0]
            ]
        );
        assert_eq!(st.gcode_position()[3], 11.0);
        // Without the section they are unknown commands, as on Klipper.
        let (_, _, res) = run(&["EXCLUDE_OBJECT_START NAME=a"]);
        assert_eq!(res[0], Ok(Applied::Unsupported("EXCLUDE_OBJECT_START".into())));
    }

    #[test]
    fn save_and_restore_gcode_state() {
        let (st, mut th, res) = run(&[
            "G28",
            "G1 X10 Y10 Z1 E1 F600",
            "SAVE_GCODE_STATE NAME=park",
            "G91",
            "M83",
            "G92 E0",
            "M220 S50",
            "G1 X5 E2 F3000",
            "RESTORE_GCODE_STATE NAME=park MOVE=1 MOVE_SPEED=20",
            "G1 X20 E3",
            "RESTORE_GCODE_STATE NAME=other",
        ]);
        assert!(res[..10].iter().all(|r| r == &Ok(Applied::Done)), "{res:?}");
        assert_eq!(
            res[10],
            Err(PlanError {
                line: 11,
                kind: PlanErrorKind::BadParameter("Unknown g-code state: other".into())
            })
        );
        let m = moves(&mut th);
        let ends: Vec<[f64; 4]> = m.iter().map(|m| m.end_pos).collect();
        // Back at X10 (E stays), at MOVE_SPEED; then absolute again at the saved F600.
        assert_eq!(ends[2], [10.0, 10.0, 1.0, 3.0]);
        assert!((m[2].cruise_v - 20.0).abs() < 1e-9, "{}", m[2].cruise_v);
        assert_eq!(ends[3], [20.0, 10.0, 1.0, 5.0]);
        assert!((m[3].cruise_v - 10.0).abs() < 1e-9);
        assert_eq!(st.gcode_position(), [20.0, 10.0, 1.0, 3.0]);
    }

    #[test]
    fn known_commands_are_the_ones_handled() {
        let src = include_str!("machine.rs");
        let body = &src[src.find("fn other(").unwrap()..src.find("fn knows(").unwrap()];
        let handled: std::collections::BTreeSet<&str> = body
            .lines()
            .map(str::trim_start)
            .filter(|l| l.starts_with('"') && l.contains("=>"))
            .flat_map(|l| l.split("=>").next().unwrap().split('|'))
            .map(|w| w.trim().trim_matches('"'))
            .filter(|w| !w.is_empty() && !w.contains(' ') && *w != "SET_INPUT_SHAPER")
            .collect();
        let known: std::collections::BTreeSet<&str> = KNOWN_OTHER.into_iter().collect();
        assert_eq!(handled, known);
        // An unknown command with text Klipper would not parse as parameters is still just
        // unknown; a known one's bad parameters are errors.
        let (_, _, res) = run(&["M118 layer 1", "M104 S2..5"]);
        assert_eq!(res[0], Ok(Applied::Unsupported("M118".into())));
        assert!(res[1].is_err());
    }

    #[test]
    fn unknown_commands_can_be_errors() {
        let mut st = GcodeState::new([0.0; 3]);
        st.set_unknown_is_error(true);
        let mut th = Toolhead::new(ToolheadConfig::default(), 0.0);
        let cmd = parse_line(7, b"M999 S1").unwrap().unwrap();
        let e = st.apply(&GcodeLine { line_no: 7, cmd }, &mut th).unwrap_err();
        assert_eq!(e.to_string(), "line 7: Unknown command:\"M999\"");
    }

    fn arb_line() -> impl proptest::strategy::Strategy<Value = String> {
        use proptest::prelude::*;
        let num = prop_oneof![
            -1e3f64..1e3,
            Just(0.0),
            Just(1e300),
            Just(-1e-300),
            Just(f64::NAN),
            Just(f64::INFINITY)
        ];
        let cmd = prop_oneof![
            Just("G1"),
            Just("G0"),
            Just("G2"),
            Just("G3"),
            Just("G4"),
            Just("G10"),
            Just("G11"),
            Just("G28"),
            Just("G90"),
            Just("G91"),
            Just("G92"),
            Just("M82"),
            Just("M83"),
            Just("M84"),
            Just("M104"),
            Just("M109"),
            Just("M106"),
            Just("M114"),
            Just("M117"),
            Just("M204"),
            Just("M220"),
            Just("M221"),
            Just("M400"),
            Just("SET_VELOCITY_LIMIT"),
            Just("SET_PRESSURE_ADVANCE"),
            Just("SET_RETRACTION"),
            Just("G20"),
            Just("M999")
        ];
        let word = (
            prop_oneof![
                Just("X"),
                Just("Y"),
                Just("Z"),
                Just("E"),
                Just("F"),
                Just("I"),
                Just("J"),
                Just("S"),
                Just("P"),
                Just("T"),
                Just("VELOCITY="),
                Just("ACCEL="),
                Just("ADVANCE="),
                Just("RETRACT_LENGTH="),
                Just("SQUARE_CORNER_VELOCITY="),
                Just("MINIMUM_CRUISE_RATIO=")
            ],
            num,
        );
        (cmd, proptest::collection::vec(word, 0..5)).prop_map(|(c, words)| {
            let mut l = c.to_string();
            for (w, v) in words {
                l.push_str(&format!(" {w}{v}"));
            }
            l
        })
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig { cases: 256, ..Default::default() })]

        /// Any sequence of (possibly absurd) commands: errors, never panics, and the toolhead
        /// keeps producing finite moves.
        #[test]
        fn command_soup_never_panics(lines in proptest::collection::vec(arb_line(), 1..30)) {
            let mut st = GcodeState::new([0.0, 0.0, 0.5]);
            let mut th = Toolhead::new(ToolheadConfig::default(), 0.0);
            for (i, l) in lines.iter().enumerate() {
                if let Ok(Some(cmd)) = parse_line(i + 1, l.as_bytes()) {
                    let _ = st.apply(&GcodeLine { line_no: i + 1, cmd }, &mut th);
                }
            }
            th.flush();
            for m in moves(&mut th) {
                proptest::prop_assert!(m.end_time().is_finite() && m.move_d.is_finite());
            }
        }
    }
}
