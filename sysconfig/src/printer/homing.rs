//! `[safe_z_home]` and `[homing_override]`: how G28 runs, as Klipper's config reference
//! describes them (the host's `homing::procedure` carries them out).
//!
//! `[safe_z_home]`: `home_xy_position` (required, `X, Y`), `speed` (> 0, default 50 mm/s),
//! `z_hop` (mm, default 0: none), `z_hop_speed` (> 0, default 15 mm/s), `move_to_previous`
//! (default false); it needs a `[stepper_z]`.
//! `[homing_override]`: `gcode` (required, a template run in place of G28), `axes` (default
//! `xyz`: a G28 naming none of them homes normally), `set_position_x/y/z` (the position
//! assumed, and the axis counted as homed, before the script runs). The two cannot be used
//! together (Klipper refuses that too).

use planner::gcode::macros::MacroDef;

use super::error::{ConfigError, ValueProblem};
use super::reader::{parse_float, Bounds, Reader, SectionReader};

/// The name the `[homing_override]` script runs under as a macro: lower case, so that no
/// G-code command (upper-cased by the parser) can call it.
pub const HOMING_OVERRIDE_MACRO: &str = "homing_override";

/// `[safe_z_home]`.
#[derive(Debug, Clone, PartialEq)]
pub struct SafeZHomeSection {
    /// X, Y the toolhead moves to before Z homes.
    pub home_xy_position: [f64; 2],
    /// mm/s of the XY moves.
    pub speed: f64,
    /// mm Z is lifted before homing (0: no lift).
    pub z_hop: f64,
    /// mm/s of the lift.
    pub z_hop_speed: f64,
    /// Return X, Y to where they were after Z homed.
    pub move_to_previous: bool,
}

/// `[homing_override]`.
#[derive(Debug, Clone, PartialEq)]
pub struct HomingOverrideSection {
    /// The axes whose homing runs the script (X, Y, Z).
    pub axes: [bool; 3],
    /// Positions assumed (those axes counted as homed) before the script runs.
    pub set_position: [Option<f64>; 3],
    /// The script, as a macro named [`HOMING_OVERRIDE_MACRO`].
    pub script: MacroDef,
}

/// Reads `[safe_z_home]`; `has_stepper_z`: the kinematics has a `[stepper_z]`.
pub(crate) fn read_safe_z_home(
    s: &SectionReader<'_>,
    has_stepper_z: bool,
) -> Result<SafeZHomeSection, ConfigError> {
    let v = s.required("home_xy_position")?;
    let parts: Vec<&str> = v.text.split(',').map(str::trim).collect();
    let home_xy_position = match parts.as_slice() {
        [x, y] => [
            parse_float(x).map_err(|p| s.bad("home_xy_position", v, p))?,
            parse_float(y).map_err(|p| s.bad("home_xy_position", v, p))?,
        ],
        _ => {
            let why = format!("must be two numbers 'X, Y', got '{}'", v.text);
            return Err(s.bad("home_xy_position", v, ValueProblem::Invalid(why)));
        }
    };
    if !has_stepper_z {
        return Err(ConfigError::BadSection {
            at: s.at().clone(),
            section: s.name().to_string(),
            reason: "needs a [stepper_z] (Missing Z endstop config for safe_z_homing)".to_string(),
        });
    }
    Ok(SafeZHomeSection {
        home_xy_position,
        speed: s.float_or("speed", 50.0, Bounds::ANY.above(0.0))?,
        z_hop: s.float_or("z_hop", 0.0, Bounds::ANY)?,
        z_hop_speed: s.float_or("z_hop_speed", 15.0, Bounds::ANY.above(0.0))?,
        move_to_previous: s.opt_bool("move_to_previous")?.unwrap_or(false),
    })
}

/// Reads `[homing_override]`.
pub(crate) fn read_homing_override(s: &SectionReader<'_>) -> Result<HomingOverrideSection, ConfigError> {
    let gcode = s.string("gcode")?;
    let axes_text = s
        .value("axes")
        .map_or("XYZ".to_string(), |v| v.text.to_uppercase());
    let axes = [b'X', b'Y', b'Z'].map(|a| axes_text.as_bytes().contains(&a));
    let set_position = [
        s.opt_float("set_position_x", Bounds::ANY)?,
        s.opt_float("set_position_y", Bounds::ANY)?,
        s.opt_float("set_position_z", Bounds::ANY)?,
    ];
    Ok(HomingOverrideSection {
        axes,
        set_position,
        script: MacroDef {
            name: HOMING_OVERRIDE_MACRO.to_string(),
            gcode,
            description: None,
            rename_existing: None,
            variables: Vec::new(),
            at: s.at().to_string(),
        },
    })
}

/// Both sections, refusing the two together.
pub(crate) fn read_homing(
    reader: &Reader<'_>,
    has_stepper_z: bool,
) -> Result<(Option<SafeZHomeSection>, Option<HomingOverrideSection>), ConfigError> {
    let safe = match reader.section("safe_z_home") {
        Some(s) => Some((read_safe_z_home(&s, has_stepper_z)?, s.at().clone())),
        None => None,
    };
    let over = match reader.section("homing_override") {
        Some(s) => Some(read_homing_override(&s)?),
        None => None,
    };
    if let (Some((_, at)), Some(_)) = (&safe, &over) {
        return Err(ConfigError::BadSection {
            at: at.clone(),
            section: "safe_z_home".to_string(),
            reason: "cannot be used together with [homing_override] (homing_override and safe_z_homing \
                     cannot be used simultaneously)"
                .to_string(),
        });
    }
    Ok((safe.map(|(s, _)| s), over))
}
