//! Klipper's host-only G-code sections (no pins, no motion of their own), all optional:
//! - `[delayed_gcode ID]`: `gcode` (required, a template), `initial_duration` (s, ≥ 0,
//!   default 0: not armed at start);
//! - `[save_variables]`: `filename` (required, `~` expanded);
//! - `[idle_timeout]`: `gcode` (default `TURN_OFF_HEATERS` then `M84`), `timeout` (s, > 0,
//!   default 600) — Klipper runs it without the section too, with the defaults;
//! - `[display_status]`: no options (`M73`, `SET_DISPLAY_TEXT` and the status object);
//! - `[force_move]`: `enable_force_move` (default False: with True, `SET_KINEMATIC_POSITION`);
//! - `[virtual_sdcard]`: `path` (required), `on_error_gcode` — the print jobs of
//!   `cadence serve`, which reads them from the configfile object.
//!
//! The scripts become macros with lower-case names (`delayed_gcode ID`, `idle_timeout`) that
//! no G-code command can call; the templates compile with the `[gcode_macro]`s at load.

use std::path::PathBuf;

use planner::gcode::host::{
    delayed_macro_name, HostConfig, DEFAULT_IDLE_GCODE, DEFAULT_IDLE_TIMEOUT, IDLE_TIMEOUT_MACRO,
};
use planner::gcode::macros::MacroDef;

use super::error::ConfigError;
use super::reader::{Bounds, Reader};

/// What the host sections configure.
#[derive(Debug, Clone, PartialEq)]
pub struct HostSections {
    /// Timers, idle timeout, variables file, display status, force move.
    pub host: HostConfig,
    /// The `[delayed_gcode]` and `[idle_timeout]` scripts as macros.
    pub scripts: Vec<MacroDef>,
    /// `[virtual_sdcard] path` (`~` expanded).
    pub virtual_sdcard: Option<PathBuf>,
}

impl Default for HostSections {
    fn default() -> Self {
        HostSections {
            host: HostConfig::default(),
            scripts: vec![script(IDLE_TIMEOUT_MACRO, DEFAULT_IDLE_GCODE, "<default>")],
            virtual_sdcard: None,
        }
    }
}

fn script(name: &str, gcode: &str, at: &str) -> MacroDef {
    MacroDef {
        name: name.to_string(),
        gcode: gcode.to_string(),
        description: None,
        rename_existing: None,
        variables: Vec::new(),
        at: at.to_string(),
    }
}

/// `~/x` → `$HOME/x`, as Python's `os.path.expanduser`.
fn expand_user(path: &str) -> PathBuf {
    let path = path.trim();
    match (path.strip_prefix("~/"), std::env::var_os("HOME")) {
        (Some(rest), Some(home)) => PathBuf::from(home).join(rest),
        _ if path == "~" => std::env::var_os("HOME").map_or_else(|| PathBuf::from(path), PathBuf::from),
        _ => PathBuf::from(path),
    }
}

pub(crate) fn read_host(reader: &Reader<'_>) -> Result<HostSections, ConfigError> {
    let mut out = HostSections::default();
    out.scripts.clear();
    for s in reader.sections_with_arg("delayed_gcode") {
        let id = s.arg().unwrap_or_default().to_string();
        let gcode = s.string("gcode")?;
        let initial = s.float_or("initial_duration", 0.0, Bounds::ANY.min(0.0))?;
        out.scripts
            .push(script(&delayed_macro_name(&id), &gcode, &s.at().to_string()));
        out.host.delayed.push((id, initial));
    }
    match reader.section("idle_timeout") {
        Some(s) => {
            out.host.idle_timeout = s.float_or("timeout", DEFAULT_IDLE_TIMEOUT, Bounds::ANY.above(0.0))?;
            let gcode = s
                .value("gcode")
                .map_or(DEFAULT_IDLE_GCODE.to_string(), |v| v.text.clone());
            out.scripts
                .push(script(IDLE_TIMEOUT_MACRO, &gcode, &s.at().to_string()));
        }
        None => out
            .scripts
            .push(script(IDLE_TIMEOUT_MACRO, DEFAULT_IDLE_GCODE, "<default>")),
    }
    if let Some(s) = reader.section("save_variables") {
        out.host.save_variables = Some(expand_user(&s.string("filename")?));
    }
    out.host.display_status = reader.section("display_status").is_some();
    if let Some(s) = reader.section("force_move") {
        out.host.enable_force_move = s.opt_bool("enable_force_move")?.unwrap_or(false);
    }
    if let Some(s) = reader.section("virtual_sdcard") {
        out.virtual_sdcard = Some(expand_user(&s.string("path")?));
        let _ = s.value("on_error_gcode");
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use std::path::PathBuf;

    use crate::printer::simulated_with as config;

    #[test]
    fn sections_read_with_klipper_defaults() {
        let c = config("").unwrap();
        assert_eq!(c.host.host.idle_timeout, 600.0);
        assert_eq!(c.host.scripts.len(), 1);
        assert!(!c.host.host.display_status && !c.host.host.enable_force_move);
        let c = config(
            "[delayed_gcode blink]\ninitial_duration: 2.5\ngcode:\n  M117 hi\n\
             [idle_timeout]\ntimeout: 30\ngcode: M84\n[save_variables]\nfilename: /tmp/v.cfg\n\
             [display_status]\n[force_move]\nenable_force_move: True\n\
             [virtual_sdcard]\npath: /tmp/gcodes\non_error_gcode: CANCEL_PRINT",
        )
        .unwrap();
        assert_eq!(c.host.host.delayed, [("blink".to_string(), 2.5)]);
        assert_eq!(c.host.host.idle_timeout, 30.0);
        assert_eq!(c.host.host.save_variables, Some(PathBuf::from("/tmp/v.cfg")));
        assert!(c.host.host.display_status && c.host.host.enable_force_move);
        assert_eq!(c.host.virtual_sdcard, Some(PathBuf::from("/tmp/gcodes")));
        let names: Vec<&str> = c.host.scripts.iter().map(|m| m.name.as_str()).collect();
        assert_eq!(names, ["delayed_gcode blink", "idle_timeout"]);
        assert!(
            c.warnings
                .iter()
                .all(|w| !w.contains("virtual_sdcard") && !w.contains("delayed_gcode")),
            "{:?}",
            c.warnings
        );
    }

    #[test]
    fn bad_values_name_section_and_option() {
        for (text, want) in [
            ("[delayed_gcode x]\ninitial_duration: 1", "gcode"),
            (
                "[delayed_gcode x]\ngcode: G4\ninitial_duration: -1",
                "initial_duration",
            ),
            ("[idle_timeout]\ntimeout: 0", "timeout"),
            ("[save_variables]\n", "filename"),
            ("[force_move]\nenable_force_move: maybe", "enable_force_move"),
            ("[delayed_gcode x]\ngcode: {% if %}", "delayed_gcode x"),
        ] {
            let e = config(text).unwrap_err();
            assert!(e.contains(want), "{text}: {e}");
        }
    }
}
