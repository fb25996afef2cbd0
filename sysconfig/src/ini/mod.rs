//! Generic Klipper config-file reader: text → sections of `key: value` options, every value
//! remembering the file and line it came from. Knows nothing about printers.
//!
//! The format (Python configparser as Klipper configures it, plus Klipper's include and
//! SAVE_CONFIG handling):
//! - `[name]` or `[name arg]` opens a section (inner whitespace collapsed to one space);
//!   `[include path]` reads `path`, relative to the including file's directory, at that point.
//!   A file may be included twice, but not from inside itself (a cycle is an error).
//! - `key: value` or `key = value`: the first `:` or `=` splits; the key is trimmed and
//!   lowercased, the value trimmed.
//! - A line indented deeper than its option's line continues the value: appended after `'\n'`,
//!   trimmed. Blank lines inside a value are kept only when a continuation line follows them.
//!   So `gcode:` followed by indented lines gives `"\nG28\nG1 X10"`.
//! - `#` or `;` starts a comment at the start of a line or after whitespace (`PA0#x` keeps the
//!   `#`). Comment-only lines are skipped and do not end a multi-line value.
//! - A section seen again merges into the first: a later option replaces the earlier value and
//!   its location, in place (the first definition's order is kept).
//! - In the main file, Klipper's `#*# <--- SAVE_CONFIG --->` marker starts the autosave block:
//!   every later line must start with `#*#`, which is removed, and is read as more config with
//!   its own physical line numbers. As in Klipper, an option the config above the block (or a
//!   file it includes) already sets keeps that value: the block's copy is ignored (SAVE_CONFIG,
//!   [`crate::autosave`], comments the body's copy out when it writes the block).

mod parse;
mod write;

use std::fmt;
use std::io;
use std::path::{Path, PathBuf};

pub use parse::MAX_INCLUDE_DEPTH;

/// Where a value or section header came from: a file and a 1-based line number.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct Location {
    pub file: PathBuf,
    pub line: usize,
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}", self.file.display(), self.line)
    }
}

/// One option's value: its text (continuation lines joined with `'\n'`) and where its key was.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Value {
    pub text: String,
    pub at: Location,
}

/// One section after merging every `[name]` of the same name.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Section {
    name: String,
    at: Location,
    options: Vec<(String, Value)>,
}

impl Section {
    /// The full name: `stepper_x`, `mcu extra`, `gcode_macro START`.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The first word of the name: `mcu` for `[mcu extra]`.
    pub fn kind(&self) -> &str {
        self.name
            .split_once(' ')
            .map_or(self.name.as_str(), |(kind, _)| kind)
    }

    /// The rest of the name after the first word: `extra` for `[mcu extra]`.
    pub fn arg(&self) -> Option<&str> {
        self.name.split_once(' ').map(|(_, arg)| arg)
    }

    /// The first header of this section.
    pub fn at(&self) -> &Location {
        &self.at
    }

    /// The value of option `key` (lowercase), if present.
    pub fn get(&self, key: &str) -> Option<&Value> {
        self.options.iter().find(|(k, _)| k == key).map(|(_, v)| v)
    }

    /// Every option in first-definition order.
    pub fn options(&self) -> impl Iterator<Item = (&str, &Value)> {
        self.options.iter().map(|(k, v)| (k.as_str(), v))
    }

    /// Number of options.
    pub fn len(&self) -> usize {
        self.options.len()
    }

    /// True when the section has no options.
    pub fn is_empty(&self) -> bool {
        self.options.is_empty()
    }
}

/// A whole parsed config: sections in order of first appearance, and every file that was read.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ConfigFile {
    sections: Vec<Section>,
    files: Vec<PathBuf>,
}

impl ConfigFile {
    /// All sections in order of first appearance.
    pub fn sections(&self) -> &[Section] {
        &self.sections
    }

    /// The section named exactly `name` (e.g. `"mcu extra"`).
    pub fn section(&self, name: &str) -> Option<&Section> {
        self.sections.iter().find(|s| s.name == name)
    }

    /// The main file first, then every included file in the order it was read.
    pub fn files(&self) -> &[PathBuf] {
        &self.files
    }

    /// The main file's path (as given).
    pub fn main_file(&self) -> &Path {
        self.files.first().map_or(Path::new(""), PathBuf::as_path)
    }

    /// Removes section `name`; false when there is none. (`cadence check-config` drops a
    /// section it has reported to look for further errors.)
    pub fn remove_section(&mut self, name: &str) -> bool {
        let before = self.sections.len();
        self.sections.retain(|s| s.name != name);
        self.sections.len() != before
    }

    /// Removes option `key` of section `section`; false when there is none.
    pub fn remove_option(&mut self, section: &str, key: &str) -> bool {
        let Some(s) = self.sections.iter_mut().find(|s| s.name == section) else {
            return false;
        };
        let before = s.options.len();
        s.options.retain(|(k, _)| k != key);
        s.options.len() != before
    }

    /// Index of section `name`, adding an empty one located at `at` when new.
    fn section_index_or_insert(&mut self, name: String, at: Location) -> usize {
        if let Some(i) = self.sections.iter().position(|s| s.name == name) {
            return i;
        }
        self.sections.push(Section {
            name,
            at,
            options: Vec::new(),
        });
        self.sections.len() - 1
    }
}

/// A line the reader cannot make sense of.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SyntaxProblem {
    #[error("option '{0}' comes before any [section] header")]
    OptionOutsideSection(String),
    #[error("'[' without a closing ']'")]
    UnclosedHeader,
    #[error("empty section name '[]'")]
    EmptySectionName,
    #[error("unexpected text '{0}' after the section header")]
    TextAfterHeader(String),
    #[error("[include] needs a file name")]
    EmptyInclude,
    #[error("empty option name before ':' or '='")]
    EmptyOptionName,
    #[error("expected 'key: value', 'key = value', '[section]' or an indented continuation, got '{0}'")]
    NotAnOption(String),
    #[error("line inside the SAVE_CONFIG block does not start with '#*#'")]
    AutosaveCorrupt,
}

/// Why a config file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum IniError {
    /// The main file cannot be read (missing, unreadable, not UTF-8).
    #[error("{}: cannot read config file: {source}", .path.display())]
    Read { path: PathBuf, source: io::Error },
    /// An `[include]`d file cannot be read.
    #[error("{at}: Include file '{}' cannot be read: {source}", .path.display())]
    Include {
        at: Location,
        path: PathBuf,
        source: io::Error,
    },
    /// A file includes itself, directly or through others.
    #[error("{at}: Recursive include of config file '{}'", .path.display())]
    IncludeCycle { at: Location, path: PathBuf },
    /// `[include *.cfg]` whose pattern is malformed or whose directory cannot be listed.
    #[error("{at}: include '{spec}': {problem}")]
    IncludeGlob {
        at: Location,
        spec: String,
        problem: String,
    },
    /// Includes nested deeper than [`MAX_INCLUDE_DEPTH`] (e.g. a symlink loop).
    #[error("{at}: includes nested deeper than {MAX_INCLUDE_DEPTH} files")]
    IncludeTooDeep { at: Location },
    /// A line that is not a header, option, continuation or comment.
    #[error("{at}: {problem}")]
    Syntax { at: Location, problem: SyntaxProblem },
}

impl IniError {
    /// The file and line the error is about, when there is one.
    pub fn location(&self) -> Option<&Location> {
        match self {
            IniError::Read { .. } => None,
            IniError::Include { at, .. }
            | IniError::IncludeCycle { at, .. }
            | IniError::IncludeGlob { at, .. }
            | IniError::IncludeTooDeep { at }
            | IniError::Syntax { at, .. } => Some(at),
        }
    }
}

/// Reads and parses `path`, includes relative to its directory.
pub fn load(path: &Path) -> Result<ConfigFile, IniError> {
    let text = std::fs::read_to_string(path).map_err(|source| IniError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    parse_str(&text, path)
}

/// Parses `text` as if it were the file `name`; includes are read from the filesystem
/// relative to `name`'s directory.
pub fn parse_str(text: &str, name: &Path) -> Result<ConfigFile, IniError> {
    parse_with(text, name, &mut |p: &Path| std::fs::read_to_string(p))
}

/// Parses `text` as the file `name`, reading included files through `read` (tests use an
/// in-memory map); glob includes are listed from the filesystem ([`glob_files`]).
pub fn parse_with(
    text: &str,
    name: &Path,
    read: &mut dyn FnMut(&Path) -> io::Result<String>,
) -> Result<ConfigFile, IniError> {
    parse_with_listing(text, name, read, &mut glob_files)
}

/// [`parse_with`], listing the files a glob include matches through `list` (given the pattern
/// joined to the including file's directory; it returns them in any order).
pub fn parse_with_listing(
    text: &str,
    name: &Path,
    read: &mut dyn FnMut(&Path) -> io::Result<String>,
    list: &mut dyn FnMut(&Path) -> Result<Vec<PathBuf>, String>,
) -> Result<ConfigFile, IniError> {
    parse::Parser::new(read, list).run(text, name)
}

/// The files on disk matching the glob `pattern` (`*`, `?`, `[...]`, in any path component).
pub fn glob_files(pattern: &Path) -> Result<Vec<PathBuf>, String> {
    let text = pattern
        .to_str()
        .ok_or_else(|| "the path is not valid UTF-8".to_string())?;
    let paths = glob::glob(text).map_err(|e| format!("bad glob pattern: {}", e.msg))?;
    paths
        .map(|p| p.map_err(|e| e.to_string()))
        .filter(|p| p.as_ref().map_or(true, |p| p.is_file()))
        .collect()
}
