//! Print jobs as Klipper's `virtual_sdcard` runs them: a G-code file from the `[virtual_sdcard]
//! path` directory read line by line while printing (`SDCARD_PRINT_FILE`, `M23`/`M24`), paused
//! and resumed at the same byte (`PAUSE`/`M25`, `RESUME`/`M24`), cancelled (`CANCEL_PRINT`),
//! with the figures of `print_stats`, `virtual_sdcard` and `display_status` ([`PrintInfo`]).

use std::fs::File;
use std::io::{BufRead, BufReader, Seek, SeekFrom};
use std::path::{Component, Path, PathBuf};
use std::time::{Duration, Instant};

/// `print_stats.state`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PrintState {
    #[default]
    Standby,
    Printing,
    Paused,
    Complete,
    Cancelled,
    Error,
}

impl PrintState {
    pub fn name(self) -> &'static str {
        match self {
            PrintState::Standby => "standby",
            PrintState::Printing => "printing",
            PrintState::Paused => "paused",
            PrintState::Complete => "complete",
            PrintState::Cancelled => "cancelled",
            PrintState::Error => "error",
        }
    }
}

/// What the status objects show of the print (published by the worker).
#[derive(Debug, Clone, Default)]
pub struct PrintInfo {
    pub state: PrintState,
    /// The file's name relative to the sdcard directory.
    pub filename: String,
    /// The open file (`None` when none is loaded).
    pub file_path: Option<PathBuf>,
    pub file_size: u64,
    pub file_position: u64,
    /// `print_stats.message`: why the print failed.
    pub message: String,
    /// `display_status.message` (M117).
    pub display_message: Option<String>,
    /// M73 P (0..1).
    pub m73_progress: Option<f64>,
    started: Option<Instant>,
    ended: Option<Instant>,
    paused_since: Option<Instant>,
    paused_for: Duration,
}

impl PrintInfo {
    /// `virtual_sdcard.progress`.
    pub fn progress(&self) -> f64 {
        if self.file_size == 0 {
            0.0
        } else {
            self.file_position as f64 / self.file_size as f64
        }
    }

    /// `print_stats.total_duration` (s): since the print started.
    pub fn total_duration(&self) -> f64 {
        match self.started {
            Some(s) => self
                .ended
                .unwrap_or_else(Instant::now)
                .duration_since(s)
                .as_secs_f64(),
            None => 0.0,
        }
    }

    /// `print_stats.print_duration` (s): without the time paused.
    pub fn print_duration(&self) -> f64 {
        let paused = self.paused_for
            + self
                .paused_since
                .map(|p| self.ended.unwrap_or_else(Instant::now).duration_since(p))
                .unwrap_or_default();
        (self.total_duration() - paused.as_secs_f64()).max(0.0)
    }

    pub fn is_active(&self) -> bool {
        self.state == PrintState::Printing
    }
}

/// The virtual sdcard: its directory, the loaded file and the print's figures.
#[derive(Debug)]
pub struct SdCard {
    dir: Option<PathBuf>,
    file: Option<BufReader<File>>,
    pub info: PrintInfo,
    line: String,
}

/// Why an sdcard command was refused (the messages are Klipper's where it has one).
#[derive(Debug, thiserror::Error)]
pub enum SdError {
    /// A file is printing.
    #[error("SD busy")]
    Busy,
    /// The service has no sdcard directory.
    #[error("no [virtual_sdcard] path in the config (or --virtual-sdcard DIR)")]
    NoDirectory,
    /// A name with `..` or an absolute part.
    #[error("Unable to open file \"{name}\": not a file name inside the sdcard")]
    NotInside { name: String },
    /// The file does not open.
    #[error("Unable to open file \"{name}\": {source}")]
    Open {
        name: String,
        #[source]
        source: std::io::Error,
    },
    /// `M24` without a loaded file.
    #[error("No file selected to print (M23 or SDCARD_PRINT_FILE first)")]
    NoFileToPrint,
    /// `M26` without a loaded file.
    #[error("No file selected (M23 first)")]
    NoFile,
    /// `M25` while paused.
    #[error("Print already paused")]
    AlreadyPaused,
    /// `M25` with nothing printing.
    #[error("No print in progress to pause")]
    NotPrinting,
    /// `M26`'s seek failed.
    #[error("M26: {0}")]
    Seek(#[source] std::io::Error),
    /// Reading the printing file failed.
    #[error("reading {name}: {source}")]
    Read {
        name: String,
        #[source]
        source: std::io::Error,
    },
}

/// The G-code terminal's and the API's view (the message as shown).
impl From<SdError> for String {
    fn from(e: SdError) -> String {
        e.to_string()
    }
}

impl SdCard {
    pub fn new(dir: Option<PathBuf>) -> SdCard {
        SdCard {
            dir,
            file: None,
            info: PrintInfo::default(),
            line: String::new(),
        }
    }

    /// Loads `name` (relative to the sdcard directory; quotes and a leading `/` allowed, `..`
    /// refused) at its start. Returns Klipper's `File opened` line.
    pub fn load(&mut self, name: &str) -> Result<String, SdError> {
        if self.info.state == PrintState::Printing {
            return Err(SdError::Busy);
        }
        let dir = self.dir.as_ref().ok_or(SdError::NoDirectory)?;
        let name = name.trim().trim_matches('"').trim_start_matches('/');
        let rel = Path::new(name);
        if name.is_empty() || rel.components().any(|c| !matches!(c, Component::Normal(_))) {
            return Err(SdError::NotInside {
                name: name.to_string(),
            });
        }
        let path = dir.join(rel);
        let file = File::open(&path).map_err(|source| SdError::Open {
            name: name.to_string(),
            source,
        })?;
        let size = file.metadata().map(|m| m.len()).unwrap_or(0);
        self.file = Some(BufReader::with_capacity(1 << 16, file));
        self.info = PrintInfo {
            filename: name.to_string(),
            file_path: Some(path),
            file_size: size,
            display_message: self.info.display_message.take(),
            ..PrintInfo::default()
        };
        Ok(format!("File opened:{name} Size:{size}"))
    }

    /// Starts or resumes the loaded file (`M24`, `RESUME`).
    pub fn start(&mut self) -> Result<(), SdError> {
        if self.file.is_none() {
            return Err(SdError::NoFileToPrint);
        }
        let now = Instant::now();
        match self.info.state {
            PrintState::Printing => return Ok(()),
            PrintState::Paused => {
                if let Some(p) = self.info.paused_since.take() {
                    self.info.paused_for += now.duration_since(p);
                }
            }
            _ => {
                self.info.started = Some(now);
                self.info.ended = None;
                self.info.paused_for = Duration::ZERO;
                self.info.message.clear();
            }
        }
        self.info.state = PrintState::Printing;
        Ok(())
    }

    /// Pauses at the current line (`M25`, `PAUSE`).
    pub fn pause(&mut self) -> Result<(), SdError> {
        match self.info.state {
            PrintState::Printing => {
                self.info.state = PrintState::Paused;
                self.info.paused_since = Some(Instant::now());
                Ok(())
            }
            PrintState::Paused => Err(SdError::AlreadyPaused),
            _ => Err(SdError::NotPrinting),
        }
    }

    /// `M26 S`: where the next line is read from.
    pub fn set_position(&mut self, pos: u64) -> Result<(), SdError> {
        if self.info.state == PrintState::Printing {
            return Err(SdError::Busy);
        }
        let f = self.file.as_mut().ok_or(SdError::NoFile)?;
        f.seek(SeekFrom::Start(pos)).map_err(SdError::Seek)?;
        self.info.file_position = pos;
        Ok(())
    }

    /// `M27`'s answer.
    pub fn report(&self) -> String {
        match self.file {
            Some(_) => format!(
                "SD printing byte {}/{}",
                self.info.file_position, self.info.file_size
            ),
            None => "Not SD printing.".into(),
        }
    }

    /// Ends the print with `state` (`CANCEL_PRINT`: cancelled; a failed line: error with
    /// `message`); the file is closed.
    pub fn end(&mut self, state: PrintState, message: &str) {
        let now = Instant::now();
        if let Some(p) = self.info.paused_since.take() {
            self.info.paused_for += now.duration_since(p);
        }
        if self.info.started.is_some() {
            self.info.ended = Some(now);
        }
        self.info.state = state;
        self.info.message = message.to_string();
        self.file = None;
        if state != PrintState::Complete {
            self.info.file_path = None;
        }
    }

    /// The next line of a printing file (`None` at its end or when not printing); the byte
    /// position moves past it.
    pub fn next_line(&mut self) -> Option<Result<&str, SdError>> {
        if self.info.state != PrintState::Printing {
            return None;
        }
        let f = self.file.as_mut()?;
        self.line.clear();
        match f.read_line(&mut self.line) {
            Ok(0) => None,
            Ok(n) => {
                self.info.file_position += n as u64;
                Some(Ok(self.line.as_str()))
            }
            Err(source) => Some(Err(SdError::Read {
                name: self.info.filename.clone(),
                source,
            })),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_prints_pauses_resumes_at_the_same_byte_and_completes() {
        let dir = std::env::temp_dir().join(format!("cadence-sdcard-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("a.gcode"), "G1 X1\nG1 X2\nG1 X3\n").unwrap();
        let mut sd = SdCard::new(Some(dir.clone()));
        assert!(sd.load("../etc/passwd").is_err());
        assert_eq!(sd.load("\"a.gcode\"").unwrap(), "File opened:a.gcode Size:18");
        assert!(sd.pause().is_err());
        sd.start().unwrap();
        assert_eq!(sd.next_line().unwrap().unwrap(), "G1 X1\n");
        sd.pause().unwrap();
        assert!(sd.next_line().is_none(), "nothing is read while paused");
        assert_eq!(sd.report(), "SD printing byte 6/18");
        sd.start().unwrap();
        assert_eq!(sd.next_line().unwrap().unwrap(), "G1 X2\n");
        assert_eq!(sd.next_line().unwrap().unwrap(), "G1 X3\n");
        assert!(sd.next_line().is_none());
        assert_eq!(sd.info.progress(), 1.0);
        sd.end(PrintState::Complete, "");
        assert_eq!(sd.info.state.name(), "complete");
        assert!(sd.info.print_duration() <= sd.info.total_duration());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
