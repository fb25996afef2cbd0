//! Modal G-code state applied to a [`Toolhead`]: absolute/relative coordinates (G90/G91),
//! absolute/relative extrusion (M82/M83), G92 offsets, the feedrate and the homed axes.
//!
//! Coordinates (Klipper's G-code move semantics): the toolhead position of an axis is the
//! G-code value plus that axis's G92 offset (`base`). In relative mode a value adds to the last
//! commanded position. E is relative when either G91 or M83 is in force. G92 sets `base` so the
//! current position reads as the given value (no argument: every axis reads 0). Feedrate F is in
//! mm/min; the toolhead gets mm/s. G28 does no motion yet: it declares the named axes (all if
//! none) homed at the configured `home_position`.

use crate::gcode::{Command, GcodeLine};
use crate::toolhead::{MoveError, Toolhead, AXIS_NAMES};

/// Speed before any F word (mm/s), as Klipper.
const DEFAULT_SPEED: f64 = 25.0;

/// What [`GcodeState::apply`] did with a line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Applied {
    Done,
    /// A well-formed command the planner does not implement; the caller warns once per name.
    Unsupported(String),
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
        }
    }

    /// Axes homed so far (X, Y, Z).
    pub fn homed(&self) -> [bool; 3] {
        self.homed
    }

    /// Declares axes homed without a G28 (e.g. a printer without endstops, tests).
    pub fn set_homed(&mut self, homed: [bool; 3]) {
        self.homed = homed;
    }

    /// The position as G-code reads it (toolhead position minus the G92 offsets).
    pub fn gcode_position(&self) -> [f64; 4] {
        let mut p = self.last;
        for (p, b) in p.iter_mut().zip(self.base) {
            *p -= b;
        }
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
                if let Some(f) = *f {
                    if f <= 0.0 {
                        return Err(err(PlanErrorKind::BadFeedrate(f)));
                    }
                }
                let mut next = self.last;
                for (i, v) in [x, y, z].into_iter().enumerate() {
                    if let Some(v) = *v {
                        next[i] = if self.absolute_coord {
                            v + self.base[i]
                        } else {
                            self.last[i] + v
                        };
                    }
                }
                if let Some(v) = *e {
                    next[3] = if self.absolute_coord && self.absolute_extrude {
                        v + self.base[3]
                    } else {
                        self.last[3] + v
                    };
                }
                let speed = f.map_or(self.speed, |f| f / 60.0);
                if next != self.last {
                    for axis in 0..3 {
                        if next[axis] != self.last[axis] && !self.homed[axis] {
                            return Err(err(PlanErrorKind::NotHomed {
                                axis: AXIS_NAMES[axis],
                            }));
                        }
                    }
                    th.move_to(next, speed).map_err(|e| err(e.into()))?;
                    self.last = next;
                }
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
                self.last = th.position();
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
                            self.base[i] = self.last[i] - v;
                        }
                    }
                }
            }
            Command::Dwell { seconds } => th.dwell(*seconds).map_err(|e| err(e.into()))?,
            Command::WaitMoves => th.flush(),
            Command::Other { name, .. } => match name.as_str() {
                "G21" => {}
                "G20" => return Err(err(PlanErrorKind::Inches)),
                _ => return Ok(Applied::Unsupported(name.clone())),
            },
        }
        Ok(Applied::Done)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gcode::parse_line;
    use crate::toolhead::{Move, ToolheadConfig};

    fn run(lines: &[&str]) -> (GcodeState, Toolhead, Vec<Result<Applied, PlanError>>) {
        let mut st = GcodeState::new([0.0, 0.0, 0.5]);
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
        assert_eq!(res[4], Ok(Applied::Unsupported("M104".into())));
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
}
