//! Why the G-code loop stopped or one of its commands failed, located as the printer reports
//! it: `FILE:LINE: COMMAND: why`, `… (in macro OUTER > INNER)` for a macro's line. The
//! target's own errors (the MCUs, the hand-off, a stop) are kept as they are, typed.

use std::path::PathBuf;

use planner::gcode::{GcodeError, GcodeErrorKind};
use planner::machine::{PlanError, PlanErrorKind};

use crate::heaters::gcode::HeatCmdError;
use crate::homing::procedure::ProcedureError;

/// Why the feed stopped (or, in a session, one checked command failed). `E`: the errors of
/// the [`super::FeedTarget`]. (`Display` and `Error` are written out: a derive would ask
/// `Box<FeedError<E>>: Display` of itself, through [`FeedError::InMacro`].)
#[derive(Debug)]
pub enum FeedError<E> {
    /// A line that does not parse (the error names its line): `FILE: why`.
    Read { file: PathBuf, source: GcodeError },
    /// The planner refused a line or a print time (the error names its line): `FILE: why`.
    Plan { file: PathBuf, source: PlanError },
    /// A command of line `line` failed: `FILE:LINE: why`.
    Command {
        file: PathBuf,
        line: usize,
        source: CommandError<E>,
    },
    /// A macro could not be started or run on (located by [`MacroRunError`]).
    Macro(MacroRunError),
    /// A line that came through macros (`via`: `OUTER > INNER`) failed: `why (in macro VIA)`.
    InMacro { source: Box<FeedError<E>>, via: String },
    /// The target failed between commands (handing steps on, pacing).
    Target(E),
}

impl<E: std::fmt::Display> std::fmt::Display for FeedError<E> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FeedError::Read { file, source } => write!(f, "{}: {source}", file.display()),
            FeedError::Plan { file, source } => {
                write!(f, "{}: {source}{}", file.display(), strict_hint(&source.kind))
            }
            FeedError::Command { file, line, source } => write!(f, "{}:{line}: {source}", file.display()),
            FeedError::Macro(e) => e.fmt(f),
            FeedError::InMacro { source, via } => write!(f, "{source} (in macro {via})"),
            FeedError::Target(e) => e.fmt(f),
        }
    }
}

impl<E: std::error::Error + 'static> std::error::Error for FeedError<E> {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            FeedError::Read { source, .. } => Some(source),
            FeedError::Plan { source, .. } => Some(source),
            FeedError::Command { source, .. } => Some(source),
            FeedError::InMacro { source, .. } => Some(&**source),
            // Transparent: the inner error's own source.
            FeedError::Macro(e) => e.source(),
            FeedError::Target(e) => e.source(),
        }
    }
}

impl<E> From<MacroRunError> for FeedError<E> {
    fn from(e: MacroRunError) -> Self {
        FeedError::Macro(e)
    }
}

impl<E> FeedError<E> {
    /// `source` of command line `line` of `file`.
    pub(crate) fn at(file: &std::path::Path, line: usize, source: CommandError<E>) -> FeedError<E> {
        FeedError::Command {
            file: file.to_path_buf(),
            line,
            source,
        }
    }
}

/// The hint after an unknown command refused in strict mode.
fn strict_hint(kind: &PlanErrorKind) -> &'static str {
    match kind {
        PlanErrorKind::UnknownCommand(_) => {
            " (strict mode: without --strict and with `unknown_commands: warn` in [gcode], the default, it is reported and skipped as Klipper does)"
        }
        _ => "",
    }
}

/// Why one command failed (located by [`FeedError::Command`]).
#[derive(Debug, thiserror::Error)]
pub enum CommandError<E> {
    /// A malformed heater or fan command.
    #[error(transparent)]
    Heat(#[from] HeatCmdError),
    /// The target refused a heater command, the drivers going off or an extruding move.
    #[error(transparent)]
    Target(E),
    /// G28 or a probe or TMC command with the MCUs in the loop (`cmd`: its name).
    #[error("{cmd}: {source}")]
    Motion {
        cmd: String,
        #[source]
        source: E,
    },
    /// A parameter of `SET_KINEMATIC_POSITION`, `FORCE_MOVE` or `STEPPER_BUZZ` (`cmd`).
    #[error("{cmd}: {source}")]
    Param {
        cmd: &'static str,
        #[source]
        source: GcodeErrorKind,
    },
    /// A required parameter of `cmd` is missing.
    #[error("{cmd}: missing {key}")]
    Missing { cmd: &'static str, key: &'static str },
    /// The planner refused a stepper moved on its own.
    #[error("{cmd}: {source}")]
    Forced {
        cmd: &'static str,
        #[source]
        source: PlanErrorKind,
    },
    /// A G28 procedure (`[safe_z_home]`, `[homing_override]`) failed.
    #[error("G28: {0}")]
    Homing(#[from] G28Error),
    /// `[probe] activate_gcode` or `deactivate_gcode` (`option`) moved the toolhead (Klipper's
    /// message).
    #[error("Toolhead moved during probe {option} script")]
    ProbeScriptMoved { option: &'static str },
    /// `[bed_screws]`'s tool refused a command, or one of its moves (`cmd`: the command).
    #[error("{cmd}: {source}")]
    BedScrews {
        cmd: String,
        #[source]
        source: BedScrewsFailure,
    },
}

/// Why a command of `[bed_screws]`'s tool failed.
#[derive(Debug, thiserror::Error)]
pub enum BedScrewsFailure {
    /// The tool's own refusal (already running).
    #[error(transparent)]
    Tool(#[from] planner::gcode::bed_screws::BedScrewsError),
    /// The axes are not homed (the tool's moves need them).
    #[error("Must home axis first: {0} (G28)")]
    NotHomed(char),
    /// The planner refused one of its moves (the tool ends, as in Klipper).
    #[error(transparent)]
    Move(#[from] PlanError),
}

/// Why a `[safe_z_home]` or `[homing_override]` G28 failed on its own.
#[derive(Debug, thiserror::Error)]
pub enum G28Error {
    /// The procedure's order was not met.
    #[error(transparent)]
    Procedure(#[from] ProcedureError),
    /// The planner refused a move of the procedure.
    #[error(transparent)]
    Move(#[from] PlanError),
}

/// Why a macro call, `SET_GCODE_VARIABLE` or a `[respond]` command failed, at the calling
/// line of `file` (`via`: the macros a failing line came through).
#[derive(Debug, thiserror::Error)]
#[error("{}:{line}: {}{source}", .file.display(), .via.as_ref().map(|v| format!("in macro {v}: ")).unwrap_or_default())]
pub struct MacroRunError {
    pub file: PathBuf,
    pub line: usize,
    pub via: Option<String>,
    #[source]
    pub source: Box<MacroStepError>,
}

/// What went wrong in one step of a macro run.
#[derive(Debug, thiserror::Error)]
pub enum MacroStepError {
    /// A macro did not render or a call was refused (recursion, a bad parameter).
    #[error(transparent)]
    Macro(#[from] planner::gcode::macros::MacroError),
    /// A `[respond]` command's parameter.
    #[error(transparent)]
    Respond(#[from] planner::gcode::respond::RespondError),
    /// A command of the host's (timers, `[save_variables]`, `[idle_timeout]`…) was refused.
    #[error(transparent)]
    Host(#[from] planner::gcode::host::HostError),
    /// `SAVE_VARIABLE` could not write its file.
    #[error("Unable to save variable ({}: {source})", .path.display())]
    Save {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A line a macro produced does not parse.
    #[error(transparent)]
    Parse(#[from] GcodeError),
}
