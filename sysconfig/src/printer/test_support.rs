//! Scaffolding shared by the section modules' unit tests: one section's body parsed on its own
//! against a pin registry (every option must be read, errors as their messages), and the body
//! a `never_panics` proptest builds from its generated option values.

use std::path::Path;

use super::error::ConfigError;
use super::pins::PinRegistry;
use super::reader::{Reader, SectionReader};
use crate::ini;

/// The MCUs the tests' pin registry knows: the main one and a probe board's (`probe_mcu:PA4`).
pub(crate) const MCUS: [&str; 2] = ["mcu", "probe_mcu"];

/// Reads `[name]` followed by `body` (from line 2 of `printer.cfg`) with `read` against a pin
/// registry of [`MCUS`], then refuses any option it left unread; an error as its message.
pub(crate) fn read_section<T>(
    name: &str,
    body: &str,
    read: impl FnOnce(&SectionReader<'_>, &mut PinRegistry) -> Result<T, ConfigError>,
) -> Result<T, String> {
    let text = format!("[{name}]\n{body}");
    let file = ini::parse_str(&text, Path::new("printer.cfg")).map_err(|e| e.to_string())?;
    let reader = Reader::new(&file);
    let s = reader.section(name).ok_or("no section")?;
    let mut pins = PinRegistry::new(MCUS.iter().map(|m| m.to_string()).collect());
    let out = read(&s, &mut pins).map_err(|e| e.to_string())?;
    reader.finish(|_| false).map_err(|e| e.to_string())?;
    Ok(out)
}

/// The `never_panics` proptests' body: reads `[name]` with `base` and then one
/// `option: value` line per entry of `options` (generated values, any of them nonsense). Its
/// postcondition is that it returns at all: whatever the result, the section's reader did not
/// panic.
pub(crate) fn read_never_panics<T>(
    name: &str,
    base: &str,
    options: &[(&str, &str)],
    read: impl FnOnce(&SectionReader<'_>, &mut PinRegistry) -> Result<T, ConfigError>,
) {
    let lines = options
        .iter()
        .map(|(option, value)| format!("{option}: {value}\n"));
    let body: String = std::iter::once(base.to_string()).chain(lines).collect();
    // Ok or Err alike: only a panic fails.
    let _ = read_section(name, &body, read);
}
