//! `[bed_mesh]` (Klipper's options, defaults and bounds) and the saved mesh profiles
//! `[bed_mesh NAME]` SAVE_CONFIG writes into the autosave block.
//!
//! Rectangular bed: `mesh_min`, `mesh_max` (`X, Y`, probe coordinates), `probe_count` (`X, Y` or
//! one number for both, each ≥ 3; default 3). Round bed: `mesh_radius` (> 0), `mesh_origin`
//! (default 0, 0), `round_probe_count` (odd, ≥ 3; default 5). Both: `speed` (default 50),
//! `horizontal_move_z` (default 5), `mesh_pps` (default 2, 2), `algorithm` (`lagrange`
//! default, `bicubic`; lagrange allows at most 6 points per axis, bicubic needs 4 and falls
//! back to lagrange otherwise, with a warning), `bicubic_tension` (0..=2, default 0.2),
//! `fade_start` (default 1), `fade_end` (default 0: no fade; else above `fade_start`),
//! `fade_target` (default: the mesh's average), `split_delta_z` (≥ 0.01, default 0.025),
//! `move_check_distance` (≥ 3, default 5), `zero_reference_position` (`X, Y`: the mesh is
//! shifted so its height there is 0). `faulty_region_*` are refused (not implemented).

use planner::bed_mesh::{Algorithm, MeshParams, BICUBIC_MIN_COUNT, LAGRANGE_MAX_COUNT};

use super::error::{ConfigError, ValueProblem};
use super::reader::{parse_float, Bounds, Reader, SectionReader};

/// The choices of `algorithm`.
pub const ALGORITHMS: [(&str, Algorithm); 2] =
    [("lagrange", Algorithm::Lagrange), ("bicubic", Algorithm::Bicubic)];

/// The bed's shape and probe grid.
#[derive(Debug, Clone, PartialEq)]
pub enum MeshShape {
    Rectangular {
        min: [f64; 2],
        max: [f64; 2],
        count: [usize; 2],
    },
    Round {
        origin: [f64; 2],
        radius: f64,
        count: usize,
    },
}

/// `[bed_mesh]`.
#[derive(Debug, Clone, PartialEq)]
pub struct BedMeshSection {
    pub shape: MeshShape,
    /// Travel speed between probe points (mm/s).
    pub speed: f64,
    /// Z of the travel between probe points.
    pub horizontal_move_z: f64,
    pub pps: [usize; 2],
    /// As configured; see [`MeshParams::effective_algorithm`].
    pub algorithm: Algorithm,
    pub bicubic_tension: f64,
    pub fade_start: f64,
    pub fade_end: f64,
    pub fade_target: Option<f64>,
    pub split_delta_z: f64,
    pub move_check_distance: f64,
    pub zero_reference_position: Option<[f64; 2]>,
    /// The saved profiles `[bed_mesh NAME]`, in file order.
    pub profiles: Vec<MeshProfile>,
}

/// A saved mesh: `[bed_mesh NAME]`.
#[derive(Debug, Clone, PartialEq)]
pub struct MeshProfile {
    pub name: String,
    pub params: MeshParams,
    /// `[row][col]`.
    pub points: Vec<Vec<f64>>,
}

/// Profile format version Klipper writes (and this reads).
pub const PROFILE_VERSION: i64 = 1;

/// `X, Y` as two numbers (`None` when the option is absent).
pub(crate) fn pair(s: &SectionReader<'_>, option: &str) -> Result<Option<[f64; 2]>, ConfigError> {
    let Some(v) = s.value(option) else {
        return Ok(None);
    };
    let parts: Vec<&str> = v.text.split(',').map(str::trim).collect();
    match parts.as_slice() {
        [x, y] => Ok(Some([
            parse_float(x).map_err(|p| s.bad(option, v, p))?,
            parse_float(y).map_err(|p| s.bad(option, v, p))?,
        ])),
        _ => Err(s.bad(
            option,
            v,
            ValueProblem::Invalid(format!("must be two numbers 'X, Y', got '{}'", v.text)),
        )),
    }
}

/// `X, Y` or one integer for both, each at least `min`.
fn int_pair(
    s: &SectionReader<'_>,
    option: &str,
    default: [usize; 2],
    min: usize,
) -> Result<[usize; 2], ConfigError> {
    let Some(v) = s.value(option) else {
        return Ok(default);
    };
    let parse = |t: &str| -> Result<usize, ValueProblem> {
        let n: i64 = t.parse().map_err(|_| ValueProblem::NotAnInteger(t.to_string()))?;
        if n < min as i64 {
            return Err(ValueProblem::BelowMinimum {
                min: min as f64,
                got: n as f64,
            });
        }
        usize::try_from(n).map_err(|_| ValueProblem::NotAnInteger(t.to_string()))
    };
    let parts: Vec<&str> = v.text.split(',').map(str::trim).collect();
    let r = match parts.as_slice() {
        [n] => parse(n).map(|n| [n, n]),
        [x, y] => parse(x).and_then(|x| Ok([x, parse(y)?])),
        _ => Err(ValueProblem::Invalid(format!(
            "must be 'X, Y' or one number, got '{}'",
            v.text
        ))),
    };
    r.map_err(|p| s.bad(option, v, p))
}

fn invalid(s: &SectionReader<'_>, option: &str, why: String) -> ConfigError {
    match s.value(option) {
        Some(v) => s.bad(option, v, ValueProblem::Invalid(why)),
        None => ConfigError::BadSection {
            at: s.at().clone(),
            section: s.name().to_string(),
            reason: why,
        },
    }
}

/// Reads `[bed_mesh]` and its saved profiles; warnings (bicubic falling back) go to `warnings`.
pub(crate) fn read_bed_mesh(
    reader: &Reader<'_>,
    s: &SectionReader<'_>,
    warnings: &mut Vec<String>,
) -> Result<BedMeshSection, ConfigError> {
    if let Some((name, _)) = s.options_with_prefix("faulty_region_").first() {
        return Err(invalid(
            s,
            &format!("faulty_region_{name}"),
            "faulty regions are not supported by Cadence yet".to_string(),
        ));
    }
    let shape = match s.opt_float("mesh_radius", Bounds::ANY.above(0.0))? {
        Some(radius) => {
            let origin = pair(s, "mesh_origin")?.unwrap_or([0.0, 0.0]);
            let count = s.int("round_probe_count", Some(5usize), 3..=99)?;
            if count % 2 == 0 {
                return Err(invalid(
                    s,
                    "round_probe_count",
                    format!("must be odd, got {count}"),
                ));
            }
            MeshShape::Round {
                origin,
                radius,
                count,
            }
        }
        None => {
            let min = pair(s, "mesh_min")?;
            let max = pair(s, "mesh_max")?;
            let (Some(min), Some(max)) = (min, max) else {
                let option = if min.is_none() { "mesh_min" } else { "mesh_max" };
                return Err(ConfigError::MissingOption {
                    at: s.at().clone(),
                    section: s.name().to_string(),
                    option: option.to_string(),
                });
            };
            if max[0] <= min[0] || max[1] <= min[1] {
                return Err(invalid(
                    s,
                    "mesh_max",
                    format!(
                        "must be above mesh_min on both axes: mesh_min {}, {}, mesh_max {}, {}",
                        min[0], min[1], max[0], max[1]
                    ),
                ));
            }
            let count = int_pair(s, "probe_count", [3, 3], 3)?;
            MeshShape::Rectangular { min, max, count }
        }
    };
    let count = match &shape {
        MeshShape::Rectangular { count, .. } => *count,
        MeshShape::Round { count, .. } => [*count, *count],
    };
    let pps = int_pair(s, "mesh_pps", [2, 2], 0)?;
    let mut algorithm = s.choice("algorithm", &ALGORITHMS, Some(Algorithm::Lagrange))?;
    let max_count = count[0].max(count[1]);
    if algorithm == Algorithm::Lagrange && max_count > LAGRANGE_MAX_COUNT && pps != [0, 0] {
        return Err(invalid(
            s,
            "algorithm",
            format!(
                "lagrange interpolation allows a probe_count of at most {LAGRANGE_MAX_COUNT}, got {}, {} (use algorithm: bicubic)",
                count[0], count[1]
            ),
        ));
    }
    if algorithm == Algorithm::Bicubic && count[0].min(count[1]) < BICUBIC_MIN_COUNT {
        warnings.push(format!(
            "{}: [bed_mesh] bicubic interpolation needs a probe_count of at least {BICUBIC_MIN_COUNT}: using lagrange",
            s.at()
        ));
        algorithm = Algorithm::Lagrange;
    }
    let bicubic_tension = s.float_or("bicubic_tension", 0.2, Bounds::ANY.min(0.0).max(2.0))?;
    let fade_start = s.float_or("fade_start", 1.0, Bounds::ANY)?;
    let fade_end = s.float_or("fade_end", 0.0, Bounds::ANY)?;
    if fade_end != 0.0 && fade_end <= fade_start {
        return Err(invalid(
            s,
            "fade_end",
            format!("must be above fade_start ({fade_start}), got {fade_end}"),
        ));
    }
    let fade_target = s.opt_float("fade_target", Bounds::ANY)?;
    let speed = s.float_or("speed", 50.0, Bounds::ANY.above(0.0))?;
    let horizontal_move_z = s.float_or("horizontal_move_z", 5.0, Bounds::ANY)?;
    let split_delta_z = s.float_or("split_delta_z", 0.025, Bounds::ANY.min(0.01))?;
    let move_check_distance = s.float_or("move_check_distance", 5.0, Bounds::ANY.min(3.0))?;
    let zero_reference_position = pair(s, "zero_reference_position")?;
    // Only with BED_MESH_CALIBRATE ADAPTIVE=1, which is refused: accepted and unused.
    let _ = s.opt_float("adaptive_margin", Bounds::ANY.min(0.0))?;
    let profiles = reader
        .sections_with_arg("bed_mesh")
        .iter()
        .map(read_profile)
        .collect::<Result<_, _>>()?;
    Ok(BedMeshSection {
        shape,
        speed,
        horizontal_move_z,
        pps,
        algorithm,
        bicubic_tension,
        fade_start,
        fade_end,
        fade_target,
        split_delta_z,
        move_check_distance,
        zero_reference_position,
        profiles,
    })
}

/// `[bed_mesh NAME]`: `version`, `points` (rows of comma-separated heights, one per line),
/// `x_count`, `y_count`, `mesh_x_pps`, `mesh_y_pps`, `algo`, `tension`, `min_x`, `max_x`,
/// `min_y`, `max_y`.
fn read_profile(s: &SectionReader<'_>) -> Result<MeshProfile, ConfigError> {
    let name = s.arg().unwrap_or_default().to_string();
    let version = s.int("version", Some(PROFILE_VERSION), i64::MIN..=i64::MAX)?;
    if version != PROFILE_VERSION {
        return Err(invalid(
            s,
            "version",
            format!("profile version {version} is not {PROFILE_VERSION}: calibrate the mesh again"),
        ));
    }
    let v = s.required("points")?;
    let points: Vec<Vec<f64>> = v
        .text
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .map(|l| {
            l.split(',')
                .map(|t| parse_float(t.trim()))
                .collect::<Result<Vec<f64>, _>>()
        })
        .collect::<Result<_, _>>()
        .map_err(|p| s.bad("points", v, p))?;
    let x_count = s.int("x_count", None, 2..=1000)?;
    let y_count = s.int("y_count", None, 2..=1000)?;
    let params = MeshParams {
        min: [s.float("min_x", Bounds::ANY)?, s.float("min_y", Bounds::ANY)?],
        max: [s.float("max_x", Bounds::ANY)?, s.float("max_y", Bounds::ANY)?],
        count: [x_count, y_count],
        pps: [
            s.int("mesh_x_pps", Some(2), 0..=1000)?,
            s.int("mesh_y_pps", Some(2), 0..=1000)?,
        ],
        algorithm: s.choice("algo", &ALGORITHMS, Some(Algorithm::Lagrange))?,
        tension: s.float_or("tension", 0.2, Bounds::ANY.min(0.0).max(2.0))?,
    };
    // The shape and the numbers are checked by building the mesh.
    planner::bed_mesh::ZMesh::new(params.clone(), points.clone())
        .map_err(|e| s.bad("points", v, ValueProblem::Invalid(e.to_string())))?;
    Ok(MeshProfile { name, params, points })
}

/// The options SAVE_CONFIG writes for a profile (Klipper's names and layout).
pub fn profile_options(params: &MeshParams, points: &[Vec<f64>]) -> Vec<(String, String)> {
    let rows: Vec<String> = points
        .iter()
        .map(|r| r.iter().map(|v| format!("{v:.6}")).collect::<Vec<_>>().join(", "))
        .collect();
    vec![
        ("version".into(), PROFILE_VERSION.to_string()),
        ("points".into(), format!("\n{}", rows.join("\n"))),
        ("x_count".into(), params.count[0].to_string()),
        ("y_count".into(), params.count[1].to_string()),
        ("mesh_x_pps".into(), params.pps[0].to_string()),
        ("mesh_y_pps".into(), params.pps[1].to_string()),
        ("algo".into(), params.algorithm.name().to_string()),
        ("tension".into(), format!("{}", params.tension)),
        ("min_x".into(), format!("{}", params.min[0])),
        ("max_x".into(), format!("{}", params.max[0])),
        ("min_y".into(), format!("{}", params.min[1])),
        ("max_y".into(), format!("{}", params.max[1])),
    ]
}

#[cfg(test)]
#[path = "bed_mesh_tests.rs"]
pub(crate) mod tests;
