//! `[printer]`: kinematics and the toolhead's velocity and acceleration limits.
//!
//! `minimum_cruise_ratio` (default 0.5) is the fraction of a move that must be able to cruise;
//! older configs give `max_accel_to_decel` instead, which maps to
//! `1 - min(1, max_accel_to_decel / max_accel)` when `minimum_cruise_ratio` is absent.
//! `max_z_velocity` / `max_z_accel` default to `max_velocity` / `max_accel`.

use super::error::ConfigError;
use super::reader::{Bounds, SectionReader};

/// The `kinematics:` choice.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kinematics {
    Cartesian,
    CoreXY,
    CoreXZ,
    /// Linear delta: towers `stepper_a`, `stepper_b`, `stepper_c` (see [`super::DeltaSection`]).
    Delta,
    None,
}

impl Kinematics {
    /// Klipper's name for it.
    pub fn name(self) -> &'static str {
        match self {
            Kinematics::Cartesian => "cartesian",
            Kinematics::CoreXY => "corexy",
            Kinematics::CoreXZ => "corexz",
            Kinematics::Delta => "delta",
            Kinematics::None => "none",
        }
    }

    /// The stepper sections this kinematics needs, in axis order.
    pub fn stepper_sections(self) -> &'static [&'static str] {
        match self {
            Kinematics::Cartesian | Kinematics::CoreXY | Kinematics::CoreXZ => {
                &["stepper_x", "stepper_y", "stepper_z"]
            }
            Kinematics::Delta => &["stepper_a", "stepper_b", "stepper_c"],
            Kinematics::None => &[],
        }
    }
}

const CHOICES: [(&str, Kinematics); 5] = [
    ("cartesian", Kinematics::Cartesian),
    ("corexy", Kinematics::CoreXY),
    ("corexz", Kinematics::CoreXZ),
    ("delta", Kinematics::Delta),
    ("none", Kinematics::None),
];

/// `[printer]`.
#[derive(Debug, Clone, PartialEq)]
pub struct PrinterSection {
    pub kinematics: Kinematics,
    /// mm/s, > 0.
    pub max_velocity: f64,
    /// mm/s², > 0.
    pub max_accel: f64,
    /// In [0, 1); default 0.5.
    pub minimum_cruise_ratio: f64,
    /// mm/s, ≥ 0; default 5.
    pub square_corner_velocity: f64,
    /// mm/s, > 0; default `max_velocity`.
    pub max_z_velocity: f64,
    /// mm/s², > 0; default `max_accel`.
    pub max_z_accel: f64,
}

pub(crate) fn read_printer(s: &SectionReader<'_>) -> Result<PrinterSection, ConfigError> {
    let kinematics = s.choice("kinematics", &CHOICES, None)?;
    let max_velocity = s.float("max_velocity", Bounds::ANY.above(0.0))?;
    let max_accel = s.float("max_accel", Bounds::ANY.above(0.0))?;
    let accel_to_decel = s.opt_float("max_accel_to_decel", Bounds::ANY.above(0.0))?;
    let default_ratio = accel_to_decel.map_or(0.5, |a2d| 1.0 - (a2d / max_accel).min(1.0));
    let minimum_cruise_ratio = s.float_or(
        "minimum_cruise_ratio",
        default_ratio,
        Bounds::ANY.min(0.0).below(1.0),
    )?;
    let square_corner_velocity = s.float_or("square_corner_velocity", 5.0, Bounds::ANY.min(0.0))?;
    let max_z_velocity = s.float_or("max_z_velocity", max_velocity, Bounds::ANY.above(0.0))?;
    let max_z_accel = s.float_or("max_z_accel", max_accel, Bounds::ANY.above(0.0))?;
    Ok(PrinterSection {
        kinematics,
        max_velocity,
        max_accel,
        minimum_cruise_ratio,
        square_corner_velocity,
        max_z_velocity,
        max_z_accel,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ini;
    use crate::printer::reader::Reader;
    use std::path::Path;

    fn read(text: &str) -> Result<PrinterSection, String> {
        let file = ini::parse_str(text, Path::new("printer.cfg")).map_err(|e| e.to_string())?;
        let reader = Reader::new(&file);
        let s = reader.section("printer").ok_or("no [printer]")?;
        read_printer(&s).map_err(|e| e.to_string())
    }

    #[test]
    fn defaults_follow_klipper() {
        let p = read("[printer]\nkinematics: corexy\nmax_velocity: 300\nmax_accel: 3000\n");
        assert_eq!(
            p,
            Ok(PrinterSection {
                kinematics: Kinematics::CoreXY,
                max_velocity: 300.0,
                max_accel: 3000.0,
                minimum_cruise_ratio: 0.5,
                square_corner_velocity: 5.0,
                max_z_velocity: 300.0,
                max_z_accel: 3000.0,
            })
        );
    }

    #[test]
    fn max_accel_to_decel_maps_to_cruise_ratio() {
        let p = read(
            "[printer]\nkinematics: none\nmax_velocity: 300\nmax_accel: 4000\nmax_accel_to_decel: 1000\n",
        );
        assert_eq!(p.map(|p| p.minimum_cruise_ratio), Ok(0.75));
        let p = read(
            "[printer]\nkinematics: none\nmax_velocity: 300\nmax_accel: 4000\nmax_accel_to_decel: 9000\n",
        );
        assert_eq!(p.map(|p| p.minimum_cruise_ratio), Ok(0.0));
    }

    #[test]
    fn errors() {
        assert_eq!(
            read("[printer]\nkinematics: polar\n"),
            Err("printer.cfg:2: [printer] kinematics: expected one of cartesian, corexy, corexz, delta, none, \
                 got 'polar'"
                .to_string())
        );
        assert_eq!(
            read("[printer]\nkinematics: cartesian\nmax_velocity: 0\n"),
            Err("printer.cfg:3: [printer] max_velocity: must be above 0, got 0".to_string())
        );
        assert_eq!(
            read("[printer]\nkinematics: cartesian\nmax_velocity: 10\n"),
            Err("printer.cfg:1: Option 'max_accel' in section 'printer' must be specified".to_string())
        );
        assert_eq!(
            read("[printer]\nkinematics: cartesian\nmax_velocity: 10\nmax_accel: 10\nminimum_cruise_ratio: 1\n"),
            Err("printer.cfg:5: [printer] minimum_cruise_ratio: must be below 1, got 1".to_string())
        );
    }
}
