//! `[extruder]`, `[extruder1]`…: the filament motor, extrusion limits, pressure advance and
//! the heater of each extruder; `[extruder_stepper NAME]`: a further filament motor that
//! follows an extruder's motion (or none: `extruder:` empty).
//!
//! Extrude-only moves are limited in filament space. With filament area
//! `A = π·(filament_diameter/2)²` and `r = 4·nozzle_diameter² / A` (how much faster the filament
//! moves than the toolhead for a bead of cross section 4·nozzle_diameter²), the defaults are
//! `max_extrude_only_velocity = max_velocity·r` and `max_extrude_only_accel = max_accel·r`, as
//! Klipper documents them (independent of `max_extrude_cross_section`, which only bounds
//! printing moves). `max_extrude_cross_section` defaults to `4·nozzle_diameter²`.

use std::f64::consts::PI;

use super::error::ConfigError;
use super::heater::{read_heater, HeaterSection};
use super::pins::PinRegistry;
use super::reader::{Bounds, Reader, SectionReader};
use super::stepper::{read_motor, MotorSection};
use super::toolhead::PrinterSection;

/// `[extruder]` or `[extruderN]`.
#[derive(Debug, Clone, PartialEq)]
pub struct ExtruderSection {
    /// `extruder`, `extruder1`…
    pub name: String,
    /// Pins, microstepping and gearing (`rotation_distance` in mm of filament).
    pub motor: MotorSection,
    /// mm, > 0.
    pub nozzle_diameter: f64,
    /// mm, ≥ nozzle_diameter.
    pub filament_diameter: f64,
    /// mm², > 0; default `4·nozzle_diameter²`.
    pub max_extrude_cross_section: f64,
    /// mm of filament, ≥ 0; default 50.
    pub max_extrude_only_distance: f64,
    /// mm/s of filament, > 0 (default: see the module docs).
    pub max_extrude_only_velocity: f64,
    /// mm/s² of filament, > 0 (default: see the module docs).
    pub max_extrude_only_accel: f64,
    /// mm/s, ≥ 0; default 1.
    pub instantaneous_corner_velocity: f64,
    /// Seconds, ≥ 0; default 0.
    pub pressure_advance: f64,
    /// Seconds, in (0, 0.2]; default 0.04.
    pub pressure_advance_smooth_time: f64,
    pub heater: HeaterSection,
}

impl ExtruderSection {
    /// mm of filament per step.
    pub fn step_dist(&self) -> f64 {
        self.motor.step_dist()
    }

    /// Filament cross-section area in mm².
    pub fn filament_area(&self) -> f64 {
        PI * (self.filament_diameter / 2.0).powi(2)
    }
}

pub(crate) fn read_extruder(
    s: &SectionReader<'_>,
    printer: &PrinterSection,
    pins: &mut PinRegistry,
) -> Result<ExtruderSection, ConfigError> {
    let m = read_motor(s, pins)?;
    let nozzle_diameter = s.float("nozzle_diameter", Bounds::ANY.above(0.0))?;
    let filament_diameter = s.float("filament_diameter", Bounds::ANY.min(nozzle_diameter))?;
    let max_extrude_cross_section = s.float_or(
        "max_extrude_cross_section",
        4.0 * nozzle_diameter * nozzle_diameter,
        Bounds::ANY.above(0.0),
    )?;
    let ratio = 4.0 * nozzle_diameter * nozzle_diameter / (PI * (filament_diameter / 2.0).powi(2));
    let max_extrude_only_velocity = s.float_or(
        "max_extrude_only_velocity",
        printer.max_velocity * ratio,
        Bounds::ANY.above(0.0),
    )?;
    let max_extrude_only_accel = s.float_or(
        "max_extrude_only_accel",
        printer.max_accel * ratio,
        Bounds::ANY.above(0.0),
    )?;
    let max_extrude_only_distance = s.float_or("max_extrude_only_distance", 50.0, Bounds::ANY.min(0.0))?;
    let instantaneous_corner_velocity =
        s.float_or("instantaneous_corner_velocity", 1.0, Bounds::ANY.min(0.0))?;
    let pressure_advance = s.float_or("pressure_advance", 0.0, Bounds::ANY.min(0.0))?;
    let pressure_advance_smooth_time = s.float_or(
        "pressure_advance_smooth_time",
        0.040,
        Bounds::ANY.above(0.0).max(0.200),
    )?;
    let heater = read_heater(s, pins)?;
    Ok(ExtruderSection {
        name: s.name().to_string(),
        motor: m,
        nozzle_diameter,
        filament_diameter,
        max_extrude_cross_section,
        max_extrude_only_distance,
        max_extrude_only_velocity,
        max_extrude_only_accel,
        instantaneous_corner_velocity,
        pressure_advance,
        pressure_advance_smooth_time,
        heater,
    })
}

/// `[extruder_stepper NAME]`.
#[derive(Debug, Clone, PartialEq)]
pub struct ExtruderStepperSection {
    /// NAME, as SYNC_EXTRUDER_MOTION and SET_PRESSURE_ADVANCE name it.
    pub name: String,
    pub motor: MotorSection,
    /// The extruder whose motion it follows (`extruder`, `extruder1`…); `None` when the
    /// option is empty (it stands still until SYNC_EXTRUDER_MOTION).
    pub extruder: Option<String>,
    /// Seconds, ≥ 0; default 0.
    pub pressure_advance: f64,
    /// Seconds, in (0, 0.2]; default 0.04.
    pub pressure_advance_smooth_time: f64,
}

/// The further extruders `[extruder1]`, `[extruder2]`… up to the first missing index (as
/// Klipper looks them up; a later one is then an unread section), at most
/// [`planner::extruders::MAX_EXTRUDERS`] in all.
pub(crate) fn read_extra_extruders(
    reader: &Reader<'_>,
    printer: &PrinterSection,
    pins: &mut PinRegistry,
) -> Result<Vec<ExtruderSection>, ConfigError> {
    let mut out = Vec::new();
    for name in planner::extruders::EXTRUDER_NAMES.iter().skip(1) {
        let Some(s) = reader.section(name) else {
            break;
        };
        out.push(read_extruder(&s, printer, pins)?);
    }
    Ok(out)
}

/// Every `[extruder_stepper NAME]`; `extruders` names the extruders there are.
pub(crate) fn read_extruder_steppers(
    reader: &Reader<'_>,
    extruders: &[&str],
    pins: &mut PinRegistry,
) -> Result<Vec<ExtruderStepperSection>, ConfigError> {
    let mut out = Vec::new();
    for s in reader.sections_with_arg("extruder_stepper") {
        let name = s.arg().unwrap_or_default().to_string();
        let motor = read_motor(&s, pins)?;
        let v = s.required("extruder")?;
        let extruder = match v.text.trim() {
            "" => None,
            e if extruders.contains(&e) => Some(e.to_string()),
            e => {
                let why = format!(
                    "'{e}' is not a valid extruder (there are: {})",
                    extruders.join(", ")
                );
                return Err(s.bad("extruder", v, super::error::ValueProblem::Invalid(why)));
            }
        };
        let pressure_advance = s.float_or("pressure_advance", 0.0, Bounds::ANY.min(0.0))?;
        let pressure_advance_smooth_time = s.float_or(
            "pressure_advance_smooth_time",
            0.040,
            Bounds::ANY.above(0.0).max(0.200),
        )?;
        out.push(ExtruderStepperSection {
            name,
            motor,
            extruder,
            pressure_advance,
            pressure_advance_smooth_time,
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ini;
    use crate::printer::reader::Reader;
    use crate::printer::toolhead::Kinematics;
    use std::path::Path;

    const BASE: &str = "step_pin: PA4\ndir_pin: PA6\nmicrosteps: 16\nrotation_distance: 33.5\n\
        heater_pin: PB4\nsensor_type: EPCOS 100K B57560G104F\nsensor_pin: PK5\ncontrol: watermark\n\
        min_temp: 0\nmax_temp: 250\n";

    /// `[extruder]` with BASE (lines 2-11) then `extra` (from line 12).
    fn extruder(extra: &str) -> Result<ExtruderSection, String> {
        let text = format!("[extruder]\n{BASE}{extra}");
        let file = ini::parse_str(&text, Path::new("printer.cfg")).map_err(|e| e.to_string())?;
        let reader = Reader::new(&file);
        let s = reader.section("extruder").ok_or("no section")?;
        let printer = PrinterSection {
            kinematics: Kinematics::Cartesian,
            max_velocity: 300.0,
            max_accel: 3000.0,
            minimum_cruise_ratio: 0.5,
            square_corner_velocity: 5.0,
            max_z_velocity: 300.0,
            max_z_accel: 3000.0,
        };
        let e = read_extruder(&s, &printer, &mut PinRegistry::new(vec!["mcu".into()]))
            .map_err(|e| e.to_string())?;
        reader.finish(|_| false).map_err(|e| e.to_string())?;
        Ok(e)
    }

    #[test]
    fn extrude_only_defaults_ignore_the_cross_section_limit() {
        let e = extruder("nozzle_diameter: 0.5\nfilament_diameter: 3.5\nmax_extrude_cross_section: 50\n")
            .unwrap_or_else(|e| panic!("{e}"));
        let ratio = 4.0 * 0.5 * 0.5 / e.filament_area();
        assert!((e.max_extrude_only_velocity - 300.0 * ratio).abs() < 1e-9);
        assert_eq!(e.max_extrude_cross_section, 50.0);
    }

    #[test]
    fn derived_defaults() {
        let e = extruder("nozzle_diameter: 0.4\nfilament_diameter: 1.75\n").unwrap_or_else(|e| panic!("{e}"));
        assert!((e.step_dist() - 33.5 / 3200.0).abs() < 1e-15);
        assert!((1.0 / e.step_dist() - 95.52).abs() < 0.01);
        let cross = 4.0 * 0.4 * 0.4;
        assert!((e.max_extrude_cross_section - cross).abs() < 1e-12);
        let ratio = cross / e.filament_area();
        assert!((e.max_extrude_only_velocity - 300.0 * ratio).abs() < 1e-9);
        assert!((e.max_extrude_only_accel - 3000.0 * ratio).abs() < 1e-9);
        assert_eq!(
            (
                e.max_extrude_only_distance,
                e.pressure_advance,
                e.pressure_advance_smooth_time
            ),
            (50.0, 0.0, 0.04)
        );
        assert_eq!(
            (e.instantaneous_corner_velocity, e.heater.name.as_str()),
            (1.0, "extruder")
        );
    }

    #[test]
    fn explicit_values_win() {
        let e = extruder(
            "nozzle_diameter: 0.5\nfilament_diameter: 3.5\nmax_extrude_cross_section: 50\n\
             max_extrude_only_distance: 500\nmax_extrude_only_velocity: 120\npressure_advance: 0.05\n",
        )
        .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            (e.max_extrude_cross_section, e.max_extrude_only_distance),
            (50.0, 500.0)
        );
        assert_eq!((e.max_extrude_only_velocity, e.pressure_advance), (120.0, 0.05));
        // The accel default follows the nozzle, not max_extrude_cross_section (as Klipper).
        assert!((e.max_extrude_only_accel - 3000.0 * 4.0 * 0.5 * 0.5 / e.filament_area()).abs() < 1e-9);
    }

    #[test]
    fn errors() {
        let cases = [
            (
                "nozzle_diameter: 0.4\n",
                "printer.cfg:1: Option 'filament_diameter' in section 'extruder' must be specified",
            ),
            (
                "nozzle_diameter: 0.4\nfilament_diameter: 0.3\n",
                "printer.cfg:13: [extruder] filament_diameter: must have minimum of 0.4, got 0.3",
            ),
            (
                "nozzle_diameter: 0.4\nfilament_diameter: 1.75\npressure_advance_smooth_time: 0\n",
                "printer.cfg:14: [extruder] pressure_advance_smooth_time: must be above 0, got 0",
            ),
            (
                "nozzle_diameter: 0.4\nfilament_diameter: 1.75\nendstop_pin: PA0\n",
                "printer.cfg:14: Option 'endstop_pin' is not valid in section 'extruder'",
            ),
        ];
        for (extra, want) in cases {
            assert_eq!(extruder(extra).map(|_| ()), Err(want.to_string()), "{extra}");
        }
    }
}
