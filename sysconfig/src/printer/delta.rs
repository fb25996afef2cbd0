//! Delta geometry: `[printer] delta_radius` (required), `print_radius` (default delta_radius),
//! `minimum_z_position` (default 0), and per tower `[stepper_a|b|c] arm_length` (required on
//! stepper_a, b and c default to a's) and `angle` (defaults 210°, 330°, 90°), as Klipper.
//! Each tower's `position_endstop` is where the carriage homes (required on stepper_a; b and c
//! default to a's, as Klipper); its `position_max` defaults to it.

use super::error::{ConfigError, ValueProblem};
use super::reader::{Bounds, SectionReader};

/// Default tower angles (degrees) of A, B, C.
pub const DEFAULT_ANGLES: [f64; 3] = [210.0, 330.0, 90.0];

/// The geometry of a linear delta printer.
#[derive(Debug, Clone, PartialEq)]
pub struct DeltaSection {
    /// Horizontal distance from the centre to each tower (mm), > 0.
    pub delta_radius: f64,
    /// Radius the effector may reach (mm), > 0.
    pub print_radius: f64,
    /// Lowest Z (mm).
    pub minimum_z_position: f64,
    /// Diagonal rod lengths of towers A, B, C (mm), each > delta_radius.
    pub arm_length: [f64; 3],
    /// Tower angles (degrees).
    pub angles: [f64; 3],
}

/// The `[printer]` part.
pub(crate) fn read_printer_delta(s: &SectionReader<'_>) -> Result<(f64, f64, f64), ConfigError> {
    let radius = s.float("delta_radius", Bounds::ANY.above(0.0))?;
    let print_radius = s.float_or("print_radius", radius, Bounds::ANY.above(0.0))?;
    let min_z = s.float_or("minimum_z_position", 0.0, Bounds::ANY)?;
    Ok((radius, print_radius, min_z))
}

/// A tower's `arm_length` and `angle` (`first_arm`: stepper_a's, the default for b and c).
pub(crate) fn read_tower(
    s: &SectionReader<'_>,
    index: usize,
    first_arm: Option<f64>,
    radius: f64,
) -> Result<(f64, f64), ConfigError> {
    let arm = match first_arm {
        Some(a) => s.float_or("arm_length", a, Bounds::ANY.above(0.0))?,
        None => s.float("arm_length", Bounds::ANY.above(0.0))?,
    };
    if arm <= radius {
        let why = format!("must be longer than delta_radius ({radius}), got {arm}");
        return match s.value("arm_length") {
            Some(v) => Err(s.bad("arm_length", v, ValueProblem::Invalid(why))),
            None => Err(ConfigError::BadSection {
                at: s.at().clone(),
                section: s.name().to_string(),
                reason: format!("arm_length (from stepper_a) {why}"),
            }),
        };
    }
    let angle = s.float_or("angle", DEFAULT_ANGLES[index.min(2)], Bounds::ANY)?;
    Ok((arm, angle))
}
