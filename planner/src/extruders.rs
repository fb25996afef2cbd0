//! Several extruders as Klipper runs them: which extruder is active, the E position each one
//! left off at, which extruder's motion each extruder stepper follows, and the commands that
//! change them (ACTIVATE_EXTRUDER, SYNC_EXTRUDER_MOTION, SET_PRESSURE_ADVANCE EXTRUDER=,
//! SET_EXTRUDER_ROTATION_DISTANCE).
//!
//! Klipper's model: each `[extruderN]` owns a motion queue; the toolhead's E moves go to the
//! active extruder's queue only. A stepper (the extruder's own, or an `[extruder_stepper]`)
//! follows one queue or none; the steppers following an inactive queue do not move. Activating
//! an extruder first brings the toolhead to rest, keeps the old extruder's E position and
//! continues from the new one's (its `last_position`); the G-code E then reads 0 (gcode_move
//! rebases E on the event). Extruder `k` is named `extruder` (k = 0) or `extruderK`.

use crate::gcode::OtherParams;

/// Most extruders a printer may have here (`extruder` … `extruder9`).
pub const MAX_EXTRUDERS: usize = 10;

/// The names of extruders 0..[`MAX_EXTRUDERS`].
pub const EXTRUDER_NAMES: [&str; MAX_EXTRUDERS] = [
    "extruder",
    "extruder1",
    "extruder2",
    "extruder3",
    "extruder4",
    "extruder5",
    "extruder6",
    "extruder7",
    "extruder8",
    "extruder9",
];

/// The index of the extruder named `name` (`extruder` → 0, `extruder2` → 2).
pub fn extruder_index(name: &str) -> Option<usize> {
    EXTRUDER_NAMES.iter().position(|n| *n == name)
}

/// The commands this module answers.
pub const EXTRUDER_COMMANDS: [&str; 4] = [
    "ACTIVATE_EXTRUDER",
    "SYNC_EXTRUDER_MOTION",
    "SET_PRESSURE_ADVANCE",
    "SET_EXTRUDER_ROTATION_DISTANCE",
];

/// What an extruder command changes in step generation (the pipeline hands it to the lanes at
/// the next move).
#[derive(Debug, Clone, PartialEq)]
pub enum ExtruderEvent {
    /// Extruder `.0` is active from the next move on (the toolhead was brought to rest).
    Activate(usize),
    /// Stepper `stepper` (an index into [`Extruders::stepper_names`]) follows extruder
    /// `queue`'s motion (or none) from the next move on.
    Sync { stepper: usize, queue: Option<usize> },
    /// Stepper `stepper`'s pressure advance.
    Advance {
        stepper: usize,
        advance: f64,
        smooth_time: f64,
    },
    /// Stepper `stepper`'s rotation distance (mm of filament per turn, the sign flips its
    /// direction): its step distance is `rotation_distance / full_steps_per_rotation`.
    RotationDistance { stepper: usize, distance: f64 },
}

/// One extruder stepper as G-code sees it.
#[derive(Debug, Clone, PartialEq)]
pub struct ExtruderStepper {
    /// Klipper's name: `extruder`, `extruder1`, or an `[extruder_stepper NAME]`'s NAME.
    pub name: String,
    /// The extruder whose motion it follows (`None`: it does not move).
    pub queue: Option<usize>,
    /// (advance, smooth_time) in force.
    pub pressure_advance: (f64, f64),
    /// Rotation distance in force (mm; negative: direction inverted against the config).
    pub rotation_distance: f64,
}

/// The printer's extruders and extruder steppers.
#[derive(Debug, Clone, PartialEq)]
pub struct Extruders {
    /// E position (toolhead coordinates) each extruder left off at.
    last_e: Vec<f64>,
    active: usize,
    steppers: Vec<ExtruderStepper>,
}

impl Default for Extruders {
    /// One extruder, no steppers known (commands naming none are refused).
    fn default() -> Self {
        Extruders::new(1, Vec::new())
    }
}

impl Extruders {
    /// `count` extruders (at least 1, at most [`MAX_EXTRUDERS`]), extruder 0 active, and
    /// their steppers.
    pub fn new(count: usize, steppers: Vec<ExtruderStepper>) -> Extruders {
        Extruders {
            last_e: vec![0.0; count.clamp(1, MAX_EXTRUDERS)],
            active: 0,
            steppers,
        }
    }

    /// The active extruder's index.
    pub fn active(&self) -> usize {
        self.active
    }

    /// How many extruders there are.
    pub fn count(&self) -> usize {
        self.last_e.len()
    }

    /// The steppers, in the order [`ExtruderEvent`] indexes them.
    pub fn steppers(&self) -> &[ExtruderStepper] {
        &self.steppers
    }

    /// The index of the stepper named `name`.
    fn stepper(&self, name: &str) -> Result<usize, String> {
        self.steppers
            .iter()
            .position(|s| s.name == name)
            .ok_or_else(|| format!("'{name}' is not a valid extruder stepper"))
    }

    /// ACTIVATE_EXTRUDER: `current_e` is the toolhead's E now (the old extruder's position).
    /// Returns the new E position and the event, or `None` when `name` is active already;
    /// the text Klipper answers with comes with it.
    pub fn activate(
        &mut self,
        name: &str,
        current_e: f64,
    ) -> Result<(Option<(f64, ExtruderEvent)>, String), String> {
        let index = extruder_index(name)
            .filter(|&i| i < self.count())
            .ok_or_else(|| format!("The value '{name}' is not valid for EXTRUDER"))?;
        if index == self.active {
            return Ok((None, format!("Extruder {name} already active")));
        }
        self.last_e[self.active] = current_e;
        self.active = index;
        let e = self.last_e[index];
        Ok((
            Some((e, ExtruderEvent::Activate(index))),
            format!("Activating extruder {name}"),
        ))
    }

    /// One of the stepper commands (`name`, parameters `p`): the event and Klipper's answer.
    pub fn command(
        &mut self,
        name: &str,
        p: &OtherParams<'_>,
    ) -> Result<(Option<ExtruderEvent>, String), String> {
        let num = |k: &str| p.float(k).map_err(|e| e.to_string());
        match name {
            "SYNC_EXTRUDER_MOTION" => {
                let stepper = self.stepper(p.get("EXTRUDER").ok_or("missing EXTRUDER")?)?;
                let q = p.get("MOTION_QUEUE").ok_or("missing MOTION_QUEUE")?;
                let queue = match q {
                    "" => None,
                    q => Some(
                        extruder_index(q)
                            .filter(|&i| i < self.count())
                            .ok_or_else(|| format!("'{q}' is not a valid extruder."))?,
                    ),
                };
                let s = &mut self.steppers[stepper];
                s.queue = queue;
                let said = format!("Extruder '{}' now syncing with '{q}'", s.name);
                Ok((Some(ExtruderEvent::Sync { stepper, queue }), said))
            }
            "SET_PRESSURE_ADVANCE" => {
                let stepper = match p.get("EXTRUDER") {
                    Some(e) => self.stepper(e)?,
                    // The active extruder's own stepper, which must follow its queue.
                    None => {
                        let own = EXTRUDER_NAMES[self.active];
                        let i = self
                            .stepper(own)
                            .map_err(|_| "Active extruder does not have a stepper".to_string())?;
                        if self.steppers[i].queue != Some(self.active) {
                            return Err("Unable to infer active extruder stepper".into());
                        }
                        i
                    }
                };
                let s = &mut self.steppers[stepper];
                let advance = num("ADVANCE")?.unwrap_or(s.pressure_advance.0);
                let smooth_time = num("SMOOTH_TIME")?.unwrap_or(s.pressure_advance.1);
                if !(0.0..10.0).contains(&advance) {
                    return Err(format!("ADVANCE={advance} must be in 0 .. 10"));
                }
                if !(smooth_time > 0.0 && smooth_time <= 0.2) {
                    return Err(format!(
                        "SMOOTH_TIME={smooth_time} must be above 0 and at most 0.2"
                    ));
                }
                let said =
                    format!("pressure_advance: {advance:.6}\npressure_advance_smooth_time: {smooth_time:.6}");
                if (advance, smooth_time) == s.pressure_advance {
                    return Ok((None, said));
                }
                s.pressure_advance = (advance, smooth_time);
                let event = ExtruderEvent::Advance {
                    stepper,
                    advance,
                    smooth_time,
                };
                Ok((Some(event), said))
            }
            "SET_EXTRUDER_ROTATION_DISTANCE" => {
                let stepper = self.stepper(p.get("EXTRUDER").ok_or("missing EXTRUDER")?)?;
                let s = &mut self.steppers[stepper];
                let event = match num("DISTANCE")? {
                    Some(d) if d == 0.0 || !d.is_finite() => {
                        return Err("Rotation distance can not be zero".into())
                    }
                    Some(d) if d != s.rotation_distance => {
                        s.rotation_distance = d;
                        Some(ExtruderEvent::RotationDistance { stepper, distance: d })
                    }
                    _ => None,
                };
                let said = format!(
                    "Extruder '{}' rotation distance set to {:.6}",
                    s.name, s.rotation_distance
                );
                Ok((event, said))
            }
            _ => Err(format!("{name} is not an extruder command")),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn two() -> Extruders {
        let st = |name: &str, queue| ExtruderStepper {
            name: name.into(),
            queue,
            pressure_advance: (0.0, 0.04),
            rotation_distance: 33.5,
        };
        Extruders::new(
            2,
            vec![st("extruder", Some(0)), st("extruder1", Some(1)), st("e2", None)],
        )
    }

    fn cmd(x: &mut Extruders, text: &str) -> Result<(Option<ExtruderEvent>, String), String> {
        let name = text.split_whitespace().next().unwrap_or("");
        let p = OtherParams::parse(text).map_err(|e| e.to_string())?;
        x.command(name, &p)
    }

    #[test]
    fn activation_keeps_each_extruders_position() {
        let mut x = two();
        let (got, said) = x.activate("extruder1", 12.5).unwrap();
        assert_eq!(got, Some((0.0, ExtruderEvent::Activate(1))));
        assert_eq!(said, "Activating extruder extruder1");
        assert_eq!(
            x.activate("extruder1", 3.0).unwrap().1,
            "Extruder extruder1 already active"
        );
        let (got, _) = x.activate("extruder", 3.0).unwrap();
        assert_eq!(got, Some((12.5, ExtruderEvent::Activate(0))));
        assert!(x.activate("extruder2", 0.0).is_err());
        assert!(x.activate("bogus", 0.0).is_err());
    }

    #[test]
    fn sync_and_advance() {
        let mut x = two();
        let (ev, said) = cmd(&mut x, "SYNC_EXTRUDER_MOTION EXTRUDER=e2 MOTION_QUEUE=extruder1").unwrap();
        assert_eq!(
            ev,
            Some(ExtruderEvent::Sync {
                stepper: 2,
                queue: Some(1)
            })
        );
        assert_eq!(said, "Extruder 'e2' now syncing with 'extruder1'");
        assert!(cmd(&mut x, "SYNC_EXTRUDER_MOTION EXTRUDER=e2 MOTION_QUEUE=extruder7").is_err());
        assert!(cmd(&mut x, "SYNC_EXTRUDER_MOTION EXTRUDER=nope MOTION_QUEUE=extruder").is_err());
        let (ev, _) = cmd(&mut x, "SET_PRESSURE_ADVANCE EXTRUDER=extruder1 ADVANCE=0.05").unwrap();
        assert_eq!(
            ev,
            Some(ExtruderEvent::Advance {
                stepper: 1,
                advance: 0.05,
                smooth_time: 0.04
            })
        );
        // Without EXTRUDER: the active extruder's stepper.
        let (ev, _) = cmd(&mut x, "SET_PRESSURE_ADVANCE ADVANCE=0.02").unwrap();
        assert!(matches!(ev, Some(ExtruderEvent::Advance { stepper: 0, .. })));
        assert!(cmd(&mut x, "SET_PRESSURE_ADVANCE ADVANCE=0.02 SMOOTH_TIME=0.5").is_err());
        let (ev, said) = cmd(&mut x, "SET_EXTRUDER_ROTATION_DISTANCE EXTRUDER=e2 DISTANCE=-20").unwrap();
        assert_eq!(
            ev,
            Some(ExtruderEvent::RotationDistance {
                stepper: 2,
                distance: -20.0
            })
        );
        assert_eq!(said, "Extruder 'e2' rotation distance set to -20.000000");
        assert!(cmd(&mut x, "SET_EXTRUDER_ROTATION_DISTANCE EXTRUDER=e2 DISTANCE=0").is_err());
    }
}
