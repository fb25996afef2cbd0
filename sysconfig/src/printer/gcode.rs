//! The sections that shape how G-code is taken, all optional:
//! - `[gcode]` (Cadence-specific): a command the planner does not know is reported the way
//!   Klipper reports it (`Unknown command:"M486"`, once per name) and skipped, the print going
//!   on (`unknown_commands: warn`, the default, Klipper's behaviour); `unknown_commands: error`
//!   (or `cadence print --strict`) stops the print with an error naming its line instead.
//! - `[gcode_arcs]` (Klipper's): `resolution`, the chord length G2/G3 arcs are split into.
//! - `[firmware_retraction]` (Klipper's): what G10/G11 do, until SET_RETRACTION changes it.
//! - `[respond]` (Klipper's): `RESPOND` and `M118` answer with `default_prefix`, else the
//!   prefix of `default_type` (`echo`, `command`, `error`; default `echo`).

use planner::machine::{Retraction, ARC_RESOLUTION};

use super::error::{ConfigError, ValueProblem};
use super::reader::{Bounds, SectionReader};

/// What an unknown G-code command does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UnknownCommands {
    /// Stop with an error naming file and line (strict).
    Error,
    /// Report it as Klipper does and skip it, once per command name (the default).
    Warn,
}

/// `[gcode]`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GcodeSection {
    pub unknown_commands: UnknownCommands,
}

impl Default for GcodeSection {
    fn default() -> Self {
        GcodeSection {
            unknown_commands: UnknownCommands::Warn,
        }
    }
}

const CHOICES: [(&str, UnknownCommands); 2] =
    [("error", UnknownCommands::Error), ("warn", UnknownCommands::Warn)];

pub(crate) fn read_gcode(s: &SectionReader<'_>) -> Result<GcodeSection, ConfigError> {
    let d = GcodeSection::default();
    Ok(GcodeSection {
        unknown_commands: s.choice("unknown_commands", &CHOICES, Some(d.unknown_commands))?,
    })
}

/// `[gcode_arcs]`.
#[derive(Debug, Clone, PartialEq)]
pub struct GcodeArcsSection {
    /// Chord length of G2/G3 arcs (mm, default the planner's [`ARC_RESOLUTION`], Klipper's 1).
    pub resolution: f64,
}

impl Default for GcodeArcsSection {
    fn default() -> Self {
        GcodeArcsSection {
            resolution: ARC_RESOLUTION,
        }
    }
}

pub(crate) fn read_gcode_arcs(s: &SectionReader<'_>) -> Result<GcodeArcsSection, ConfigError> {
    let d = GcodeArcsSection::default();
    Ok(GcodeArcsSection {
        resolution: s.float_or("resolution", d.resolution, Bounds::ANY.above(0.0))?,
    })
}

/// `[respond]`: the default prefix of `RESPOND`/`M118` answers.
pub(crate) fn read_respond(s: &SectionReader<'_>) -> Result<String, ConfigError> {
    let types = planner::gcode::respond::RESPOND_TYPES;
    let default_type = match s.value("default_type") {
        Some(v) => {
            let t = v.text.trim();
            planner::gcode::respond::type_prefix(Some(t)).ok_or_else(|| {
                let expected = types.iter().map(|(n, _)| n.to_string()).collect();
                s.bad(
                    "default_type",
                    v,
                    ValueProblem::NotAChoice {
                        got: t.to_string(),
                        expected,
                    },
                )
            })?
        }
        None => "echo:",
    };
    Ok(match s.value("default_prefix") {
        Some(v) => v.text.trim().to_string(),
        None => default_type.to_string(),
    })
}

/// `[firmware_retraction]`: the planner's G10/G11 settings, whose defaults are Klipper's
/// (length 0 and 0 extra, speeds 20 and 10 mm/s).
pub type FirmwareRetractionSection = Retraction;

pub(crate) fn read_firmware_retraction(
    s: &SectionReader<'_>,
) -> Result<FirmwareRetractionSection, ConfigError> {
    let d = FirmwareRetractionSection::default();
    Ok(FirmwareRetractionSection {
        retract_length: s.float_or("retract_length", d.retract_length, Bounds::ANY.min(0.0))?,
        retract_speed: s.float_or("retract_speed", d.retract_speed, Bounds::ANY.min(1.0))?,
        unretract_extra_length: s.float_or(
            "unretract_extra_length",
            d.unretract_extra_length,
            Bounds::ANY.min(0.0),
        )?,
        unretract_speed: s.float_or("unretract_speed", d.unretract_speed, Bounds::ANY.min(1.0))?,
    })
}

#[cfg(test)]
mod tests {
    use super::{FirmwareRetractionSection, GcodeArcsSection, GcodeSection, UnknownCommands};

    use crate::printer::simulated_with as config;

    fn with(section: &str) -> Result<GcodeSection, String> {
        config(section).map(|c| c.gcode)
    }

    #[test]
    fn arcs_and_retraction_read_with_klipper_defaults() {
        let c = config("").unwrap();
        assert_eq!(c.gcode_arcs, GcodeArcsSection::default());
        assert_eq!(c.firmware_retraction, FirmwareRetractionSection::default());
        let c = config(
            "[gcode_arcs]\nresolution: 0.1\n[firmware_retraction]\nretract_length: 0.8\n\
             retract_speed: 35\nunretract_extra_length: 0.05\nunretract_speed: 25",
        )
        .unwrap();
        assert_eq!(c.gcode_arcs.resolution, 0.1);
        assert_eq!(
            c.firmware_retraction,
            FirmwareRetractionSection {
                retract_length: 0.8,
                retract_speed: 35.0,
                unretract_extra_length: 0.05,
                unretract_speed: 25.0,
            }
        );
        assert!(c
            .warnings
            .iter()
            .all(|w| !w.contains("gcode_arcs") && !w.contains("firmware_retraction")));
        for (text, option) in [
            ("[gcode_arcs]\nresolution: 0", "resolution"),
            ("[firmware_retraction]\nretract_length: -1", "retract_length"),
            ("[firmware_retraction]\nretract_speed: 0.5", "retract_speed"),
            ("[firmware_retraction]\nunretract_speed: fast", "unretract_speed"),
        ] {
            let e = config(text).unwrap_err();
            assert!(e.contains(option), "{text}: {e}");
        }
    }

    #[test]
    fn respond_prefix_from_type_or_prefix() {
        let prefix = |section: &str| config(section).map(|c| c.respond);
        assert_eq!(prefix("").unwrap(), None);
        assert_eq!(prefix("[respond]").unwrap().as_deref(), Some("echo:"));
        assert_eq!(
            prefix("[respond]\ndefault_type: error").unwrap().as_deref(),
            Some("!!")
        );
        assert_eq!(
            prefix("[respond]\ndefault_type: command\ndefault_prefix: note:")
                .unwrap()
                .as_deref(),
            Some("note:")
        );
        let e = prefix("[respond]\ndefault_type: loud").unwrap_err();
        assert!(
            e.contains("default_type") && e.contains("loud") && e.contains("command"),
            "{e}"
        );
    }

    #[test]
    fn unknown_commands_are_skipped_unless_error() {
        assert_eq!(with("").unwrap().unknown_commands, UnknownCommands::Warn);
        assert_eq!(
            with("[gcode]\nunknown_commands: warn").unwrap().unknown_commands,
            UnknownCommands::Warn
        );
        assert_eq!(
            with("[gcode]\nunknown_commands: error").unwrap().unknown_commands,
            UnknownCommands::Error
        );
    }

    #[test]
    fn bad_values_name_section_and_option() {
        let e = with("[gcode]\nunknown_commands: ignore").unwrap_err();
        assert!(
            e.contains("[gcode]") && e.contains("unknown_commands") && e.contains("warn"),
            "{e}"
        );
        let e = with("[gcode]\nstrict: 1").unwrap_err();
        assert!(e.contains("strict") && e.contains("gcode"), "{e}");
    }
}
