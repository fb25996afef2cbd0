//! Klipper sections Cadence accepts but does not implement yet: a config containing them loads,
//! with one warning per kind ("[bed_mesh] is not implemented by Cadence yet; section ignored"),
//! instead of failing. Some of them would shape motion or homing on Klipper (`bed_mesh`,
//! `skew_correction`, `safe_z_home`, `homing_override`): the warning is the
//! user's notice that they are not applied; their G-code commands are unknown commands (errors
//! by default, see `[gcode]`). Extra steppers and dual carriages are deliberately not on this
//! list: a config with them does not load.

/// Section kinds (the first word of the section name) that are read past with a warning.
pub const IGNORED_SECTIONS: &[&str] = &[
    "adc_temperature",
    "bed_mesh",
    "bed_screws",
    "bed_tilt",
    "bltouch",
    "board_pins",
    "controller_fan",
    "delayed_gcode",
    "display",
    "display_data",
    "display_glyph",
    "display_status",
    "display_template",
    "dotstar",
    "endstop_phase",
    "exclude_object",
    "fan",
    "fan_generic",
    "filament_motion_sensor",
    "filament_switch_sensor",
    "force_move",
    "gcode_button",
    "gcode_macro",
    "heater_fan",
    "homing_heaters",
    "homing_override",
    "idle_timeout",
    "led",
    "menu",
    "neopixel",
    "output_pin",
    "pause_resume",
    "print_stats",
    "quad_gantry_level",
    "respond",
    "safe_z_home",
    "save_variables",
    "screws_tilt_adjust",
    "servo",
    "skew_correction",
    "static_digital_output",
    "temperature_fan",
    "temperature_sensor",
    "thermistor",
    "tmc2130",
    "tmc2208",
    "tmc2209",
    "tmc2240",
    "tmc2660",
    "tmc5160",
    "verify_heater",
    "virtual_sdcard",
    "z_tilt",
];

/// True when sections of `kind` are accepted and ignored.
pub fn is_ignored(kind: &str) -> bool {
    IGNORED_SECTIONS.contains(&kind)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn list_is_sorted_and_unique() {
        assert!(IGNORED_SECTIONS.windows(2).all(|w| w[0] < w[1]));
        assert!(is_ignored("gcode_macro") && is_ignored("tmc2209") && !is_ignored("stepper_z1"));
    }
}
