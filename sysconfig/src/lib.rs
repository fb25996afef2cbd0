//! Klipper-format printer.cfg → validated, typed configuration for Cadence.
//!
//! Layers:
//! - [`ini`]: the generic config-file reader (sections, options, continuation lines, comments,
//!   includes, SAVE_CONFIG block); every value keeps its file and line.
//! - [`printer`]: the typed config ([`PrinterConfig`]) with Klipper's option names, defaults and
//!   bounds; every option must be consumed, unknown sections are errors unless listed as
//!   accepted-and-ignored (then warnings).
//!
//! - [`autosave`]: SAVE_CONFIG's rewrite of printer.cfg (the `#*#` autosave block, a backup)
//!   from the typed [`autosave::Changes`] calibration commands leave pending.
//! - [`systemd`]: the systemd units: the printer service and the IO stage alone.
//!
//! Guarantees: no input makes these parsers panic; every error names the file, the line when
//! there is one, the section and the option.
#![deny(unsafe_code)]

pub mod autosave;
pub mod ini;
pub mod planning;
pub mod printer;
pub mod systemd;

pub use printer::{builtin_simulated, load, parse_str, ConfigError, PrinterConfig, SIMULATED_PRINTER_CFG};
