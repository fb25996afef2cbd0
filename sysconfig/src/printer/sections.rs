//! Every section kind of Klipper's config reference, and what Cadence does with it: the one list
//! (README "printer.cfg sections") that says which sections are read, which are accepted and
//! ignored with one notice each, and which are refused because loading them without their
//! effect would make the printer move or home wrongly.
//!
//! Ignored sections have no effect on motion or homing without hardware Cadence does not drive
//! yet (displays, LEDs, digipots, accelerometers, fans and sensors, filament sensors) or are host
//! features not implemented yet whose absence the user should know of (`gcode_macro`,
//! `bed_tilt`, `skew_correction`…): the load warning is the notice, and their G-code commands are
//! unknown commands. Refused sections (load cell and eddy current probes, more extruders) fail the
//! load with `[section] is not supported by Cadence yet (what)`, before anything else is
//! checked, so the first error names the real cause.

/// What Cadence does with a section kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Support {
    /// Read and validated; it takes effect.
    Read,
    /// Accepted with a warning and no effect.
    Ignored,
    /// The load fails, naming the feature (the text) Cadence lacks.
    Refused(&'static str),
}

use Support::{Ignored, Read, Refused};

/// Section kinds (the first word of the section name), sorted, with their support. Klipper's
/// documented sections (v0.13 config reference), plus Cadence's own `[simulator]`,
/// `[realtime]` and `[gcode]`. `stepper_*` and `extruderN` are matched by [`support`].
pub const SECTIONS: &[(&str, Support)] = &[
    ("ad5206", Ignored),
    ("adc_scaled", Read),
    ("adc_temperature", Ignored),
    ("ads1x1x", Ignored),
    ("adxl345", Ignored),
    ("angle", Ignored),
    ("axis_twist_compensation", Ignored),
    ("bed_mesh", Read),
    ("bed_screws", Read),
    ("bed_tilt", Ignored),
    ("bltouch", Read),
    ("bmi160", Ignored),
    ("board_pins", Read),
    ("controller_fan", Read),
    ("dac084S085", Ignored),
    ("delayed_gcode", Read),
    ("delta_calibrate", Ignored),
    ("display", Ignored),
    ("display_data", Ignored),
    ("display_glyph", Ignored),
    ("display_status", Read),
    ("display_template", Ignored),
    ("dotstar", Ignored),
    ("dual_carriage", Refused("dual carriage")),
    ("duplicate_pin_override", Ignored),
    ("endstop_phase", Ignored),
    ("exclude_object", Read),
    ("extra_carriage", Refused("dual carriage")),
    ("extruder", Read),
    ("extruder_stepper", Read),
    ("fan", Read),
    ("fan_generic", Read),
    ("filament_motion_sensor", Ignored),
    ("filament_switch_sensor", Ignored),
    ("firmware_retraction", Read),
    ("force_move", Read),
    ("gcode", Read),
    ("gcode_arcs", Read),
    ("gcode_button", Ignored),
    ("gcode_macro", Read),
    ("hall_filament_width_sensor", Ignored),
    ("heater_bed", Read),
    ("heater_fan", Read),
    ("heater_generic", Read),
    ("homing_heaters", Ignored),
    ("homing_override", Read),
    ("icm20948", Ignored),
    ("idle_timeout", Read),
    ("input_shaper", Read),
    ("led", Ignored),
    ("lis2dw", Ignored),
    ("lis3dh", Ignored),
    ("load_cell", Ignored),
    ("load_cell_probe", Refused("load cell probe")),
    ("manual_stepper", Refused("manual steppers")),
    ("mcp4018", Ignored),
    ("mcp4451", Ignored),
    ("mcp4728", Ignored),
    ("mcu", Read),
    ("menu", Ignored),
    ("mpu9250", Ignored),
    ("multi_pin", Read),
    ("neopixel", Ignored),
    ("output_pin", Ignored),
    ("palette2", Ignored),
    ("pause_resume", Ignored),
    ("pca9533", Ignored),
    ("pca9632", Ignored),
    ("print_stats", Ignored),
    ("printer", Read),
    ("probe", Read),
    ("probe_eddy_current", Refused("eddy current probe")),
    ("pwm_cycle_time", Ignored),
    ("pwm_tool", Ignored),
    ("quad_gantry_level", Read),
    ("realtime", Read),
    ("replicape", Ignored),
    ("resonance_tester", Ignored),
    ("respond", Read),
    ("safe_z_home", Read),
    ("samd_sercom", Ignored),
    ("save_variables", Read),
    ("screws_tilt_adjust", Read),
    ("sdcard_loop", Ignored),
    ("servo", Ignored),
    ("simulator", Read),
    ("skew_correction", Ignored),
    ("smart_effector", Read),
    ("static_digital_output", Ignored),
    ("static_pwm_clock", Ignored),
    ("sx1509", Ignored),
    ("temperature_fan", Read),
    ("temperature_probe", Ignored),
    ("temperature_sensor", Read),
    ("thermistor", Read),
    ("tmc2130", Read),
    ("tmc2208", Read),
    ("tmc2209", Read),
    ("tmc2240", Read),
    ("tmc2660", Read),
    ("tmc5160", Read),
    ("tsl1401cl_filament_width_sensor", Ignored),
    ("verify_heater", Read),
    ("virtual_sdcard", Read),
    ("z_thermal_adjust", Ignored),
    ("z_tilt", Read),
];

/// What Cadence does with sections of `kind`; `None` for a kind Klipper does not have either
/// (then "is not a valid config section"). The kinematics' rails (`stepper_x`, `stepper_a`…)
/// and their further motors (`stepper_z1`, `stepper_x2`) are read; so are further extruders
/// up to `extruder9` (more are refused).
pub fn support(kind: &str) -> Option<Support> {
    if let Some(axis) = kind.strip_prefix("stepper_") {
        return match axis.as_bytes() {
            [a] if a.is_ascii_lowercase() => Some(Read),
            [a, n @ ..] if a.is_ascii_lowercase() && is_index(n) => Some(Read),
            _ => None,
        };
    }
    if let Some(n) = kind.strip_prefix("extruder") {
        if is_index(n.as_bytes()) {
            return Some(match n.parse::<usize>() {
                Ok(i) if i < planner::extruders::MAX_EXTRUDERS => Read,
                _ => Refused("more than 10 extruders"),
            });
        }
    }
    SECTIONS
        .binary_search_by(|(k, _)| (*k).cmp(kind))
        .ok()
        .and_then(|i| SECTIONS.get(i))
        .map(|&(_, s)| s)
}

/// `1`, `2`, … `10`: a decimal index without a leading zero.
fn is_index(n: &[u8]) -> bool {
    !n.is_empty() && n[0] != b'0' && n.iter().all(u8::is_ascii_digit)
}

/// True when sections of `kind` are accepted and ignored.
pub fn is_ignored(kind: &str) -> bool {
    support(kind) == Some(Ignored)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn list_is_sorted_and_unique() {
        assert!(SECTIONS.windows(2).all(|w| w[0].0 < w[1].0));
    }

    /// The README's copy of the list names every kind under its support and nothing else.
    #[test]
    fn readme_lists_every_kind_under_its_support() {
        let readme = include_str!("../../../README.md");
        let list = |head: &str| -> Vec<&str> {
            let start = readme
                .find(head)
                .unwrap_or_else(|| panic!("README has no {head}"));
            let rest = &readme[start..];
            // The list ends at the next list item or the paragraph's end, whichever is first.
            let paragraph = rest.find("\n\n").unwrap_or(rest.len());
            let end = rest[2..]
                .find("\n- **")
                .map_or(paragraph, |e| (e + 2).min(paragraph));
            rest[..end]
                .split("`[")
                .skip(1)
                .filter_map(|t| t.split_once("]`").map(|(k, _)| k))
                .collect()
        };
        let read = list("- **read**");
        let ignored = list("- **accepted and ignored**");
        let refused = list("- **refused**");
        for (kinds, want) in [(&read, "read"), (&ignored, "ignored"), (&refused, "refused")] {
            for kind in kinds.iter() {
                let name = kind.split_whitespace().next().unwrap_or(kind);
                let got = match support(name) {
                    Some(Read) => "read",
                    Some(Ignored) => "ignored",
                    Some(Refused(_)) => "refused",
                    None => "unknown",
                };
                assert_eq!(got, want, "README lists [{kind}] as {want}");
            }
        }
        for (kind, s) in SECTIONS {
            let listed = match s {
                Read => &read,
                Ignored => &ignored,
                Refused(_) => &refused,
            };
            assert!(listed.contains(kind), "README does not list [{kind}] as {s:?}");
        }
    }

    #[test]
    fn kinds() {
        assert!(is_ignored("ad5206"));
        assert_eq!(support("tmc2209"), Some(Read));
        assert_eq!(support("bed_mesh"), Some(Read));
        assert_eq!(support("gcode_macro"), Some(Read));
        assert_eq!(support("stepper_x"), Some(Read));
        assert_eq!(support("stepper_a"), Some(Read));
        assert_eq!(support("stepper_z1"), Some(Read));
        assert_eq!(support("stepper_y12"), Some(Read));
        assert_eq!(support("extruder1"), Some(Read));
        assert_eq!(support("extruder_stepper"), Some(Read));
        assert_eq!(support("extruder10"), Some(Refused("more than 10 extruders")));
        assert_eq!(support("extruder"), Some(Read));
        assert_eq!(support("bltouch"), Some(Read));
        assert_eq!(support("smart_effector"), Some(Read));
        assert_eq!(support("load_cell_probe"), Some(Refused("load cell probe")));
        for unknown in [
            "stepper_z01",
            "stepper_",
            "stepper_xy",
            "extruder01",
            "frobnicator",
            "",
        ] {
            assert_eq!(support(unknown), None, "{unknown}");
        }
    }
}
