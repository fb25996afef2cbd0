//! A printer.cfg looked over as a whole (`cadence check-config`): every section with what
//! Cadence does with it (read, ignored, refused, unknown), the load's warnings, and as many
//! errors as can be found in one pass. The load stops at its first error, so the check loads
//! again after setting the reported part aside: a refused or unknown section is dropped, an
//! invalid or malformed option is dropped (the error it leaves behind, "must be specified", is
//! the same problem and not reported twice). Errors that leave nothing to set aside (a missing
//! section, a macro that does not compile) end the search.

use std::path::{Path, PathBuf};

use super::error::ConfigError;
use super::sections::{support, Support};
use super::PrinterConfig;
use crate::ini::{self, ConfigFile, Location};

/// Most loads one check makes (each finds one error).
const MAX_LOADS: usize = 200;

/// What Cadence does with one section of the file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SectionUse {
    /// Read and validated; it takes effect.
    Read,
    /// Accepted with a warning and no effect.
    Ignored,
    /// Not supported yet (the feature named).
    Refused(&'static str),
    /// Neither Klipper nor Cadence has such a section.
    Unknown,
}

impl SectionUse {
    /// One word for listings: `read`, `ignored`, `refused`, `unknown`.
    pub fn word(&self) -> &'static str {
        match self {
            SectionUse::Read => "read",
            SectionUse::Ignored => "ignored",
            SectionUse::Refused(_) => "refused",
            SectionUse::Unknown => "unknown",
        }
    }
}

/// One section of the checked file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CheckedSection {
    /// The full name (`stepper_x`, `gcode_macro START_PRINT`).
    pub name: String,
    /// Its first header.
    pub at: Location,
    pub usage: SectionUse,
}

/// The outcome of [`check`].
#[derive(Debug)]
pub struct ConfigCheck {
    /// The file checked.
    pub file: PathBuf,
    /// Every section, in file order (empty when the file could not be parsed).
    pub sections: Vec<CheckedSection>,
    /// The errors found, in the order the loads met them.
    pub errors: Vec<ConfigError>,
    /// Whether the search for errors ended early (an error that cannot be set aside), so the
    /// file may hold more.
    pub stopped_early: bool,
    /// The load's warnings (the last load's when there were errors).
    pub warnings: Vec<String>,
    /// The typed config when the file loads without error.
    pub config: Option<PrinterConfig>,
}

impl ConfigCheck {
    /// The sections used as `usage`.
    pub fn sections_of(&self, usage: fn(&SectionUse) -> bool) -> impl Iterator<Item = &CheckedSection> {
        self.sections.iter().filter(move |s| usage(&s.usage))
    }
}

/// Checks the printer.cfg at `path` (includes relative to it).
pub fn check(path: &Path) -> ConfigCheck {
    check_file(path, ini::load(path))
}

/// Checks `text` as the file `name`.
pub fn check_str(text: &str, name: &Path) -> ConfigCheck {
    check_file(name, ini::parse_str(text, name))
}

fn check_file(path: &Path, parsed: Result<ConfigFile, ini::IniError>) -> ConfigCheck {
    let mut report = ConfigCheck {
        file: path.to_path_buf(),
        sections: Vec::new(),
        errors: Vec::new(),
        stopped_early: false,
        warnings: Vec::new(),
        config: None,
    };
    let mut file = match parsed {
        Ok(f) => f,
        Err(e) => {
            report.errors.push(ConfigError::Ini(e));
            report.stopped_early = true;
            return report;
        }
    };
    report.sections = file
        .sections()
        .iter()
        .map(|s| CheckedSection {
            name: s.name().to_string(),
            at: s.at().clone(),
            usage: match support(s.kind()) {
                Some(Support::Read) => SectionUse::Read,
                Some(Support::Ignored) => SectionUse::Ignored,
                Some(Support::Refused(what)) => SectionUse::Refused(what),
                None => SectionUse::Unknown,
            },
        })
        .collect();
    // The option dropped after the last error: its "must be specified" is the same problem.
    let mut dropped: Option<(String, String)> = None;
    for _ in 0..MAX_LOADS {
        let e = match PrinterConfig::from_ini(&file) {
            Ok(cfg) => {
                report.warnings = cfg.warnings.clone();
                if report.errors.is_empty() {
                    report.config = Some(cfg);
                }
                return report;
            }
            Err(e) => e,
        };
        let set_aside = match &e {
            ConfigError::UnknownSection { section, .. } | ConfigError::BadSection { section, .. } => {
                file.remove_section(section)
            }
            ConfigError::UnknownOption { section, option, .. }
            | ConfigError::BadValue { section, option, .. } => {
                dropped = Some((section.clone(), option.clone()));
                file.remove_option(section, option)
            }
            ConfigError::MissingOption { section, option, .. } => {
                let same = dropped.as_ref().is_some_and(|(s, o)| s == section && o == option);
                if !same {
                    report.errors.push(e);
                }
                report.stopped_early = true;
                return report;
            }
            _ => false,
        };
        report.errors.push(e);
        if !set_aside {
            report.stopped_early = true;
            return report;
        }
    }
    report.stopped_early = true;
    report
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::printer::SIMULATED_PRINTER_CFG;

    fn run(extra: &str) -> ConfigCheck {
        check_str(
            &format!("{SIMULATED_PRINTER_CFG}\n{extra}"),
            Path::new("printer.cfg"),
        )
    }

    #[test]
    fn a_good_config_has_no_errors_and_lists_its_sections() {
        let c = run("[display_glyph heart]\n[neopixel led]\npin: PA9\n");
        assert!(c.errors.is_empty(), "{:?}", c.errors);
        assert!(c.config.is_some() && !c.stopped_early);
        let ignored: Vec<&str> = c
            .sections_of(|u| *u == SectionUse::Ignored)
            .map(|s| s.name.as_str())
            .collect();
        assert_eq!(ignored, ["display_glyph heart", "neopixel led"]);
        assert!(c
            .sections_of(|u| *u == SectionUse::Read)
            .any(|s| s.name == "printer"));
    }

    #[test]
    fn every_set_aside_error_is_reported_with_its_line() {
        let c = run(
            "[load_cell_probe]\npin: PA9\n[stepper_yy]\nstep_pin: PB1\n[gcode_arcs]\nresolution: 0\n\
             [firmware_retraction]\nretract_lenght: 1\n",
        );
        let texts: Vec<String> = c.errors.iter().map(|e| e.to_string()).collect();
        assert_eq!(texts.len(), 4, "{texts:#?}");
        assert!(
            texts[0].contains("[load_cell_probe] is not supported by Cadence yet"),
            "{texts:#?}"
        );
        let has = |needle: &str| texts.iter().any(|t| t.contains(needle));
        assert!(
            has("Section 'stepper_yy' is not a valid config section"),
            "{texts:#?}"
        );
        assert!(has("[gcode_arcs] resolution"), "{texts:#?}");
        assert!(
            has("Option 'retract_lenght' is not valid in section 'firmware_retraction'"),
            "{texts:#?}"
        );
        assert!(c.errors.iter().all(|e| e.location().is_some_and(|l| l.line > 0)));
        assert!(c.config.is_none() && !c.stopped_early);
        let refused: Vec<&str> = c
            .sections_of(|u| matches!(u, SectionUse::Refused(_)))
            .map(|s| s.name.as_str())
            .collect();
        assert_eq!(refused, ["load_cell_probe"]);
    }

    #[test]
    fn a_required_option_with_a_bad_value_is_one_error() {
        let text = SIMULATED_PRINTER_CFG.replacen("max_accel:", "max_accel: fast\n#", 1);
        let c = check_str(&text, Path::new("printer.cfg"));
        assert_eq!(c.errors.len(), 1, "{:?}", c.errors);
        assert!(c.errors[0].to_string().contains("max_accel"), "{}", c.errors[0]);
        assert!(c.stopped_early);
    }

    #[test]
    fn an_unreadable_file_is_one_error() {
        let c = check(Path::new("/nonexistent/printer.cfg"));
        assert_eq!(c.errors.len(), 1);
        assert!(c.sections.is_empty() && c.stopped_early);
    }
}
