//! `[gcode]` (Cadence-specific, optional): how G-code files are taken. A command the planner
//! does not know stops the print with an error naming its line (`unknown_commands: error`, the
//! default); `unknown_commands: warn` skips each such command with one warning per name (for
//! files full of slicer or macro commands this host does not implement, such as `START_PRINT`
//! from an ignored `[gcode_macro]`).

use super::error::ConfigError;
use super::reader::SectionReader;

/// What an unknown G-code command does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UnknownCommands {
    /// Stop with an error naming file and line.
    Error,
    /// Skip it, warning once per command name.
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
            unknown_commands: UnknownCommands::Error,
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

#[cfg(test)]
mod tests {
    use super::{GcodeSection, UnknownCommands};
    use crate::printer::parse_str;
    use std::path::Path;

    fn with(section: &str) -> Result<GcodeSection, String> {
        let text = format!("{}\n{section}\n", crate::printer::SIMULATED_PRINTER_CFG);
        parse_str(&text, Path::new("printer.cfg"))
            .map(|c| c.gcode)
            .map_err(|e| e.to_string())
    }

    #[test]
    fn unknown_commands_are_errors_unless_warn() {
        assert_eq!(with("").unwrap().unknown_commands, UnknownCommands::Error);
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
