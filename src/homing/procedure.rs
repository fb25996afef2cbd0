//! G28 as printer.cfg asks for it (Klipper's behaviour, from its config reference):
//! - `[homing_override]`: a G28 naming one of its `axes` (a bare G28 names all) assumes the
//!   `set_position_*` positions (those axes count as homed), then runs the override script
//!   with the G28's parameters; a G28 inside the script is the printer's own. A G28 naming
//!   none of its axes homes normally.
//! - `[safe_z_home]`: with `z_hop`, Z is first lifted by `z_hop` when not homed (its position
//!   taken as 0 for the lift, then unhomed again) or up to `z_hop` when homed below it; X and
//!   Y home (those asked for); then, for Z, X and Y must be homed ("Must home X and Y axes
//!   first"), the toolhead moves to `home_xy_position` at `speed`, Z homes, Z is lifted to
//!   `z_hop` again if below it, and with `move_to_previous` X and Y return to where they were.
//!
//! Pure sequencing over [`HomeOps`] (the G-code feed supplies the planner, the printer's own
//! G28 and the script runner), so the same procedure runs in batch and live prints and is
//! tested here with a recording printer.

use sysconfig::printer::{HomingOverrideSection, SafeZHomeSection};

/// How G28 runs on this printer.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct HomingProcedure {
    pub safe_z_home: Option<SafeZHomeSection>,
    pub homing_override: Option<HomingOverrideSection>,
    /// `[probe] activate_gcode` / `deactivate_gcode` around each probing session.
    pub probe_scripts: ProbeScripts,
}

/// The commands that probe (each one probing session): a Z homing on the probe is one too.
pub const PROBING_COMMANDS: [&str; 7] = [
    "PROBE",
    "PROBE_ACCURACY",
    "PROBE_CALIBRATE",
    "BED_MESH_CALIBRATE",
    "Z_TILT_ADJUST",
    "QUAD_GANTRY_LEVEL",
    "SCREWS_TILT_CALCULATE",
];

/// `[probe]`'s scripts run around each probing session (Klipper's `activate_gcode` before
/// the probe is used, `deactivate_gcode` after), as the macros
/// [`sysconfig::printer::PROBE_ACTIVATE_MACRO`] and
/// [`sysconfig::printer::PROBE_DEACTIVATE_MACRO`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ProbeScripts {
    /// There is an `activate_gcode`.
    pub activate: bool,
    /// There is a `deactivate_gcode`.
    pub deactivate: bool,
    /// Z homes on the probe (`probe:z_virtual_endstop`): a G28 of Z is a probing session.
    pub z_on_probe: bool,
}

impl ProbeScripts {
    /// Whether a command `name` (a G28 of `home` when it is one) is a probing session that
    /// has a script to run.
    pub fn around(&self, name: &str, home: Option<[bool; 3]>) -> bool {
        if !(self.activate || self.deactivate) {
            return false;
        }
        match home {
            Some(axes) => self.z_on_probe && (axes[2] || axes == [false; 3]),
            None => PROBING_COMMANDS.contains(&name),
        }
    }
}

/// Why the procedure itself refused to go on.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProcedureError {
    /// `[safe_z_home]`: Z homes only after X and Y.
    #[error("Must home X and Y axes first")]
    XyNotHomed,
}

/// What the procedure needs of the printer.
pub(crate) trait HomeOps {
    /// Why one of the printer's operations failed (the procedure's own errors too).
    type Error;
    /// Homed X, Y, Z.
    fn homed(&self) -> [bool; 3];
    /// Toolhead X, Y, Z, E.
    fn position(&self) -> [f64; 4];
    /// Redefines the toolhead position and the homed axes without moving.
    fn set_position(&mut self, pos: [f64; 4], homed: [bool; 3]);
    /// The printer's own G28 of `axes`.
    fn home(&mut self, axes: [bool; 3]) -> Result<(), Self::Error>;
    /// A toolhead move (toolhead coordinates, not G-code ones) to `pos` at `speed` mm/s.
    fn move_to(&mut self, pos: [f64; 4], speed: f64) -> Result<(), Self::Error>;
    /// Runs the `[homing_override]` script with the G28's raw parameters.
    fn run_override(&mut self, rawparams: &str) -> Result<(), Self::Error>;
    /// The procedure's own error `why`, located as the printer reports errors.
    fn fail(&self, why: ProcedureError) -> Self::Error;
}

impl HomingProcedure {
    /// True when G28 runs anything but the printer's own homing.
    pub fn is_custom(&self) -> bool {
        self.safe_z_home.is_some() || self.homing_override.is_some()
    }

    /// A G28 naming `axes` (X, Y, Z; a bare G28 names all three).
    pub(crate) fn g28<O: HomeOps>(&self, axes: [bool; 3], ops: &mut O) -> Result<(), O::Error> {
        if let Some(o) = &self.homing_override {
            let overridden = !axes.iter().any(|&a| a) || (0..3).any(|a| axes[a] && o.axes[a]);
            if overridden {
                let mut pos = ops.position();
                let mut homed = ops.homed();
                for (a, at) in o.set_position.iter().enumerate() {
                    if let Some(v) = *at {
                        pos[a] = v;
                        homed[a] = true;
                    }
                }
                ops.set_position(pos, homed);
                // The script sees the G28's own parameters, as on Klipper: none for a bare
                // G28 (which the parser reads as all three axes), else the axes it names.
                let rawparams: Vec<&str> = match axes {
                    [true, true, true] => Vec::new(),
                    _ => ["X", "Y", "Z"]
                        .iter()
                        .zip(axes)
                        .filter(|(_, on)| *on)
                        .map(|(n, _)| *n)
                        .collect(),
                };
                return ops.run_override(&rawparams.join(" "));
            }
            return ops.home(axes);
        }
        match &self.safe_z_home {
            Some(s) => safe_z_home(s, axes, ops),
            None => ops.home(axes),
        }
    }
}

fn safe_z_home<O: HomeOps>(s: &SafeZHomeSection, axes: [bool; 3], ops: &mut O) -> Result<(), O::Error> {
    if s.z_hop != 0.0 {
        let mut pos = ops.position();
        let mut homed = ops.homed();
        if !homed[2] {
            pos[2] = 0.0;
            homed[2] = true;
            ops.set_position(pos, homed);
            lift(s, ops, pos)?;
            homed[2] = false;
            let now = ops.position();
            ops.set_position(now, homed);
        } else if pos[2] < s.z_hop {
            lift(s, ops, pos)?;
        }
    }
    let need = if axes.iter().any(|&a| a) { axes } else { [true; 3] };
    if need[0] || need[1] {
        ops.home([need[0], need[1], false])?;
    }
    if need[2] {
        let homed = ops.homed();
        if !(homed[0] && homed[1]) {
            return Err(ops.fail(ProcedureError::XyNotHomed));
        }
        let previous = ops.position();
        let mut pos = previous;
        pos[0] = s.home_xy_position[0];
        pos[1] = s.home_xy_position[1];
        ops.move_to(pos, s.speed)?;
        ops.home([false, false, true])?;
        if s.z_hop != 0.0 {
            let pos = ops.position();
            if pos[2] < s.z_hop {
                lift(s, ops, pos)?;
            }
        }
        if s.move_to_previous {
            let mut pos = ops.position();
            pos[0] = previous[0];
            pos[1] = previous[1];
            ops.move_to(pos, s.speed)?;
        }
    }
    Ok(())
}

/// Moves Z to `z_hop` from `pos` at `z_hop_speed`.
fn lift<O: HomeOps>(s: &SafeZHomeSection, ops: &mut O, mut pos: [f64; 4]) -> Result<(), O::Error> {
    pos[2] = s.z_hop;
    ops.move_to(pos, s.z_hop_speed)
}

#[cfg(test)]
mod tests {
    use super::*;
    use planner::gcode::macros::MacroDef;

    /// A printer that records what it is asked: homing puts an axis at its endstop (0 for X
    /// and Y, 0.5 for Z).
    #[derive(Default)]
    struct Recorder {
        pos: [f64; 4],
        homed: [bool; 3],
        log: Vec<String>,
    }

    impl HomeOps for Recorder {
        type Error = ProcedureError;
        fn homed(&self) -> [bool; 3] {
            self.homed
        }
        fn position(&self) -> [f64; 4] {
            self.pos
        }
        fn set_position(&mut self, pos: [f64; 4], homed: [bool; 3]) {
            self.log.push(format!("set {:?} {:?}", &pos[..3], homed));
            self.pos = pos;
            self.homed = homed;
        }
        fn home(&mut self, axes: [bool; 3]) -> Result<(), Self::Error> {
            self.log.push(format!("home {axes:?}"));
            for (a, at) in [0.0, 0.0, 0.5].into_iter().enumerate() {
                if axes[a] {
                    self.pos[a] = at;
                    self.homed[a] = true;
                }
            }
            Ok(())
        }
        fn move_to(&mut self, pos: [f64; 4], speed: f64) -> Result<(), Self::Error> {
            self.log.push(format!("move {:?} at {speed}", &pos[..3]));
            self.pos = pos;
            Ok(())
        }
        fn run_override(&mut self, rawparams: &str) -> Result<(), Self::Error> {
            self.log.push(format!("script '{rawparams}'"));
            Ok(())
        }
        fn fail(&self, why: ProcedureError) -> ProcedureError {
            why
        }
    }

    fn safe(z_hop: f64, move_to_previous: bool) -> HomingProcedure {
        HomingProcedure {
            safe_z_home: Some(SafeZHomeSection {
                home_xy_position: [100.0, 120.0],
                speed: 50.0,
                z_hop,
                z_hop_speed: 15.0,
                move_to_previous,
            }),
            homing_override: None,
            probe_scripts: ProbeScripts::default(),
        }
    }

    fn run(p: &HomingProcedure, r: &mut Recorder, axes: [bool; 3]) -> Result<Vec<String>, ProcedureError> {
        r.log.clear();
        p.g28(axes, r)?;
        Ok(r.log.clone())
    }

    #[test]
    fn safe_z_home_lifts_homes_xy_then_z_at_the_safe_spot() {
        let p = safe(10.0, false);
        let mut r = Recorder {
            pos: [30.0, 40.0, 3.0, 0.0],
            ..Recorder::default()
        };
        let log = run(&p, &mut r, [true; 3]).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            log,
            [
                "set [30.0, 40.0, 0.0] [false, false, true]",
                "move [30.0, 40.0, 10.0] at 15",
                "set [30.0, 40.0, 10.0] [false, false, false]",
                "home [true, true, false]",
                "move [100.0, 120.0, 10.0] at 50",
                "home [false, false, true]",
                "move [100.0, 120.0, 10.0] at 15",
            ]
        );
        // Homed Z above z_hop: no lift; below: up to z_hop.
        r.pos[2] = 12.0;
        let log = run(&p, &mut r, [false, false, true]).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(log[0], "move [100.0, 120.0, 12.0] at 50");
        r.pos[2] = 4.0;
        let log = run(&p, &mut r, [true, false, false]).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            log,
            ["move [100.0, 120.0, 10.0] at 15", "home [true, false, false]"]
        );
    }

    #[test]
    fn safe_z_home_needs_x_and_y_and_can_return_to_the_previous_xy() {
        let p = safe(0.0, true);
        let mut r = Recorder::default();
        assert_eq!(
            run(&p, &mut r, [false, false, true]),
            Err(ProcedureError::XyNotHomed)
        );
        r.homed = [true, true, false];
        r.pos = [5.0, 6.0, 7.0, 0.0];
        let log = run(&p, &mut r, [false, false, true]).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            log,
            [
                "move [100.0, 120.0, 7.0] at 50",
                "home [false, false, true]",
                "move [5.0, 6.0, 0.5] at 50",
            ]
        );
    }

    #[test]
    fn probing_sessions_are_the_probing_commands_and_a_z_homing_on_the_probe() {
        let s = ProbeScripts {
            activate: true,
            deactivate: false,
            z_on_probe: true,
        };
        assert!(s.around("PROBE", None) && s.around("BED_MESH_CALIBRATE", None));
        assert!(!s.around("QUERY_PROBE", None) && !s.around("BED_MESH_PROFILE", None));
        assert!(s.around("G28", Some([false; 3])) && s.around("G28", Some([false, false, true])));
        assert!(!s.around("G28", Some([true, true, false])));
        let off_probe = ProbeScripts {
            z_on_probe: false,
            ..s
        };
        assert!(!off_probe.around("G28", Some([false; 3])));
        assert!(!ProbeScripts::default().around("PROBE", None));
    }

    #[test]
    fn homing_override_runs_its_script_for_its_axes_only() {
        let p = HomingProcedure {
            safe_z_home: None,
            homing_override: Some(HomingOverrideSection {
                axes: [false, false, true],
                set_position: [None, None, Some(0.0)],
                script: MacroDef {
                    name: "homing_override".into(),
                    gcode: "G28".into(),
                    description: None,
                    rename_existing: None,
                    variables: Vec::new(),
                    at: "printer.cfg:1".into(),
                },
            }),
            probe_scripts: ProbeScripts::default(),
        };
        let mut r = Recorder {
            pos: [1.0, 2.0, 3.0, 0.0],
            ..Recorder::default()
        };
        let log = run(&p, &mut r, [true; 3]).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(log, ["set [1.0, 2.0, 0.0] [false, false, true]", "script ''"]);
        let log = run(&p, &mut r, [false, false, true]).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(log, ["set [1.0, 2.0, 0.0] [false, false, true]", "script 'Z'"]);
        let log = run(&p, &mut r, [true, false, false]).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(log, ["home [true, false, false]"]);
    }
}
