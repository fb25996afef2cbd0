//! `[stepper_*]` rails: the motor (pins and step distance) plus the axis range and homing.
//!
//! Step distance, in mm per (micro)step:
//! `step_dist = rotation_distance / (full_steps_per_rotation · microsteps · gear_ratio)`,
//! where `gear_ratio` is the product of `a/b` over the `a:b` pairs (`"80:16, 3:1"` → 15).
//! E.g. 40 mm per rotation, 200 full steps, 16 microsteps: 1/80 mm.
//!
//! Homing direction, when `homing_positive_dir` is absent: towards position_min if the endstop
//! lies in the first quarter of the axis, towards position_max if in the last quarter, otherwise
//! it cannot be inferred. When given, it may not point away from an endstop sitting exactly at
//! position_min or position_max.

use super::error::{ConfigError, ValueProblem};
use super::pins::{PinKind, PinRef, PinRegistry, Share};
use super::probe::{ProbeSection, PROBE_PIN_MCU};
use super::reader::{parse_float, Bounds, SectionReader};

/// One linear-axis stepper (`stepper_x` …).
#[derive(Debug, Clone, PartialEq)]
pub struct StepperSection {
    /// Section name: `stepper_x`.
    pub name: String,
    /// Pins, microstepping and gearing.
    pub motor: MotorSection,
    pub endstop_pin: Option<PinRef>,
    /// Required when `endstop_pin` is set; within [position_min, position_max]. With
    /// `endstop_pin: probe:z_virtual_endstop`: the `[probe] z_offset`.
    pub position_endstop: Option<f64>,
    /// Default 0.
    pub position_min: f64,
    /// Required, > position_min.
    pub position_max: f64,
    /// mm/s, > 0; default 5.
    pub homing_speed: f64,
    /// mm/s, > 0; default `homing_speed`.
    pub homing_retract_speed: f64,
    /// mm, ≥ 0; default 5.
    pub homing_retract_dist: f64,
    /// mm/s, > 0; default `homing_speed / 2`.
    pub second_homing_speed: f64,
    /// Given, or inferred from where position_endstop lies (see the module docs).
    pub homing_positive_dir: bool,
}

impl StepperSection {
    /// mm per step (see the module docs).
    pub fn step_dist(&self) -> f64 {
        self.motor.step_dist()
    }
}

/// The motor options of a rail (`[stepper_*]`) or of the `[extruder]`.
#[derive(Debug, Clone, PartialEq)]
pub struct MotorSection {
    pub step_pin: PinRef,
    /// On the same MCU as `step_pin`.
    pub dir_pin: PinRef,
    pub enable_pin: Option<PinRef>,
    /// ≥ 1.
    pub microsteps: u32,
    /// mm of travel (or of filament) per full rotation, > 0.
    pub rotation_distance: f64,
    /// Multiple of 4; default 200.
    pub full_steps_per_rotation: u32,
    /// Product of the `a:b` pairs; default 1.
    pub gear_ratio: f64,
    /// Seconds, in [0, 0.001]; `None`: the MCU's default.
    pub step_pulse_duration: Option<f64>,
}

impl MotorSection {
    /// mm per step: `rotation_distance / (full_steps · microsteps · gear_ratio)`.
    pub fn step_dist(&self) -> f64 {
        self.rotation_distance
            / (f64::from(self.full_steps_per_rotation) * f64::from(self.microsteps) * self.gear_ratio)
    }
}

/// Parses `"a:b, c:d"` into the product of `a/b`; empty means 1.
pub(crate) fn parse_gear_ratio(text: &str) -> Result<f64, ValueProblem> {
    let bad = || ValueProblem::BadRatio(text.to_string());
    let mut ratio = 1.0;
    for pair in text.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        let (a, b) = pair.split_once(':').ok_or_else(bad)?;
        let (a, b) = (
            parse_float(a).map_err(|_| bad())?,
            parse_float(b).map_err(|_| bad())?,
        );
        if a <= 0.0 || b <= 0.0 {
            return Err(bad());
        }
        ratio *= a / b;
    }
    if ratio.is_finite() && ratio > 0.0 {
        Ok(ratio)
    } else {
        Err(bad())
    }
}

pub(crate) fn read_motor(s: &SectionReader<'_>, pins: &mut PinRegistry) -> Result<MotorSection, ConfigError> {
    let step_pin = s.pin("step_pin", PinKind::Output, pins, Share::Exclusive)?;
    let dir_pin = s.pin("dir_pin", PinKind::Output, pins, Share::Exclusive)?;
    if dir_pin.mcu != step_pin.mcu {
        let v = s.required("dir_pin")?;
        let why = format!("must be on the same mcu as step_pin ('{}')", step_pin.mcu);
        return Err(s.bad("dir_pin", v, ValueProblem::Invalid(why)));
    }
    let rotation_distance = s.float("rotation_distance", Bounds::ANY.above(0.0))?;
    let microsteps = s.int("microsteps", None, 1..=i64::from(u32::MAX))?;
    let full_steps_per_rotation: u32 =
        s.int("full_steps_per_rotation", Some(200), 1..=i64::from(u32::MAX))?;
    if !full_steps_per_rotation.is_multiple_of(4) {
        let v = s.required("full_steps_per_rotation")?;
        let why = format!("must be a multiple of 4, got {full_steps_per_rotation}");
        return Err(s.bad("full_steps_per_rotation", v, ValueProblem::Invalid(why)));
    }
    let gear_ratio = match s.value("gear_ratio") {
        Some(v) => parse_gear_ratio(&v.text).map_err(|p| s.bad("gear_ratio", v, p))?,
        None => 1.0,
    };
    let enable_pin = s.opt_pin("enable_pin", PinKind::Output, pins, Share::StepperEnable)?;
    let step_pulse_duration = s.opt_float("step_pulse_duration", Bounds::ANY.min(0.0).max(0.001))?;
    Ok(MotorSection {
        step_pin,
        dir_pin,
        enable_pin,
        microsteps,
        rotation_distance,
        full_steps_per_rotation,
        gear_ratio,
        step_pulse_duration,
    })
}

/// A linear rail: motor, endstop, range and homing.
/// A rail; `default_endstop`: the `position_endstop` taken when the section has none (a delta's
/// `stepper_b` and `stepper_c` take `stepper_a`'s, as Klipper does).
/// `delta`: a delta tower, whose `position_endstop` is required and is the default
/// `position_max`.
/// `probe`: the `[probe]`, whose `z_offset` is the endstop position when `endstop_pin` is
/// `probe:z_virtual_endstop` (`position_endstop` is then not an option).
pub(crate) fn read_rail(
    s: &SectionReader<'_>,
    pins: &mut PinRegistry,
    delta: bool,
    probe: Option<&ProbeSection>,
    default_endstop: Option<f64>,
) -> Result<StepperSection, ConfigError> {
    let m = read_motor(s, pins)?;
    let endstop_pin = s.opt_pin("endstop_pin", PinKind::Input, pins, Share::Exclusive)?;
    let probe_z_offset = match (&endstop_pin, probe) {
        (Some(p), Some(probe)) if p.mcu == PROBE_PIN_MCU => Some(probe.z_offset),
        _ => None,
    };
    // The option errors about the endstop position blame: position_endstop, or endstop_pin
    // when the probe's z_offset stands in for it.
    let blame = if probe_z_offset.is_some() {
        "endstop_pin"
    } else {
        "position_endstop"
    };
    let given_endstop = || match default_endstop {
        Some(d) => s.float_or("position_endstop", d, Bounds::ANY),
        None => s.float("position_endstop", Bounds::ANY),
    };
    let position_endstop = match endstop_pin {
        Some(_) if probe_z_offset.is_some() => probe_z_offset,
        Some(_) => Some(given_endstop()?),
        None if delta => Some(given_endstop()?),
        None => s.opt_float("position_endstop", Bounds::ANY)?,
    };
    let position_min = s.float_or("position_min", 0.0, Bounds::ANY)?;
    let position_max = match (delta, position_endstop) {
        (true, Some(e)) => s.float_or("position_max", e, Bounds::ANY.above(position_min))?,
        _ => s.float("position_max", Bounds::ANY.above(position_min))?,
    };
    let homing_speed = s.float_or("homing_speed", 5.0, Bounds::ANY.above(0.0))?;
    let second_homing_speed =
        s.float_or("second_homing_speed", homing_speed / 2.0, Bounds::ANY.above(0.0))?;
    let homing_retract_speed = s.float_or("homing_retract_speed", homing_speed, Bounds::ANY.above(0.0))?;
    let homing_retract_dist = s.float_or("homing_retract_dist", 5.0, Bounds::ANY.min(0.0))?;
    let positive_dir = s.opt_bool("homing_positive_dir")?;

    let homing_positive_dir = match position_endstop {
        None => positive_dir.unwrap_or(false),
        Some(endstop) => {
            let in_range = |what: String| {
                let v = s.required(blame)?;
                let what = match probe_z_offset {
                    Some(_) => format!("the endstop position is [probe] z_offset: {what}"),
                    None => what,
                };
                Err(s.bad(blame, v, ValueProblem::Invalid(what)))
            };
            if endstop < position_min || endstop > position_max {
                return in_range(format!(
                    "must be between position_min ({position_min}) and position_max ({position_max}), got {endstop}"
                ));
            }
            let quarter = (position_max - position_min) / 4.0;
            match positive_dir {
                Some(dir) => {
                    if (dir && endstop == position_min) || (!dir && endstop == position_max) {
                        let v = s.required("homing_positive_dir")?;
                        let why = format!(
                            "homing {} is away from position_endstop {endstop}",
                            if dir {
                                "towards position_max"
                            } else {
                                "towards position_min"
                            }
                        );
                        return Err(s.bad("homing_positive_dir", v, ValueProblem::Invalid(why)));
                    }
                    dir
                }
                None if endstop <= position_min + quarter => false,
                None if endstop >= position_max - quarter => true,
                None => {
                    return in_range(format!(
                        "{endstop} is too far from both position_min and position_max to infer the homing \
                         direction; set homing_positive_dir"
                    ))
                }
            }
        }
    };

    Ok(StepperSection {
        name: s.name().to_string(),
        motor: m,
        endstop_pin,
        position_endstop,
        position_min,
        position_max,
        homing_speed,
        homing_retract_speed,
        homing_retract_dist,
        second_homing_speed,
        homing_positive_dir,
    })
}

/// A further motor of a rail (`[stepper_z1]`, `[stepper_x1]`…): stepped with the rail's first
/// motor (`[stepper_z]`), from the same planned motion, and stopped when homing on its own
/// endstop (`endstop_pin`), or with the rail's first motor on the rail's endstop.
#[derive(Debug, Clone, PartialEq)]
pub struct ExtraStepperSection {
    /// Section name: `stepper_z1`.
    pub name: String,
    /// The rail it moves with: its index in [`super::PrinterConfig::steppers`] (0..=2).
    pub rail: usize,
    /// Pins, microstepping and gearing (its own).
    pub motor: MotorSection,
    /// Its own endstop, which stops it alone when homing (Klipper: a further motor with an
    /// `endstop_pin` homes to it; the rail's `position_endstop` and homing options apply).
    /// `None`: it stops on the rail's endstop, also when `endstop_pin` names that same pin.
    pub endstop_pin: Option<PinRef>,
}

/// Reads `[stepper_z1]`-style section `s`, a further motor of `primary` (rail `rail`).
///
/// The motors of one axis share an MCU (Klipper: "Multi-mcu homing not supported on multi-mcu
/// shared axis"): the trigger that stops them is relayed to one MCU. A motor's own
/// `endstop_pin` may be on any MCU; naming the rail's endstop pin shares that endstop (with the
/// same `^`/`~`/`!` as there, as Klipper requires); the probe's and a driver's virtual endstops
/// are refused for a further motor.
pub(crate) fn read_extra(
    s: &SectionReader<'_>,
    pins: &mut PinRegistry,
    rail: usize,
    primary: &StepperSection,
) -> Result<ExtraStepperSection, ConfigError> {
    let motor = read_motor(s, pins)?;
    let endstop_pin = read_extra_endstop(s, pins, primary)?;
    if motor.step_pin.mcu != primary.motor.step_pin.mcu {
        let v = s.required("step_pin")?;
        let why = format!(
            "must be on the same mcu as [{}]'s step_pin ('{}'): the motors of one axis stop on its \
             endstops' triggers, which Cadence (like Klipper: multi-mcu homing is not supported on a \
             multi-mcu shared axis) relays only to motors on one MCU",
            primary.name, primary.motor.step_pin.mcu
        );
        return Err(s.bad("step_pin", v, ValueProblem::Invalid(why)));
    }
    Ok(ExtraStepperSection {
        name: s.name().to_string(),
        rail,
        motor,
        endstop_pin,
    })
}

/// The further motor's own endstop (see [`read_extra`]); `None` when it has none or shares the
/// rail's.
fn read_extra_endstop(
    s: &SectionReader<'_>,
    pins: &mut PinRegistry,
    primary: &StepperSection,
) -> Result<Option<PinRef>, ConfigError> {
    let Some(v) = s.value("endstop_pin") else {
        return Ok(None);
    };
    let invalid = |why: String| Err(s.bad("endstop_pin", v, ValueProblem::Invalid(why)));
    let Some(rail_pin) = &primary.endstop_pin else {
        return invalid(format!(
            "[{}] has no endstop_pin: a motor's own endstop needs the rail's homing options \
             (position_endstop, homing_speed…) from there",
            primary.name
        ));
    };
    let parsed = PinRef::parse(&v.text, PinKind::Input).map_err(|problem| {
        s.bad(
            "endstop_pin",
            v,
            ValueProblem::BadPin {
                pin: v.text.clone(),
                problem,
            },
        )
    })?;
    let pin = pins.resolve(parsed).map_err(|p| s.bad("endstop_pin", v, p))?;
    if pin.mcu == rail_pin.mcu && pin.pin == rail_pin.pin {
        // Klipper: one endstop for both, its pull-up and inversion given alike.
        if (pin.invert, pin.pullup, pin.pulldown) != (rail_pin.invert, rail_pin.pullup, rail_pin.pulldown) {
            return invalid(format!(
                "shares [{}]'s endstop pin '{rail_pin}' and must specify the same pullup/invert settings",
                primary.name
            ));
        }
        // Read (and counted as used) without claiming the pin a second time.
        return Ok(None);
    }
    let rail_virtual = rail_pin.mcu == PROBE_PIN_MCU || !pins.has_mcu(&rail_pin.mcu);
    if rail_virtual {
        return invalid(format!(
            "is not supported by Cadence yet with [{}] homing on the virtual endstop '{rail_pin}' \
             (a further motor's own endstop beside it)",
            primary.name
        ));
    }
    let virtual_endstop =
        pin.mcu == PROBE_PIN_MCU || (pin.pin == "virtual_endstop" && !pins.has_mcu(&pin.mcu));
    if virtual_endstop {
        return invalid(format!(
            "pin '{pin}': a further motor's own endstop must be a pin of an [mcu] (the probe's and a \
             driver's virtual endstops are not supported there by Cadence yet)"
        ));
    }
    s.opt_pin("endstop_pin", PinKind::Input, pins, Share::Exclusive)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ini;
    use crate::printer::reader::Reader;
    use proptest::prelude::*;
    use std::path::Path;

    const BASE: &str = "step_pin: PA0\ndir_pin: PA1\nmicrosteps: 16\nrotation_distance: 40\n";

    /// Reads `[stepper_x]` with BASE (lines 2-5) followed by `extra` (from line 6).
    fn rail(extra: &str) -> Result<StepperSection, String> {
        let text = format!("[stepper_x]\n{BASE}{extra}");
        let file = ini::parse_str(&text, Path::new("printer.cfg")).map_err(|e| e.to_string())?;
        let reader = Reader::new(&file);
        let s = reader.section("stepper_x").ok_or("no section")?;
        let mut pins = PinRegistry::new(vec!["mcu".into(), "ebb".into()]);
        let r = read_rail(&s, &mut pins, false, None, None).map_err(|e| e.to_string())?;
        reader.finish(|_| false).map_err(|e| e.to_string())?;
        Ok(r)
    }

    #[test]
    fn defaults_and_step_dist() {
        let r = rail("endstop_pin: ^PA2\nposition_endstop: 0\nposition_max: 200\n")
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(r.step_dist(), 1.0 / 80.0);
        assert_eq!(
            (
                r.motor.full_steps_per_rotation,
                r.motor.gear_ratio,
                r.position_min
            ),
            (200, 1.0, 0.0)
        );
        assert_eq!(
            (r.homing_speed, r.second_homing_speed, r.homing_retract_speed),
            (5.0, 2.5, 5.0)
        );
        assert_eq!(
            (
                r.homing_retract_dist,
                r.homing_positive_dir,
                r.motor.step_pulse_duration
            ),
            (5.0, false, None)
        );
        assert!(r.endstop_pin.as_ref().is_some_and(|p| p.pullup));
    }

    #[test]
    fn gear_ratio_and_full_steps() {
        let r = rail("gear_ratio: 80:16, 3:1\nfull_steps_per_rotation: 400\nposition_max: 10\n");
        let r = r.unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(r.motor.gear_ratio, 15.0);
        assert_eq!(r.step_dist(), 40.0 / (400.0 * 16.0 * 15.0));
        assert_eq!(parse_gear_ratio(""), Ok(1.0));
        assert_eq!(parse_gear_ratio("57:11,"), Ok(57.0 / 11.0));
        for bad in ["3", "a:b", "0:1", "1:-2", "1:2:3"] {
            assert_eq!(
                parse_gear_ratio(bad),
                Err(ValueProblem::BadRatio(bad.into())),
                "{bad}"
            );
        }
    }

    #[test]
    fn homing_direction_is_inferred_or_checked() {
        let dir = |extra: &str| {
            rail(&format!("endstop_pin: PA2\nposition_max: 200\n{extra}")).map(|r| r.homing_positive_dir)
        };
        assert_eq!(dir("position_endstop: 0\n"), Ok(false));
        assert_eq!(dir("position_endstop: 50\n"), Ok(false));
        assert_eq!(dir("position_endstop: 150\n"), Ok(true));
        assert_eq!(dir("position_endstop: 200\n"), Ok(true));
        assert_eq!(
            dir("position_endstop: 100\n"),
            Err(
                "printer.cfg:8: [stepper_x] position_endstop: 100 is too far from both position_min and \
                 position_max to infer the homing direction; set homing_positive_dir"
                    .to_string()
            )
        );
        assert_eq!(
            dir("position_endstop: 100\nhoming_positive_dir: true\n"),
            Ok(true)
        );
        assert_eq!(
            dir("position_endstop: 0\nhoming_positive_dir: true\n"),
            Err(
                "printer.cfg:9: [stepper_x] homing_positive_dir: homing towards position_max is away from \
                 position_endstop 0"
                    .to_string()
            )
        );
        assert_eq!(
            rail("position_max: 10\n").map(|r| r.homing_positive_dir),
            Ok(false)
        );
    }

    #[test]
    fn error_messages() {
        let cases = [
            ("position_max: 200\nendstop_pin: PA2\n", "printer.cfg:1: Option 'position_endstop' in section 'stepper_x' must be specified"),
            ("endstop_pin: PA2\nposition_endstop: 0\n", "printer.cfg:1: Option 'position_max' in section 'stepper_x' must be specified"),
            (
                "position_endstop: 250\nposition_max: 200\n",
                "printer.cfg:6: [stepper_x] position_endstop: must be between position_min (0) and position_max \
                 (200), got 250",
            ),
            ("position_min: 5\nposition_max: 5\n", "printer.cfg:7: [stepper_x] position_max: must be above 5, got 5"),
            (
                "position_max: 1\nfull_steps_per_rotation: 201\n",
                "printer.cfg:7: [stepper_x] full_steps_per_rotation: must be a multiple of 4, got 201",
            ),
            (
                "position_max: 1\nstep_pulse_duration: 0.01\n",
                "printer.cfg:7: [stepper_x] step_pulse_duration: must have maximum of 0.001, got 0.01",
            ),
            ("position_max: 1\nhoming_speed: 0\n", "printer.cfg:7: [stepper_x] homing_speed: must be above 0, got 0"),
            ("position_max: 1\nfoo: 1\n", "printer.cfg:7: Option 'foo' is not valid in section 'stepper_x'"),
            (
                "position_max: 1\nendstop_pin: !^PA3\n",
                "printer.cfg:7: [stepper_x] endstop_pin: invalid pin '!^PA3': '^' or '~' must come before '!'",
            ),
        ];
        for (extra, want) in cases {
            assert_eq!(rail(extra).map(|_| ()), Err(want.to_string()), "{extra}");
        }
        let text = "[stepper_x]\nstep_pin: PA0\ndir_pin: ebb:PA1\n";
        let file = ini::parse_str(text, Path::new("printer.cfg")).unwrap_or_else(|e| panic!("{e}"));
        let reader = Reader::new(&file);
        let s = reader
            .section("stepper_x")
            .unwrap_or_else(|| panic!("no section"));
        let mut pins = PinRegistry::new(vec!["mcu".into(), "ebb".into()]);
        assert_eq!(
            read_rail(&s, &mut pins, false, None, None)
                .map(|_| ())
                .map_err(|e| e.to_string()),
            Err(
                "printer.cfg:3: [stepper_x] dir_pin: must be on the same mcu as step_pin ('mcu')".to_string()
            )
        );
        let text = "[stepper_x]\nstep_pin: PA0\ndir_pin: PA1\nrotation_distance: 40\nmicrosteps: abc\n";
        let file = ini::parse_str(text, Path::new("printer.cfg")).unwrap_or_else(|e| panic!("{e}"));
        let reader = Reader::new(&file);
        let s = reader
            .section("stepper_x")
            .unwrap_or_else(|| panic!("no section"));
        let mut pins = PinRegistry::new(vec!["mcu".into()]);
        assert_eq!(
            read_rail(&s, &mut pins, false, None, None)
                .map(|_| ())
                .map_err(|e| e.to_string()),
            Err("printer.cfg:5: [stepper_x] microsteps: expected an integer, got 'abc'".to_string())
        );
    }

    proptest! {
        #[test]
        fn gear_ratio_never_panics(text in "[0-9.:, -]{0,16}") {
            if let Ok(r) = parse_gear_ratio(&text) {
                prop_assert!(r.is_finite() && r > 0.0);
            }
        }
    }
}
