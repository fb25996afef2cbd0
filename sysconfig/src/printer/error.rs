//! Why a printer config is rejected. Every message names the file, the line (when there is one),
//! the section and the option, in Klipper's words where Klipper has them:
//! `printer.cfg:14: [stepper_x] microsteps: expected an integer, got 'abc'`.

use std::path::PathBuf;

use crate::ini::{IniError, Location};

use super::pins::PinProblem;

/// What is wrong with one option's value.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ValueProblem {
    #[error("expected a number, got '{0}'")]
    NotANumber(String),
    #[error("expected a finite number, got '{0}'")]
    NotFinite(String),
    #[error("expected an integer, got '{0}'")]
    NotAnInteger(String),
    #[error("expected a boolean (true/false, yes/no, on/off, 1/0), got '{0}'")]
    NotABoolean(String),
    #[error("expected one of {}, got '{got}'", .expected.join(", "))]
    NotAChoice { got: String, expected: Vec<String> },
    #[error("must have minimum of {min}, got {got}")]
    BelowMinimum { min: f64, got: f64 },
    #[error("must have maximum of {max}, got {got}")]
    AboveMaximum { max: f64, got: f64 },
    #[error("must be above {bound}, got {got}")]
    NotAbove { bound: f64, got: f64 },
    #[error("must be below {bound}, got {got}")]
    NotBelow { bound: f64, got: f64 },
    #[error("expected ratios like '80:16, 3:1' with positive numbers, got '{0}'")]
    BadRatio(String),
    #[error("invalid pin '{pin}': {problem}")]
    BadPin { pin: String, problem: PinProblem },
    #[error("pin '{pin}' refers to mcu '{mcu}', but there is no [mcu {mcu}] section")]
    UnknownMcu { pin: String, mcu: String },
    #[error("pin '{pin}' is also used by [{section}] {option}")]
    PinInUse {
        pin: String,
        section: String,
        option: String,
    },
    #[error("shared pin '{pin}' must have the same '!' as in [{section}] {option}")]
    SharedPinPolarity {
        pin: String,
        section: String,
        option: String,
    },
    /// A rule between options or a value Cadence does not support (the text says which).
    #[error("{0}")]
    Invalid(String),
}

/// Why [`super::load`] / [`super::parse_str`] failed.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read or has a syntax error.
    #[error(transparent)]
    Ini(#[from] IniError),
    /// A section the config needs is absent (`at` is the main file: there is no line).
    #[error("{}: Section '{section}' must be specified{}", .file.display(), fmt_needed_by(.needed_by))]
    MissingSection {
        file: PathBuf,
        section: String,
        needed_by: Option<String>,
    },
    /// A `[gcode_macro]` whose template does not compile or whose variable is not a literal
    /// (the message names file, line and section).
    #[error(transparent)]
    Macro(Box<planner::gcode::macros::MacroError>),
    /// A section nothing reads and that is not on the list of accepted-and-ignored sections.
    #[error("{at}: Section '{section}' is not a valid config section")]
    UnknownSection { at: Location, section: String },
    /// A section whose name itself is wrong (e.g. `[mcu mcu]`).
    #[error("{at}: [{section}] {reason}")]
    BadSection {
        at: Location,
        section: String,
        reason: String,
    },
    /// A required option is absent (`at` is the section's header).
    #[error("{at}: Option '{option}' in section '{section}' must be specified")]
    MissingOption {
        at: Location,
        section: String,
        option: String,
    },
    /// An option nothing reads.
    #[error("{at}: Option '{option}' is not valid in section '{section}'")]
    UnknownOption {
        at: Location,
        section: String,
        option: String,
    },
    /// An option whose value is malformed, out of bounds, or inconsistent with others.
    #[error("{at}: [{section}] {option}: {problem}")]
    BadValue {
        at: Location,
        section: String,
        option: String,
        /// Boxed to keep `Result<_, ConfigError>` small.
        problem: Box<ValueProblem>,
    },
}

fn fmt_needed_by(by: &Option<String>) -> String {
    by.as_ref().map(|by| format!(" ({by})")).unwrap_or_default()
}

impl ConfigError {
    /// The file and line the error is about, when there is one.
    pub fn location(&self) -> Option<&Location> {
        match self {
            ConfigError::Ini(e) => e.location(),
            ConfigError::MissingSection { .. } | ConfigError::Macro(_) => None,
            ConfigError::UnknownSection { at, .. }
            | ConfigError::BadSection { at, .. }
            | ConfigError::MissingOption { at, .. }
            | ConfigError::UnknownOption { at, .. }
            | ConfigError::BadValue { at, .. } => Some(at),
        }
    }

    /// The section the error is about, when there is one.
    pub fn section(&self) -> Option<&str> {
        match self {
            ConfigError::Ini(_) | ConfigError::Macro(_) => None,
            ConfigError::MissingSection { section, .. }
            | ConfigError::UnknownSection { section, .. }
            | ConfigError::BadSection { section, .. }
            | ConfigError::MissingOption { section, .. }
            | ConfigError::UnknownOption { section, .. }
            | ConfigError::BadValue { section, .. } => Some(section),
        }
    }

    /// What is wrong with the value, for [`ConfigError::BadValue`].
    pub fn problem(&self) -> Option<&ValueProblem> {
        match self {
            ConfigError::BadValue { problem, .. } => Some(problem),
            _ => None,
        }
    }

    /// The option the error is about, when there is one.
    pub fn option(&self) -> Option<&str> {
        match self {
            ConfigError::MissingOption { option, .. }
            | ConfigError::UnknownOption { option, .. }
            | ConfigError::BadValue { option, .. } => Some(option),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(line: usize) -> Location {
        Location {
            file: PathBuf::from("printer.cfg"),
            line,
        }
    }

    #[test]
    fn messages_name_file_line_section_and_option() {
        let cases: Vec<(ConfigError, &str)> = vec![
            (
                ConfigError::BadValue {
                    at: at(14),
                    section: "stepper_x".into(),
                    option: "microsteps".into(),
                    problem: Box::new(ValueProblem::NotAnInteger("abc".into())),
                },
                "printer.cfg:14: [stepper_x] microsteps: expected an integer, got 'abc'",
            ),
            (
                ConfigError::MissingOption {
                    at: at(9),
                    section: "stepper_x".into(),
                    option: "rotation_distance".into(),
                },
                "printer.cfg:9: Option 'rotation_distance' in section 'stepper_x' must be specified",
            ),
            (
                ConfigError::UnknownOption {
                    at: at(12),
                    section: "stepper_x".into(),
                    option: "foo".into(),
                },
                "printer.cfg:12: Option 'foo' is not valid in section 'stepper_x'",
            ),
            (
                ConfigError::UnknownSection {
                    at: at(3),
                    section: "frobnicator".into(),
                },
                "printer.cfg:3: Section 'frobnicator' is not a valid config section",
            ),
            (
                ConfigError::MissingSection {
                    file: PathBuf::from("printer.cfg"),
                    section: "stepper_z".into(),
                    needed_by: Some("kinematics: cartesian".into()),
                },
                "printer.cfg: Section 'stepper_z' must be specified (kinematics: cartesian)",
            ),
            (
                ConfigError::MissingSection {
                    file: PathBuf::from("printer.cfg"),
                    section: "mcu".into(),
                    needed_by: None,
                },
                "printer.cfg: Section 'mcu' must be specified",
            ),
            (
                ConfigError::BadSection {
                    at: at(1),
                    section: "mcu mcu".into(),
                    reason: "bad name".into(),
                },
                "printer.cfg:1: [mcu mcu] bad name",
            ),
        ];
        for (e, want) in cases {
            assert_eq!(e.to_string(), want);
        }
    }

    #[test]
    fn value_problem_messages() {
        let cases: Vec<(ValueProblem, &str)> = vec![
            (ValueProblem::NotANumber("x".into()), "expected a number, got 'x'"),
            (
                ValueProblem::NotFinite("nan".into()),
                "expected a finite number, got 'nan'",
            ),
            (
                ValueProblem::NotABoolean("2".into()),
                "expected a boolean (true/false, yes/no, on/off, 1/0), got '2'",
            ),
            (
                ValueProblem::NotAChoice {
                    got: "polar".into(),
                    expected: vec!["cartesian".into(), "corexy".into()],
                },
                "expected one of cartesian, corexy, got 'polar'",
            ),
            (
                ValueProblem::BelowMinimum { min: 1.0, got: 0.0 },
                "must have minimum of 1, got 0",
            ),
            (
                ValueProblem::AboveMaximum { max: 0.001, got: 0.5 },
                "must have maximum of 0.001, got 0.5",
            ),
            (
                ValueProblem::NotAbove {
                    bound: 0.0,
                    got: -40.0,
                },
                "must be above 0, got -40",
            ),
            (
                ValueProblem::NotBelow { bound: 1.0, got: 1.0 },
                "must be below 1, got 1",
            ),
            (
                ValueProblem::BadRatio("3".into()),
                "expected ratios like '80:16, 3:1' with positive numbers, got '3'",
            ),
            (
                ValueProblem::UnknownMcu {
                    pin: "ebb:PA0".into(),
                    mcu: "ebb".into(),
                },
                "pin 'ebb:PA0' refers to mcu 'ebb', but there is no [mcu ebb] section",
            ),
            (
                ValueProblem::PinInUse {
                    pin: "PA0".into(),
                    section: "stepper_x".into(),
                    option: "step_pin".into(),
                },
                "pin 'PA0' is also used by [stepper_x] step_pin",
            ),
            (
                ValueProblem::SharedPinPolarity {
                    pin: "PA2".into(),
                    section: "stepper_x".into(),
                    option: "enable_pin".into(),
                },
                "shared pin 'PA2' must have the same '!' as in [stepper_x] enable_pin",
            ),
            (ValueProblem::Invalid("something".into()), "something"),
        ];
        for (p, want) in cases {
            assert_eq!(p.to_string(), want);
        }
    }

    #[test]
    fn accessors() {
        let e = ConfigError::BadValue {
            at: at(2),
            section: "printer".into(),
            option: "max_accel".into(),
            problem: Box::new(ValueProblem::NotANumber("x".into())),
        };
        assert_eq!(
            (e.section(), e.option(), e.location().map(|l| l.line)),
            (Some("printer"), Some("max_accel"), Some(2))
        );
    }
}
