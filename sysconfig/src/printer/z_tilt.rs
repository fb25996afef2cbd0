//! `[z_tilt]`: several independently driven Z motors levelled with the probe (Klipper's options:
//! `z_positions` — one `X, Y` per Z motor, `[stepper_z]` first then `[stepper_z1]`…, where each
//! motor lifts the gantry; `points` — at least 2 nozzle positions `X, Y` to probe; `speed`
//! (> 0, default 50), `horizontal_move_z` (default 5), `retries` (≥ 0, default 0),
//! `retry_tolerance` (≥ 0, default 0)). `[quad_gantry_level]`: four Z motors at the corners of
//! `gantry_corners` (two `X, Y` lines: one corner and the opposite; the motors in Klipper's
//! order `[stepper_z]` front left, `[stepper_z1]` back left, `[stepper_z2]` back right,
//! `[stepper_z3]` front right), exactly 4 `points`, `max_adjust` (> 0, default 4) and the same
//! `speed`, `horizontal_move_z`, `retries`, `retry_tolerance`.

use super::error::{ConfigError, ValueProblem};
use super::reader::{parse_float, Bounds, SectionReader};

/// `[z_tilt]`.
#[derive(Debug, Clone, PartialEq)]
pub struct ZTiltSection {
    pub z_positions: Vec<[f64; 2]>,
    pub points: Vec<[f64; 2]>,
    pub speed: f64,
    pub horizontal_move_z: f64,
    pub retries: u32,
    pub retry_tolerance: f64,
    /// `[quad_gantry_level]`: the largest correction allowed (mm); `None` for `[z_tilt]`.
    pub max_adjust: Option<f64>,
}

/// A list of `X, Y` lines (or `X, Y` pairs separated by newlines).
pub(crate) fn xy_list(s: &SectionReader<'_>, option: &str, min: usize) -> Result<Vec<[f64; 2]>, ConfigError> {
    let v = s.required(option)?;
    let mut out = Vec::new();
    for line in v.text.lines().map(str::trim).filter(|l| !l.is_empty()) {
        let parts: Vec<&str> = line.split(',').map(str::trim).collect();
        let [x, y] = parts.as_slice() else {
            let why = format!("each line must be two numbers 'X, Y', got '{line}'");
            return Err(s.bad(option, v, ValueProblem::Invalid(why)));
        };
        out.push([
            parse_float(x).map_err(|p| s.bad(option, v, p))?,
            parse_float(y).map_err(|p| s.bad(option, v, p))?,
        ]);
    }
    if out.len() < min {
        let why = format!("needs at least {min} 'X, Y' lines, got {}", out.len());
        return Err(s.bad(option, v, ValueProblem::Invalid(why)));
    }
    Ok(out)
}

/// Reads `[z_tilt]` for a printer with `z_motors` Z motors.
pub(crate) fn read_z_tilt(s: &SectionReader<'_>, z_motors: usize) -> Result<ZTiltSection, ConfigError> {
    let z_positions = xy_list(s, "z_positions", 2)?;
    if z_positions.len() != z_motors {
        let v = s.required("z_positions")?;
        let why = format!(
            "has {} positions, the printer has {z_motors} Z motors ([stepper_z], [stepper_z1]…): give one per motor",
            z_positions.len()
        );
        return Err(s.bad("z_positions", v, ValueProblem::Invalid(why)));
    }
    Ok(ZTiltSection {
        z_positions,
        points: xy_list(s, "points", 2)?,
        speed: s.float_or("speed", 50.0, Bounds::ANY.above(0.0))?,
        horizontal_move_z: s.float_or("horizontal_move_z", 5.0, Bounds::ANY)?,
        retries: s.int("retries", Some(0u32), 0..=1000)?,
        retry_tolerance: s.float_or("retry_tolerance", 0.0, Bounds::ANY.min(0.0))?,
        max_adjust: None,
    })
}

/// Reads `[quad_gantry_level]` (as a [`ZTiltSection`] whose `z_positions` are the four
/// corners) for a printer with `z_motors` Z motors.
pub(crate) fn read_quad_gantry_level(
    s: &SectionReader<'_>,
    z_motors: usize,
) -> Result<ZTiltSection, ConfigError> {
    let corners = xy_list(s, "gantry_corners", 2)?;
    let v = s.required("gantry_corners")?;
    let [a, b] = corners.as_slice() else {
        let why = format!("must be 2 'X, Y' lines (opposite corners), got {}", corners.len());
        return Err(s.bad("gantry_corners", v, ValueProblem::Invalid(why)));
    };
    if z_motors != 4 {
        let why = format!("needs 4 Z motors ([stepper_z] … [stepper_z3]), the printer has {z_motors}");
        return Err(s.bad("gantry_corners", v, ValueProblem::Invalid(why)));
    }
    let (x0, x1, y0, y1) = (a[0].min(b[0]), a[0].max(b[0]), a[1].min(b[1]), a[1].max(b[1]));
    let points = xy_list(s, "points", 4)?;
    if points.len() != 4 {
        let pv = s.required("points")?;
        let why = format!("needs exactly 4 'X, Y' lines, got {}", points.len());
        return Err(s.bad("points", pv, ValueProblem::Invalid(why)));
    }
    Ok(ZTiltSection {
        z_positions: vec![[x0, y0], [x0, y1], [x1, y1], [x1, y0]],
        points,
        speed: s.float_or("speed", 50.0, Bounds::ANY.above(0.0))?,
        horizontal_move_z: s.float_or("horizontal_move_z", 5.0, Bounds::ANY)?,
        retries: s.int("retries", Some(0u32), 0..=1000)?,
        retry_tolerance: s.float_or("retry_tolerance", 0.0, Bounds::ANY.min(0.0))?,
        max_adjust: Some(s.float_or("max_adjust", 4.0, Bounds::ANY.above(0.0))?),
    })
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use crate::printer::parse_str;

    use crate::printer::bed_mesh::tests::BASE;

    const Z1: &str = "[stepper_z1]\nstep_pin: PD0\ndir_pin: PD1\nmicrosteps: 16\nrotation_distance: 8\n";

    fn parse(body: &str) -> Result<super::ZTiltSection, String> {
        parse_str(&format!("{BASE}{Z1}[z_tilt]\n{body}"), Path::new("printer.cfg"))
            .map(|c| c.z_tilt.unwrap_or_else(|| panic!("no z_tilt")))
            .map_err(|e| e.to_string())
    }

    #[test]
    fn options_and_defaults() {
        let z = parse("z_positions:\n  -20, 100\n  220, 100\npoints:\n  20, 100\n  180, 100\nretries: 5\nretry_tolerance: 0.01\n")
            .unwrap();
        assert_eq!(z.z_positions, vec![[-20.0, 100.0], [220.0, 100.0]]);
        assert_eq!(z.points, vec![[20.0, 100.0], [180.0, 100.0]]);
        assert_eq!(
            (z.speed, z.horizontal_move_z, z.retries, z.retry_tolerance),
            (50.0, 5.0, 5, 0.01)
        );
    }

    #[test]
    fn errors_name_the_option() {
        let e = |b: &str| parse(b).unwrap_err();
        assert!(e("points:\n 1, 2\n 3, 4\n")
            .contains("Option 'z_positions' in section 'z_tilt' must be specified"));
        assert!(e("z_positions:\n 1, 2\n 3, 4\n 5, 6\npoints:\n 1, 2\n 3, 4\n")
            .contains("has 3 positions, the printer has 2 Z motors"));
        assert!(
            e("z_positions:\n 1, 2\n 3, 4\npoints:\n 1, 2\n").contains("[z_tilt] points: needs at least 2")
        );
        assert!(e("z_positions:\n 1, 2\n 3\npoints:\n 1, 2\n 3, 4\n")
            .contains("each line must be two numbers 'X, Y', got '3'"));
    }

    #[test]
    fn quad_gantry_level() {
        let z23 = "[stepper_z2]\nstep_pin: PE0\ndir_pin: PE1\nmicrosteps: 16\nrotation_distance: 8\n\
                   [stepper_z3]\nstep_pin: PF0\ndir_pin: PF1\nmicrosteps: 16\nrotation_distance: 8\n";
        let q = |body: &str| {
            parse_str(
                &format!("{BASE}{Z1}{z23}[quad_gantry_level]\n{body}"),
                Path::new("printer.cfg"),
            )
            .map(|c| c.quad_gantry_level.unwrap_or_else(|| panic!("no qgl")))
            .map_err(|e| e.to_string())
        };
        let g = q("gantry_corners:\n -60, -10\n 360, 370\npoints:\n 50, 25\n 50, 225\n 250, 225\n 250, 25\nmax_adjust: 10\n")
            .unwrap();
        assert_eq!(
            g.z_positions,
            vec![[-60.0, -10.0], [-60.0, 370.0], [360.0, 370.0], [360.0, -10.0]]
        );
        assert_eq!(g.max_adjust, Some(10.0));
        let e = q("gantry_corners:\n 0, 0\n 1, 1\npoints:\n 1, 1\n 2, 2\n 3, 3\n").unwrap_err();
        assert!(e.contains("[quad_gantry_level] points: needs at least 4"), "{e}");
        let two = parse_str(
            &format!("{BASE}{Z1}[quad_gantry_level]\ngantry_corners:\n 0, 0\n 1, 1\npoints:\n 1, 1\n 2, 2\n 3, 3\n 4, 4\n"),
            Path::new("printer.cfg"),
        )
        .map(|_| ())
        .unwrap_err()
        .to_string();
        assert!(two.contains("needs 4 Z motors"), "{two}");
    }

    proptest::proptest! {
        #[test]
        fn never_panics(a in "[-0-9., \n]{0,20}") {
            let _ = parse(&format!("z_positions:{a}\npoints:{a}\n"));
        }
    }
}
