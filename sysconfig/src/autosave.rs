//! SAVE_CONFIG: the options calibration commands (PID_CALIBRATE, BED_MESH_CALIBRATE, …) want
//! kept ([`Changes`]) written into printer.cfg's autosave block, the way Klipper writes it:
//!
//! ```text
//! …the user's config, with any option the block now sets commented out with '#'…
//!
//! #*# <---------------------- SAVE_CONFIG ---------------------->
//! #*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.
//! #*#
//! #*# [extruder]
//! #*# control = pid
//! #*# pid_kp = 22.200
//! #*#
//! ```
//!
//! The block keeps the sections it already had (a change replaces one option, a removal drops
//! a whole section, as `[bed_mesh PROFILE]` removals do). An option the block sets that an
//! *included* file also sets is refused ("SAVE_CONFIG section 'extruder' option 'control'
//! conflicts with included value"); one the main file's body sets is commented out there.
//! Writing: the new text goes to `<name>_autosave.cfg`, the old file is renamed to the backup
//! `<name>-YYYYMMDD_HHMMSS.cfg` (UTC), the new one to the config's name. Reading the block back
//! is [`crate::ini`]'s job.

use std::fmt::Write as _;
use std::io;
use std::path::{Path, PathBuf};

use crate::ini::{self, ConfigFile, IniError};

/// The autosave block's first line.
pub const MARKER: &str = "#*# <---------------------- SAVE_CONFIG ---------------------->";
/// Its second line.
pub const DO_NOT_EDIT: &str = "#*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.";

/// One section's pending change.
#[derive(Debug, Clone, PartialEq)]
pub enum SectionChange {
    /// Options set (lower-case names, values as they will be written).
    Set(Vec<(String, String)>),
    /// The whole section removed from the block.
    Remove,
}

/// The options waiting for SAVE_CONFIG, in the order they were set.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Changes {
    sections: Vec<(String, SectionChange)>,
}

impl Changes {
    /// Sets `option` of `[section]` to `value` (replacing an earlier pending value).
    pub fn set(&mut self, section: &str, option: &str, value: impl std::fmt::Display) {
        let option = option.to_lowercase();
        let value = value.to_string();
        let i = match self.sections.iter().position(|(s, _)| s == section) {
            Some(i) => i,
            None => {
                self.sections
                    .push((section.to_string(), SectionChange::Set(Vec::new())));
                self.sections.len() - 1
            }
        };
        let change = &mut self.sections[i].1;
        if let SectionChange::Remove = change {
            *change = SectionChange::Set(Vec::new());
        }
        if let SectionChange::Set(opts) = change {
            match opts.iter_mut().find(|(k, _)| *k == option) {
                Some(slot) => slot.1 = value,
                None => opts.push((option, value)),
            }
        }
    }

    /// Drops `[section]` from the block (and any pending value of it).
    pub fn remove_section(&mut self, section: &str) {
        self.sections.retain(|(s, _)| s != section);
        self.sections.push((section.to_string(), SectionChange::Remove));
    }

    /// Adds `other`'s changes after these (a later change of a section wins).
    pub fn merge(&mut self, other: Changes) {
        for (section, change) in other.sections {
            match change {
                SectionChange::Remove => self.remove_section(&section),
                SectionChange::Set(opts) => {
                    for (k, v) in opts {
                        self.set(&section, &k, v);
                    }
                }
            }
        }
    }

    /// True when nothing is pending.
    pub fn is_empty(&self) -> bool {
        self.sections.is_empty()
    }

    /// Every pending section change (Klipper's `save_config_pending_items`).
    pub fn items(&self) -> &[(String, SectionChange)] {
        &self.sections
    }
}

/// Why SAVE_CONFIG could not write the config.
#[derive(Debug, thiserror::Error)]
pub enum SaveError {
    /// The config file could not be read.
    #[error("Unable to read existing config on SAVE_CONFIG ({}: {source})", .path.display())]
    Read { path: PathBuf, source: io::Error },
    /// A line after the block's marker does not start with `#*#`.
    #[error("Existing config autosave is corrupted. Can't complete SAVE_CONFIG ({}:{line})", .path.display())]
    Corrupt { path: PathBuf, line: usize },
    /// The config (or its new text) does not parse.
    #[error("Unable to parse existing config on SAVE_CONFIG: {0}")]
    Parse(#[from] IniError),
    /// An included file sets an option the block would set.
    #[error("SAVE_CONFIG section '{section}' option '{option}' conflicts with included value")]
    IncludeConflict { section: String, option: String },
    /// Writing the new file, the backup or the rename failed.
    #[error("Unable to write config file during SAVE_CONFIG ({}: {source})", .path.display())]
    Write { path: PathBuf, source: io::Error },
}

/// What SAVE_CONFIG wrote.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Saved {
    /// The config file rewritten.
    pub path: PathBuf,
    /// The previous version, renamed.
    pub backup: PathBuf,
}

/// Writes `changes` into the autosave block of the config file `path` (backup kept, see the
/// module doc). `Ok(None)`: nothing to save (no change and no block yet).
pub fn save(path: &Path, changes: &Changes) -> Result<Option<Saved>, SaveError> {
    let text = std::fs::read_to_string(path).map_err(|source| SaveError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let Some(new_text) = render(&text, path, changes, &mut |p: &Path| std::fs::read_to_string(p))? else {
        return Ok(None);
    };
    let (backup, temp) = sibling_names(path, &utc_stamp(std::time::SystemTime::now()));
    let write_err = |path: &Path| {
        let path = path.to_path_buf();
        move |source| SaveError::Write { path, source }
    };
    std::fs::write(&temp, new_text).map_err(write_err(&temp))?;
    std::fs::rename(path, &backup).map_err(write_err(&backup))?;
    std::fs::rename(&temp, path).map_err(write_err(path))?;
    Ok(Some(Saved {
        path: path.to_path_buf(),
        backup,
    }))
}

/// The backup and temporary file names of config `path` for the stamp `-YYYYMMDD_HHMMSS`.
pub fn sibling_names(path: &Path, stamp: &str) -> (PathBuf, PathBuf) {
    let name = path.to_string_lossy();
    match name.strip_suffix(".cfg") {
        Some(base) => (
            PathBuf::from(format!("{base}{stamp}.cfg")),
            PathBuf::from(format!("{base}_autosave.cfg")),
        ),
        None => (
            PathBuf::from(format!("{name}{stamp}")),
            PathBuf::from(format!("{name}_autosave")),
        ),
    }
}

/// `-YYYYMMDD_HHMMSS` of `t` in UTC.
pub fn utc_stamp(t: std::time::SystemTime) -> String {
    let secs = t.duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs());
    let (days, rem) = (secs / 86_400, secs % 86_400);
    // Civil date from days since 1970-01-01 (Howard Hinnant's days_from_civil inverse).
    let z = days as i64 + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "-{year:04}{month:02}{day:02}_{:02}{:02}{:02}",
        rem / 3600,
        rem / 60 % 60,
        rem % 60
    )
}

/// The new text of the config `text` (the file `path`; included files read through `read`)
/// with `changes` merged into its autosave block; `None` when there is nothing to write.
pub fn render(
    text: &str,
    path: &Path,
    changes: &Changes,
    read: &mut dyn FnMut(&Path) -> io::Result<String>,
) -> Result<Option<String>, SaveError> {
    let (regular, old_block) = split(text, path)?;
    let mut block: Vec<(String, Vec<(String, String)>)> = Vec::new();
    if let Some(old) = old_block {
        let parsed = ini::parse_with(&old, path, &mut |p: &Path| {
            Err(io::Error::other(format!(
                "{}: no include inside the SAVE_CONFIG block",
                p.display()
            )))
        })?;
        for s in parsed.sections() {
            let opts = s
                .options()
                .map(|(k, v)| (k.to_string(), v.text.clone()))
                .collect();
            block.push((s.name().to_string(), opts));
        }
    }
    for (section, change) in &changes.sections {
        let i = block.iter().position(|(s, _)| s == section);
        match (change, i) {
            (SectionChange::Remove, Some(i)) => {
                block.remove(i);
            }
            (SectionChange::Remove, None) => {}
            (SectionChange::Set(opts), i) => {
                let i = i.unwrap_or_else(|| {
                    block.push((section.clone(), Vec::new()));
                    block.len() - 1
                });
                for (k, v) in opts {
                    match block[i].1.iter_mut().find(|(bk, _)| bk == k) {
                        Some(slot) => slot.1 = v.clone(),
                        None => block[i].1.push((k.clone(), v.clone())),
                    }
                }
            }
        }
    }
    if block.is_empty() && changes.is_empty() {
        return Ok(None);
    }
    let regular = comment_out(&regular, &block);
    check_includes(&regular, path, &block, read)?;
    let mut out = regular.trim_end().to_string();
    out.push_str("\n\n");
    out.push_str(MARKER);
    out.push('\n');
    out.push_str(DO_NOT_EDIT);
    out.push_str("\n#*#\n");
    for (name, opts) in &block {
        let _ = writeln!(out, "#*# [{name}]");
        for (k, v) in opts {
            let mut lines = v.split('\n');
            let first = lines.next().unwrap_or("");
            let _ = writeln!(out, "{}", format!("#*# {k} = {first}").trim_end());
            for line in lines {
                let _ = writeln!(out, "{}", format!("#*# \t{line}").trim_end());
            }
        }
        out.push_str("#*#\n");
    }
    Ok(Some(out))
}

/// The text above the block, and the block's config text (`#*# ` removed, the marker and the
/// DO NOT EDIT line dropped).
fn split(text: &str, path: &Path) -> Result<(String, Option<String>), SaveError> {
    let mut regular = String::new();
    let mut block: Option<String> = None;
    for (i, line) in text.lines().enumerate() {
        if let Some(b) = block.as_mut() {
            if line.trim().is_empty() {
                b.push('\n');
                continue;
            }
            let Some(rest) = line.strip_prefix("#*#") else {
                return Err(SaveError::Corrupt {
                    path: path.to_path_buf(),
                    line: i + 1,
                });
            };
            let rest = rest.strip_prefix(' ').unwrap_or(rest);
            if !rest.starts_with("DO NOT EDIT") {
                b.push_str(rest);
            }
            b.push('\n');
        } else if is_marker(line) {
            block = Some(String::new());
        } else {
            regular.push_str(line);
            regular.push('\n');
        }
    }
    Ok((regular, block))
}

/// The reader's test for the block's first line.
fn is_marker(line: &str) -> bool {
    line.trim().strip_prefix("#*#").is_some_and(|rest| {
        let rest = rest.trim();
        rest.starts_with('<') && rest.contains("SAVE_CONFIG")
    })
}

/// `regular` with every option the block sets commented out with `#` (and its continuation
/// lines), as Klipper's SAVE_CONFIG does.
fn comment_out(regular: &str, block: &[(String, Vec<(String, String)>)]) -> String {
    let mut out = String::with_capacity(regular.len());
    let mut section = String::new();
    // Indentation of the open option's line (deeper lines continue it) and whether it is a
    // duplicate.
    let mut open: Option<(usize, bool)> = None;
    for line in regular.lines() {
        let pruned = strip_comment(line).trim_end();
        let indent = line.chars().take_while(|c| c.is_whitespace()).count();
        let trimmed = pruned.trim_start();
        let mark = match open {
            _ if trimmed.is_empty() => false,
            Some((at, dup)) if indent > at => dup,
            _ if trimmed.starts_with('[') => {
                open = None;
                let inner = trimmed.trim_start_matches('[');
                let inner = inner.split(']').next().unwrap_or("");
                section = inner.split_whitespace().collect::<Vec<_>>().join(" ");
                false
            }
            _ => {
                let key = trimmed
                    .split([':', '='])
                    .next()
                    .unwrap_or("")
                    .trim()
                    .to_lowercase();
                let dup = block
                    .iter()
                    .any(|(s, opts)| *s == section && opts.iter().any(|(k, _)| *k == key));
                open = Some((indent, dup));
                dup
            }
        };
        if mark {
            out.push('#');
        }
        out.push_str(line);
        out.push('\n');
    }
    out
}

/// `line` without its comment: `#` or `;` at the start or after whitespace (the reader's rule).
fn strip_comment(line: &str) -> &str {
    let mut after_space = true;
    for (i, c) in line.char_indices() {
        if (c == '#' || c == ';') && after_space {
            return line.get(..i).unwrap_or("");
        }
        after_space = c.is_whitespace();
    }
    line
}

/// Refuses an option of the block that an included file of `regular` sets.
fn check_includes(
    regular: &str,
    path: &Path,
    block: &[(String, Vec<(String, String)>)],
    read: &mut dyn FnMut(&Path) -> io::Result<String>,
) -> Result<(), SaveError> {
    let parsed: ConfigFile = ini::parse_with(regular, path, read)?;
    for (name, opts) in block {
        let Some(section) = parsed.section(name) else {
            continue;
        };
        if let Some((k, _)) = opts.iter().find(|(k, _)| section.get(k).is_some()) {
            return Err(SaveError::IncludeConflict {
                section: name.clone(),
                option: k.clone(),
            });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    fn fs(files: &[(&str, &str)]) -> impl FnMut(&Path) -> io::Result<String> {
        let map: HashMap<PathBuf, String> = files
            .iter()
            .map(|(p, t)| (PathBuf::from(p), t.to_string()))
            .collect();
        move |p: &Path| {
            map.get(p)
                .cloned()
                .ok_or_else(|| io::Error::new(io::ErrorKind::NotFound, "no such file"))
        }
    }

    fn pid() -> Changes {
        let mut c = Changes::default();
        c.set("extruder", "control", "pid");
        c.set("extruder", "pid_Kp", "22.200");
        c.set("extruder", "pid_ki", "1.080");
        c
    }

    const MAIN: &str = "[extruder]\ncontrol: watermark # old\nmax_power: 1\n\n[fan]\npin: PA1\n";

    #[test]
    fn writes_klippers_block_and_comments_the_body_out() {
        let out = render(MAIN, Path::new("/c/printer.cfg"), &pid(), &mut fs(&[]))
            .unwrap()
            .unwrap();
        assert_eq!(
            out,
            "[extruder]\n#control: watermark # old\nmax_power: 1\n\n[fan]\npin: PA1\n\n\
             #*# <---------------------- SAVE_CONFIG ---------------------->\n\
             #*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.\n\
             #*#\n#*# [extruder]\n#*# control = pid\n#*# pid_kp = 22.200\n#*# pid_ki = 1.080\n#*#\n"
        );
        // Read back: the block's values apply.
        let cfg = ini::parse_str(&out, Path::new("/c/printer.cfg")).unwrap();
        let ext = cfg.section("extruder").unwrap();
        assert_eq!(ext.get("control").unwrap().text, "pid");
        assert_eq!(ext.get("pid_kp").unwrap().text, "22.200");
        assert_eq!(ext.get("max_power").unwrap().text, "1");
    }

    #[test]
    fn a_second_save_merges_into_the_block() {
        let first = render(MAIN, Path::new("/c/printer.cfg"), &pid(), &mut fs(&[]))
            .unwrap()
            .unwrap();
        let mut more = Changes::default();
        more.set("extruder", "pid_kp", "30.000");
        more.set("bed_mesh default", "points", "\n0.1, 0.2\n0.3, 0.4");
        let second = render(&first, Path::new("/c/printer.cfg"), &more, &mut fs(&[]))
            .unwrap()
            .unwrap();
        assert!(
            second.contains("#*# pid_kp = 30.000\n#*# pid_ki = 1.080\n"),
            "{second}"
        );
        assert!(
            second.contains("#*# [bed_mesh default]\n#*# points =\n#*# \t0.1, 0.2\n#*# \t0.3, 0.4\n#*#\n"),
            "{second}"
        );
        assert_eq!(second.matches(MARKER).count(), 1);
        let cfg = ini::parse_str(&second, Path::new("/c/printer.cfg")).unwrap();
        let mesh = cfg.section("bed_mesh default").unwrap();
        assert_eq!(mesh.get("points").unwrap().text, "\n0.1, 0.2\n0.3, 0.4");
        // A removal drops the section; nothing left and nothing pending: nothing to write.
        let mut rm = Changes::default();
        rm.remove_section("bed_mesh default");
        let third = render(&second, Path::new("/c/printer.cfg"), &rm, &mut fs(&[]))
            .unwrap()
            .unwrap();
        assert!(!third.contains("bed_mesh"), "{third}");
        assert_eq!(
            render(
                MAIN,
                Path::new("/c/printer.cfg"),
                &Changes::default(),
                &mut fs(&[])
            )
            .unwrap(),
            None
        );
    }

    #[test]
    fn included_values_conflict_and_corrupt_blocks_are_refused() {
        let main = "[include extra.cfg]\n[fan]\npin: PA1\n";
        let e = render(
            main,
            Path::new("/c/printer.cfg"),
            &pid(),
            &mut fs(&[("/c/extra.cfg", "[extruder]\ncontrol: watermark\n")]),
        )
        .unwrap_err();
        assert_eq!(
            e.to_string(),
            "SAVE_CONFIG section 'extruder' option 'control' conflicts with included value"
        );
        let bad = format!("{MAIN}{MARKER}\n#*# [x]\nplain: 1\n");
        let e = render(&bad, Path::new("/c/printer.cfg"), &pid(), &mut fs(&[])).unwrap_err();
        assert!(matches!(e, SaveError::Corrupt { line: 9, .. }), "{e}");
    }

    #[test]
    fn save_keeps_a_backup() {
        let dir = std::env::temp_dir().join(format!("cadence-autosave-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("printer.cfg");
        std::fs::write(&path, MAIN).unwrap();
        let saved = save(&path, &pid()).unwrap().unwrap();
        assert_eq!(std::fs::read_to_string(&saved.backup).unwrap(), MAIN);
        let name = saved.backup.file_name().unwrap().to_string_lossy().to_string();
        assert!(
            name.starts_with("printer-") && name.ends_with(".cfg") && name.len() == 27,
            "{name}"
        );
        assert!(std::fs::read_to_string(&path).unwrap().contains(MARKER));
        assert!(!dir.join("printer_autosave.cfg").exists());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn stamps_and_names() {
        let t = std::time::UNIX_EPOCH + std::time::Duration::from_secs(1_796_300_000);
        // 2026-12-03 12:13:20 UTC (date -u -d @1796300000).
        assert_eq!(utc_stamp(t), "-20261203_121320");
        assert_eq!(utc_stamp(std::time::UNIX_EPOCH), "-19700101_000000");
        let (b, t) = sibling_names(Path::new("/c/printer.cfg"), "-1");
        assert_eq!(
            (b.as_path(), t.as_path()),
            (
                Path::new("/c/printer-1.cfg"),
                Path::new("/c/printer_autosave.cfg")
            )
        );
    }

    proptest::proptest! {
        /// Whatever the config text, rendering never panics; what it writes reads back with
        /// the changed values.
        #[test]
        fn render_never_panics(text in "[\\[\\]a-z_:=#*;<> \n\t0-9-]{0,200}") {
            let path = Path::new("/c/printer.cfg");
            if let Ok(Some(out)) = render(&text, path, &pid(), &mut fs(&[])) {
                if let Ok(cfg) = ini::parse_str(&out, path) {
                    let v = cfg.section("extruder").and_then(|s| s.get("pid_kp")).map(|v| v.text.clone());
                    proptest::prop_assert_eq!(v.as_deref(), Some("22.200"));
                }
            }
        }
    }
}
