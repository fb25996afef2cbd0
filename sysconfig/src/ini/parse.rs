//! The line-by-line state machine behind [`super::parse_with`]: classifies each line (blank,
//! comment, continuation, header, include, option), merges sections, follows includes with a
//! stack of open files for cycle detection, and switches to the SAVE_CONFIG block in the main
//! file. No input can make it panic: every malformed line is an [`IniError`].

use std::io;
use std::path::{Component, Path, PathBuf};

use super::{ConfigFile, IniError, Location, SyntaxProblem, Value};

/// Deepest include nesting accepted (the main file counts as one); guards against loops that
/// path comparison cannot see.
pub const MAX_INCLUDE_DEPTH: usize = 32;

/// The option whose value later continuation lines extend.
#[derive(Debug, Clone, Copy)]
struct OpenValue {
    section: usize,
    option: usize,
    /// Indentation (in characters) of the option's line; continuations are deeper.
    indent: usize,
    /// Blank lines seen since the last line of the value; kept only if a continuation follows.
    blanks: usize,
}

/// What a line inside the SAVE_CONFIG block stands for.
enum AutosaveLine<'a> {
    Text(&'a str),
    Skip,
    Corrupt,
}

pub(super) struct Parser<'r> {
    read: &'r mut dyn FnMut(&Path) -> io::Result<String>,
    list: &'r mut dyn FnMut(&Path) -> Result<Vec<PathBuf>, String>,
    out: ConfigFile,
    /// Identities of the files being read, outermost first.
    open: Vec<PathBuf>,
    /// Line of the main file's SAVE_CONFIG marker, once read.
    autosave_line: Option<usize>,
}

impl<'r> Parser<'r> {
    pub(super) fn new(
        read: &'r mut dyn FnMut(&Path) -> io::Result<String>,
        list: &'r mut dyn FnMut(&Path) -> Result<Vec<PathBuf>, String>,
    ) -> Self {
        Parser {
            read,
            list,
            out: ConfigFile::default(),
            open: Vec::new(),
            autosave_line: None,
        }
    }

    /// Parses the main file `text` named `name` and everything it includes.
    pub(super) fn run(mut self, text: &str, name: &Path) -> Result<ConfigFile, IniError> {
        self.out.files.push(name.to_path_buf());
        self.open.push(identity(name));
        self.parse_file(text, name, true)?;
        Ok(self.out)
    }

    fn parse_file(&mut self, text: &str, file: &Path, main: bool) -> Result<(), IniError> {
        let text = text.strip_prefix('\u{feff}').unwrap_or(text);
        let mut section: Option<usize> = None;
        let mut value: Option<OpenValue> = None;
        let mut autosave = false;
        // Indentation of an autosave option being skipped (its continuation lines go too).
        let mut skipping: Option<usize> = None;
        for (index, raw) in text.lines().enumerate() {
            let at = || Location {
                file: file.to_path_buf(),
                line: index + 1,
            };
            let syntax = |problem| IniError::Syntax { at: at(), problem };
            let line = if autosave {
                match autosave_line(raw) {
                    AutosaveLine::Text(line) => line,
                    AutosaveLine::Skip => continue,
                    AutosaveLine::Corrupt => return Err(syntax(SyntaxProblem::AutosaveCorrupt)),
                }
            } else if main && is_autosave_marker(raw) {
                autosave = true;
                self.autosave_line = Some(index + 1);
                section = None;
                value = None;
                continue;
            } else {
                raw
            };

            let content = strip_comment(line);
            let trimmed = content.trim();
            if trimmed.is_empty() {
                // A comment-only line neither counts as blank nor ends the value.
                if line.trim().is_empty() {
                    if let Some(v) = value.as_mut() {
                        v.blanks += 1;
                    }
                }
                continue;
            }

            let indent = line.chars().take_while(|c| c.is_whitespace()).count();
            if let Some(skip) = skipping {
                if indent > skip {
                    continue;
                }
                skipping = None;
            }
            if let Some(v) = value.as_mut() {
                if indent > v.indent {
                    self.continue_value(v, trimmed);
                    continue;
                }
            }
            value = None;

            if trimmed.starts_with('[') {
                let name = parse_header(trimmed).map_err(syntax)?;
                section = None;
                if let Some(spec) = include_spec(&name) {
                    if spec.is_empty() {
                        return Err(syntax(SyntaxProblem::EmptyInclude));
                    }
                    self.include(spec, file, at())?;
                } else {
                    let name = name.split_whitespace().collect::<Vec<_>>().join(" ");
                    section = Some(self.out.section_index_or_insert(name, at()));
                }
                continue;
            }

            let Some(split) = trimmed.find([':', '=']) else {
                return Err(syntax(SyntaxProblem::NotAnOption(trimmed.to_string())));
            };
            let key = trimmed.get(..split).unwrap_or("").trim().to_lowercase();
            let text = trimmed.get(split + 1..).unwrap_or("").trim();
            if key.is_empty() {
                return Err(syntax(SyntaxProblem::EmptyOptionName));
            }
            let Some(sec) = section else {
                return Err(syntax(SyntaxProblem::OptionOutsideSection(key)));
            };
            if autosave && self.defined_outside_autosave(sec, &key, file) {
                // Klipper's rule: the config above the block (and its includes) wins; the
                // block's copy is ignored (SAVE_CONFIG comments the other out when it writes).
                value = None;
                skipping = Some(indent);
                continue;
            }
            let option = self.set_option(
                sec,
                key,
                Value {
                    text: text.to_string(),
                    at: at(),
                },
            );
            value = Some(OpenValue {
                section: sec,
                option,
                indent,
                blanks: 0,
            });
        }
        Ok(())
    }

    /// True when option `key` of section `sec` was set by the config above the SAVE_CONFIG
    /// block of `main` (the main file's body or an included file).
    fn defined_outside_autosave(&self, sec: usize, key: &str, main: &Path) -> bool {
        let Some(section) = self.out.sections.get(sec) else {
            return false;
        };
        let Some(start) = self.autosave_line else {
            return false;
        };
        section
            .options
            .iter()
            .any(|(k, v)| k == key && (v.at.file != main || v.at.line < start))
    }

    /// Appends a continuation line (after any blank lines it keeps) to the open value.
    fn continue_value(&mut self, v: &mut OpenValue, line: &str) {
        let slot = self
            .out
            .sections
            .get_mut(v.section)
            .and_then(|s| s.options.get_mut(v.option));
        if let Some((_, value)) = slot {
            for _ in 0..=v.blanks {
                value.text.push('\n');
            }
            value.text.push_str(line);
        }
        v.blanks = 0;
    }

    /// Sets `key` in section `sec`, replacing an earlier value in place; returns its index.
    fn set_option(&mut self, sec: usize, key: String, value: Value) -> usize {
        let Some(section) = self.out.sections.get_mut(sec) else {
            return 0;
        };
        let options = &mut section.options;
        match options.iter().position(|(k, _)| *k == key) {
            Some(i) => {
                if let Some(slot) = options.get_mut(i) {
                    slot.1 = value;
                }
                i
            }
            None => {
                options.push((key, value));
                options.len() - 1
            }
        }
    }

    /// Reads `spec` relative to `from`'s directory, in place of the `[include]` line at `at`.
    /// A glob (`*`, `?`, `[`) includes every file it matches in name order, and none is fine
    /// (as in Klipper); a plain name must exist.
    fn include(&mut self, spec: &str, from: &Path, at: Location) -> Result<(), IniError> {
        let dir = from.parent().unwrap_or(Path::new(""));
        if !spec.contains(['*', '?', '[']) {
            return self.include_path(dir.join(spec), at);
        }
        let mut paths = (self.list)(&dir.join(spec)).map_err(|problem| IniError::IncludeGlob {
            at: at.clone(),
            spec: spec.to_string(),
            problem,
        })?;
        paths.sort();
        for path in paths {
            self.include_path(path, at.clone())?;
        }
        Ok(())
    }

    fn include_path(&mut self, path: PathBuf, at: Location) -> Result<(), IniError> {
        let id = identity(&path);
        if self.open.contains(&id) {
            return Err(IniError::IncludeCycle { at, path });
        }
        if self.open.len() >= MAX_INCLUDE_DEPTH {
            return Err(IniError::IncludeTooDeep { at });
        }
        let text = match (self.read)(&path) {
            Ok(text) => text,
            Err(source) => return Err(IniError::Include { at, path, source }),
        };
        self.open.push(id);
        self.out.files.push(path.clone());
        let result = self.parse_file(&text, &path, false);
        self.open.pop();
        result
    }
}

/// The inside of a `[...]` header line (already comment-stripped and trimmed).
fn parse_header(line: &str) -> Result<String, SyntaxProblem> {
    let close = line.rfind(']').ok_or(SyntaxProblem::UnclosedHeader)?;
    let after = line.get(close + 1..).unwrap_or("").trim();
    if !after.is_empty() {
        return Err(SyntaxProblem::TextAfterHeader(after.to_string()));
    }
    let inner = line.get(1..close).unwrap_or("").trim();
    if inner.is_empty() {
        return Err(SyntaxProblem::EmptySectionName);
    }
    Ok(inner.to_string())
}

/// `Some(path)` when the header names an include (`include` alone gives an empty path).
fn include_spec(header: &str) -> Option<&str> {
    let rest = header.strip_prefix("include")?;
    if rest.is_empty() || rest.starts_with(char::is_whitespace) {
        Some(rest.trim())
    } else {
        None
    }
}

/// Cuts a `#` or `;` comment that starts the line or follows whitespace.
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

/// Klipper's `#*# <---------------------- SAVE_CONFIG ---------------------->` line.
fn is_autosave_marker(line: &str) -> bool {
    line.trim().strip_prefix("#*#").is_some_and(|rest| {
        let rest = rest.trim();
        rest.starts_with('<') && rest.contains("SAVE_CONFIG")
    })
}

/// One line of the SAVE_CONFIG block with its `#*#` prefix removed.
fn autosave_line(raw: &str) -> AutosaveLine<'_> {
    if raw.trim().is_empty() {
        return AutosaveLine::Text("");
    }
    let Some(rest) = raw.strip_prefix("#*#") else {
        return AutosaveLine::Corrupt;
    };
    let rest = rest.strip_prefix(' ').unwrap_or(rest);
    if rest.trim_start().starts_with("DO NOT EDIT") {
        AutosaveLine::Skip
    } else {
        AutosaveLine::Text(rest)
    }
}

/// The identity of a file for cycle detection: its canonical path when it exists on disk,
/// else the lexically normalized path (`a/../b` → `b`), which in-memory readers use.
fn identity(path: &Path) -> PathBuf {
    std::fs::canonicalize(path).unwrap_or_else(|_| normalize(path))
}

fn normalize(path: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    for c in path.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir => match out.components().next_back() {
                Some(Component::Normal(_)) => {
                    out.pop();
                }
                Some(Component::RootDir | Component::Prefix(_)) => {}
                _ => out.push(".."),
            },
            other => out.push(other),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::super::{parse_with, ConfigFile};
    use super::*;
    use proptest::prelude::*;
    use std::collections::HashMap;

    fn files(list: &[(&str, &str)]) -> HashMap<PathBuf, String> {
        list.iter()
            .map(|(p, t)| (PathBuf::from(p), t.to_string()))
            .collect()
    }

    /// Parses `/cfg/printer.cfg` = `main`, includes from `fs`.
    fn parse_in(main: &str, fs: &HashMap<PathBuf, String>) -> Result<ConfigFile, IniError> {
        let mut read = |p: &Path| {
            fs.get(&normalize(p))
                .cloned()
                .ok_or_else(|| io::Error::new(io::ErrorKind::NotFound, "no such file"))
        };
        parse_with(main, Path::new("/cfg/printer.cfg"), &mut read)
    }

    fn parse(main: &str) -> ConfigFile {
        match parse_in(main, &HashMap::new()) {
            Ok(cfg) => cfg,
            Err(e) => panic!("parse failed: {e}"),
        }
    }

    fn text<'a>(cfg: &'a ConfigFile, section: &str, key: &str) -> &'a str {
        cfg.section(section)
            .and_then(|s| s.get(key))
            .map_or("<missing>", |v| v.text.as_str())
    }

    fn err(main: &str) -> String {
        match parse_in(main, &HashMap::new()) {
            Ok(cfg) => panic!("expected an error, got {cfg:?}"),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn options_with_both_delimiters_lowercased_and_trimmed() {
        let cfg = parse("[printer]\nKinematics :  cartesian  \nmax_velocity=300\nmax_accel = 3000\n");
        assert_eq!(text(&cfg, "printer", "kinematics"), "cartesian");
        assert_eq!(text(&cfg, "printer", "max_velocity"), "300");
        assert_eq!(text(&cfg, "printer", "max_accel"), "3000");
        let v = cfg
            .section("printer")
            .and_then(|s| s.get("max_velocity"))
            .cloned();
        assert_eq!(
            v.map(|v| v.at.to_string()),
            Some("/cfg/printer.cfg:3".to_string())
        );
    }

    #[test]
    fn first_delimiter_splits() {
        let cfg = parse("[stepper_z]\nendstop_pin: probe:z_virtual_endstop\na = b: c\nd: e = f\n");
        assert_eq!(text(&cfg, "stepper_z", "endstop_pin"), "probe:z_virtual_endstop");
        assert_eq!(text(&cfg, "stepper_z", "a"), "b: c");
        assert_eq!(text(&cfg, "stepper_z", "d"), "e = f");
    }

    #[test]
    fn continuation_lines_join_with_newline() {
        let cfg = parse(
            "[gcode_macro START]\ngcode:\n  G28\n\n  # homing done\n    G1 X10\n\n\nvariable_x: 1\n  2\n\n[next]\n",
        );
        assert_eq!(text(&cfg, "gcode_macro START", "gcode"), "\nG28\n\nG1 X10");
        assert_eq!(text(&cfg, "gcode_macro START", "variable_x"), "1\n2");
        assert!(cfg.section("next").is_some_and(|s| s.is_empty()));
    }

    #[test]
    fn continuation_must_be_deeper_than_its_option() {
        let cfg = parse("[a]\n  x: 1\n  y: 2\n    more\n");
        assert_eq!(text(&cfg, "a", "x"), "1");
        assert_eq!(text(&cfg, "a", "y"), "2\nmore");
    }

    #[test]
    fn comments_whole_line_and_trailing_after_whitespace() {
        let cfg = parse(
            "# top\n; also\n[mcu] # the main mcu\nserial: /dev/ttyACM0 ; port\npin: PA0#1\n  ; indented\nx: a;b\n",
        );
        assert_eq!(text(&cfg, "mcu", "serial"), "/dev/ttyACM0");
        assert_eq!(text(&cfg, "mcu", "pin"), "PA0#1");
        assert_eq!(text(&cfg, "mcu", "x"), "a;b");
        assert_eq!(cfg.sections().len(), 1);
    }

    #[test]
    fn crlf_and_bom_are_accepted() {
        let cfg = parse("\u{feff}[a]\r\nx: 1\r\ny: 2\r\n  3\r\n");
        assert_eq!(text(&cfg, "a", "x"), "1");
        assert_eq!(text(&cfg, "a", "y"), "2\n3");
    }

    #[test]
    fn duplicate_sections_merge_and_later_options_win() {
        let cfg = parse("[a]\nx: 1\ny: 2\n[b]\nz: 3\n[a]\nx: 10\nw: 4\n");
        let names: Vec<_> = cfg.sections().iter().map(|s| s.name()).collect();
        assert_eq!(names, ["a", "b"]);
        let a = cfg.section("a").cloned().unwrap_or_else(|| panic!("no [a]"));
        let keys: Vec<_> = a
            .options()
            .map(|(k, v)| (k.to_string(), v.text.clone(), v.at.line))
            .collect();
        assert_eq!(
            keys,
            [
                ("x".into(), "10".into(), 7),
                ("y".into(), "2".into(), 3),
                ("w".into(), "4".into(), 8)
            ]
        );
        assert_eq!(a.at().line, 1);
    }

    #[test]
    fn section_names_normalized_kind_and_arg() {
        let cfg = parse("[ mcu   extra ]\nserial: x\n[stepper_x]\n");
        let s = cfg
            .section("mcu extra")
            .cloned()
            .unwrap_or_else(|| panic!("no [mcu extra]"));
        assert_eq!((s.kind(), s.arg()), ("mcu", Some("extra")));
        let x = cfg
            .section("stepper_x")
            .cloned()
            .unwrap_or_else(|| panic!("no [stepper_x]"));
        assert_eq!((x.kind(), x.arg()), ("stepper_x", None));
    }

    #[test]
    fn includes_resolve_relative_to_the_including_file() {
        let fs = files(&[
            (
                "/cfg/sub/steppers.cfg",
                "[stepper_x]\nmicrosteps: 16\n[include ../common.cfg]\n",
            ),
            ("/cfg/common.cfg", "[printer]\nmax_velocity: 200\n"),
        ]);
        let cfg = parse_in(
            "[printer]\nmax_velocity: 100\n[include sub/steppers.cfg]\n[printer]\nmax_accel: 1\n",
            &fs,
        )
        .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(text(&cfg, "stepper_x", "microsteps"), "16");
        // The include comes after the main file's value, so it overrides it.
        assert_eq!(text(&cfg, "printer", "max_velocity"), "200");
        assert_eq!(text(&cfg, "printer", "max_accel"), "1");
        let at = cfg
            .section("printer")
            .and_then(|s| s.get("max_velocity"))
            .map(|v| v.at.to_string());
        assert_eq!(at.as_deref(), Some("/cfg/sub/../common.cfg:2"));
        let read: Vec<_> = cfg.files().iter().map(|p| p.display().to_string()).collect();
        assert_eq!(
            read,
            [
                "/cfg/printer.cfg",
                "/cfg/sub/steppers.cfg",
                "/cfg/sub/../common.cfg"
            ]
        );
    }

    #[test]
    fn same_file_may_be_included_twice_but_not_recursively() {
        let fs = files(&[("/cfg/a.cfg", "[a]\nx: 1\n")]);
        let cfg = parse_in("[include a.cfg]\n[include ./a.cfg]\n", &fs).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(text(&cfg, "a", "x"), "1");

        let fs = files(&[
            ("/cfg/a.cfg", "[a]\n[include sub/b.cfg]\n"),
            ("/cfg/sub/b.cfg", "[include ../a.cfg]\n"),
        ]);
        let e = parse_in("[include a.cfg]\n", &fs)
            .map(|_| ())
            .map_err(|e| e.to_string());
        assert_eq!(
            e,
            Err("/cfg/sub/b.cfg:1: Recursive include of config file '/cfg/sub/../a.cfg'".to_string())
        );

        let e = parse_in("[a]\n[include printer.cfg]\n", &HashMap::new()).map(|_| ());
        assert!(matches!(e, Err(IniError::IncludeCycle { .. })), "{e:?}");
    }

    #[test]
    fn include_errors_name_file_and_line() {
        assert_eq!(
            err("[a]\n\n[include missing.cfg]\n"),
            "/cfg/printer.cfg:3: Include file '/cfg/missing.cfg' cannot be read: no such file"
        );
        assert_eq!(
            err("[include conf.d/[*.cfg]\n"),
            "/cfg/printer.cfg:1: include 'conf.d/[*.cfg': bad glob pattern: invalid range pattern"
        );
        assert_eq!(
            err("[include]\n"),
            "/cfg/printer.cfg:1: [include] needs a file name"
        );
        let fs = files(&[("/cfg/a.cfg", "[a]\nx: 1\n")]);
        let e = parse_in("[b]\n[include a.cfg]\ny: 2\n", &fs)
            .map(|_| ())
            .map_err(|e| e.to_string());
        assert_eq!(
            e,
            Err("/cfg/printer.cfg:3: option 'y' comes before any [section] header".to_string())
        );
    }

    /// [`parse_in`] with glob includes listed from `fs` too.
    fn parse_globbing(main: &str, fs: &HashMap<PathBuf, String>) -> Result<ConfigFile, IniError> {
        let mut read = |p: &Path| {
            fs.get(&normalize(p))
                .cloned()
                .ok_or_else(|| io::Error::new(io::ErrorKind::NotFound, "no such file"))
        };
        let mut list = |pattern: &Path| {
            let pattern =
                glob::Pattern::new(&normalize(pattern).to_string_lossy()).map_err(|e| e.to_string())?;
            // Reverse name order: the parser must sort.
            let mut hits: Vec<PathBuf> = fs.keys().filter(|p| pattern.matches_path(p)).cloned().collect();
            hits.sort_by(|a, b| b.cmp(a));
            Ok(hits)
        };
        super::super::parse_with_listing(main, Path::new("/cfg/printer.cfg"), &mut read, &mut list)
    }

    #[test]
    fn glob_includes_take_every_match_in_name_order() {
        let fs = files(&[
            ("/cfg/conf.d/b.cfg", "[printer]\nmax_accel: 2\n"),
            ("/cfg/conf.d/a.cfg", "[printer]\nmax_accel: 1\nmax_velocity: 5\n"),
            ("/cfg/conf.d/notes.txt", "not a config"),
        ]);
        let cfg = parse_globbing("[include conf.d/*.cfg]\n", &fs).unwrap_or_else(|e| panic!("{e}"));
        // b.cfg comes after a.cfg, so its value wins.
        assert_eq!(text(&cfg, "printer", "max_accel"), "2");
        assert_eq!(text(&cfg, "printer", "max_velocity"), "5");
        // No match is no include (Klipper), a plain missing name is an error.
        let cfg = parse_globbing("[a]\n[include macros/*.cfg]\n", &fs).unwrap_or_else(|e| panic!("{e}"));
        assert!(cfg.section("a").is_some());
        // A glob that matches the including file is a cycle.
        let fs = files(&[("/cfg/conf.d/a.cfg", "[include *.cfg]\n")]);
        let e = parse_globbing("[include conf.d/a.cfg]\n", &fs).map(|_| ());
        assert!(matches!(e, Err(IniError::IncludeCycle { .. })), "{e:?}");
    }

    #[test]
    fn glob_includes_read_the_disk() {
        let dir = std::env::temp_dir().join(format!("cadence-glob-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("parts")).unwrap();
        std::fs::write(dir.join("parts/2.cfg"), "[b]\ny: 2\n").unwrap();
        std::fs::write(dir.join("parts/1.cfg"), "[a]\nx: 1\n").unwrap();
        std::fs::create_dir_all(dir.join("parts/sub.cfg")).unwrap(); // a directory: skipped
        std::fs::write(dir.join("printer.cfg"), "[include parts/*.cfg]\n").unwrap();
        let cfg = super::super::load(&dir.join("printer.cfg")).unwrap_or_else(|e| panic!("{e}"));
        let _ = std::fs::remove_dir_all(&dir);
        assert_eq!((text(&cfg, "a", "x"), text(&cfg, "b", "y")), ("1", "2"));
        let names: Vec<_> = cfg.files.iter().filter_map(|f| f.file_name()).collect();
        assert_eq!(names, ["printer.cfg", "1.cfg", "2.cfg"]);
    }

    #[test]
    fn includes_nested_too_deep_are_an_error() {
        // Each file includes a deeper, distinct path: no cycle by name, but unbounded.
        let mut read = |_: &Path| Ok("[include x/n.cfg]\n".to_string());
        let e = parse_with("[include x/n.cfg]\n", Path::new("/v/n.cfg"), &mut read);
        assert!(matches!(e, Err(IniError::IncludeTooDeep { .. })), "{e:?}");
    }

    #[test]
    fn syntax_error_messages() {
        assert_eq!(
            err("x: 1\n"),
            "/cfg/printer.cfg:1: option 'x' comes before any [section] header"
        );
        assert_eq!(err("[a]\n[b\n"), "/cfg/printer.cfg:2: '[' without a closing ']'");
        assert_eq!(err("[ ]\n"), "/cfg/printer.cfg:1: empty section name '[]'");
        assert_eq!(
            err("[a] b\n"),
            "/cfg/printer.cfg:1: unexpected text 'b' after the section header"
        );
        assert_eq!(
            err("[a]\n: 1\n"),
            "/cfg/printer.cfg:2: empty option name before ':' or '='"
        );
        assert_eq!(
            err("[a]\n\nfoo bar\n"),
            "/cfg/printer.cfg:3: expected 'key: value', 'key = value', '[section]' or an indented \
             continuation, got 'foo bar'"
        );
    }

    #[test]
    fn main_file_read_error_names_the_file() {
        let e = super::super::load(Path::new("/nonexistent/printer.cfg")).map(|_| ());
        let e = e.map_err(|e| e.to_string()).err().unwrap_or_default();
        assert!(
            e.starts_with("/nonexistent/printer.cfg: cannot read config file: "),
            "{e}"
        );
    }

    #[test]
    fn save_config_block_adds_but_the_body_wins() {
        // Klipper's load: an option the body sets is kept; the block's copy is ignored
        // (multi-line values too), the block's other options apply.
        let main = "[extruder]\ncontrol: watermark\n[bed_mesh default]\npoints: 1\n\n\
            #*# <---------------------- SAVE_CONFIG ---------------------->\n\
            #*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.\n\
            #*#\n#*# [extruder]\n#*# control = pid\n#*# pid_kp = 22.2\n\
            #*#\n#*# [bed_mesh default]\n#*# points =\n#*# \t0.1, 0.2\n#*# x = 1\n";
        let cfg = parse(main);
        assert_eq!(text(&cfg, "extruder", "control"), "watermark");
        assert_eq!(text(&cfg, "extruder", "pid_kp"), "22.2");
        assert_eq!(text(&cfg, "bed_mesh default", "points"), "1");
        assert_eq!(text(&cfg, "bed_mesh default", "x"), "1");
    }

    #[test]
    fn save_config_block_overrides() {
        let main = "[extruder]\nmax_power: 1\n\n\
            #*# <---------------------- SAVE_CONFIG ---------------------->\n\
            #*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.\n\
            #*#\n#*# [extruder]\n#*# control = pid\n#*# pid_kp = 22.2\n\
            #*#\n#*# [bed_mesh default]\n#*# points =\n#*# \t0.1, 0.2\n#*# \t0.3, 0.4\n";
        let cfg = parse(main);
        assert_eq!(text(&cfg, "extruder", "control"), "pid");
        assert_eq!(text(&cfg, "extruder", "pid_kp"), "22.2");
        assert_eq!(text(&cfg, "bed_mesh default", "points"), "\n0.1, 0.2\n0.3, 0.4");
        let at = cfg
            .section("extruder")
            .and_then(|s| s.get("control"))
            .map(|v| v.at.line);
        assert_eq!(at, Some(8));
        assert_eq!(
            err("[a]\n#*# <---------------------- SAVE_CONFIG ---------------------->\n#*# [b]\nc: 1\n"),
            "/cfg/printer.cfg:4: line inside the SAVE_CONFIG block does not start with '#*#'"
        );
    }

    #[test]
    fn save_config_marker_only_in_the_main_file() {
        let fs = files(&[(
            "/cfg/a.cfg",
            "#*# <---------------------- SAVE_CONFIG ---------------------->\n#*# [b]\nplain: 1\n",
        )]);
        let e = parse_in("[include a.cfg]\n", &fs)
            .map(|_| ())
            .map_err(|e| e.to_string());
        assert_eq!(
            e,
            Err("/cfg/a.cfg:3: option 'plain' comes before any [section] header".to_string())
        );
    }

    #[test]
    fn normalize_is_lexical() {
        assert_eq!(normalize(Path::new("/a/./b/../c.cfg")), PathBuf::from("/a/c.cfg"));
        assert_eq!(normalize(Path::new("../x/../../y")), PathBuf::from("../../y"));
        assert_eq!(normalize(Path::new("/../y")), PathBuf::from("/y"));
    }

    /// Sections and options without locations, for comparing parses.
    fn shape(cfg: &ConfigFile) -> Vec<(String, Vec<(String, String)>)> {
        cfg.sections()
            .iter()
            .map(|s| {
                (
                    s.name().to_string(),
                    s.options()
                        .map(|(k, v)| (k.to_string(), v.text.clone()))
                        .collect(),
                )
            })
            .collect()
    }

    fn no_fs(_: &Path) -> io::Result<String> {
        Err(io::Error::new(
            io::ErrorKind::NotFound,
            "no includes in this test",
        ))
    }

    fn arb_value() -> impl Strategy<Value = String> {
        // First line may be empty; later lines are non-empty, or empty between non-empty ones.
        let word = "[A-Za-z0-9_.:=!^~/-]([A-Za-z0-9_.:=!^~/ -]{0,12}[A-Za-z0-9_.:=!^~/-])?";
        (
            proptest::option::of(word),
            proptest::collection::vec(proptest::option::of(word), 0..4),
        )
            .prop_map(|(first, rest)| {
                let mut lines = vec![first.unwrap_or_default()];
                let mut pending = 0;
                for l in rest {
                    match l {
                        Some(l) => {
                            lines.extend(std::iter::repeat_n(String::new(), pending));
                            pending = 0;
                            lines.push(l);
                        }
                        None => pending += 1,
                    }
                }
                lines.join("\n")
            })
    }

    type Model = Vec<(String, Vec<(String, String)>)>;

    fn arb_model() -> impl Strategy<Value = Model> {
        let section = (
            "[a-z_][a-z0-9_]{0,8}( [A-Za-z0-9_]{1,6})?",
            proptest::collection::vec(("[a-z_][a-z0-9_]{0,10}", arb_value()), 0..6),
        );
        let section = section.prop_filter("[include] is not a section", |(name, _)| {
            include_spec(name).is_none()
        });
        proptest::collection::vec(section, 0..6).prop_map(|sections| {
            // Merge like the parser does, so the model is what a parse must give.
            let mut merged: Model = Vec::new();
            for (name, options) in sections {
                let i = match merged.iter().position(|(n, _)| *n == name) {
                    Some(i) => i,
                    None => {
                        merged.push((name, Vec::new()));
                        merged.len() - 1
                    }
                };
                for (k, v) in options {
                    let opts = &mut merged[i].1;
                    match opts.iter_mut().find(|(ok, _)| *ok == k) {
                        Some(slot) => slot.1 = v,
                        None => opts.push((k, v)),
                    }
                }
            }
            merged
        })
    }

    fn render(model: &Model, delimiter: &str, indent: &str) -> String {
        let mut out = String::new();
        for (name, options) in model {
            out.push_str(&format!("# section {name}\n[{name}]\n"));
            for (k, v) in options {
                let mut lines = v.split('\n');
                out.push_str(&format!("{k}{delimiter}{}\n", lines.next().unwrap_or("")));
                for l in lines {
                    out.push_str(&format!("{indent}{l}\n"));
                }
            }
            out.push('\n');
        }
        out
    }

    proptest! {
        #[test]
        fn never_panics_on_arbitrary_text(text in "(?s).{0,400}") {
            let _ = parse_with(&text, Path::new("/p/printer.cfg"), &mut no_fs);
        }

        #[test]
        fn never_panics_on_line_soup(lines in proptest::collection::vec(
            "[ \t]{0,3}(\\[[a-z ]{0,6}\\]?|[a-z#;]{0,4}[:=]?[ a-z#;:=\\[\\]]{0,8}|#\\*# .{0,10}|#\\*# <- SAVE_CONFIG ->)",
            0..30,
        )) {
            let text = lines.join("\n");
            let _ = parse_with(&text, Path::new("/p/printer.cfg"), &mut no_fs);
        }

        #[test]
        fn generated_files_round_trip(model in arb_model(), colon in any::<bool>(), tab in any::<bool>()) {
            let text = render(&model, if colon { ": " } else { " = " }, if tab { "\t" } else { "    " });
            let cfg = parse_with(&text, Path::new("/p/printer.cfg"), &mut no_fs);
            let cfg = cfg.map_err(|e| TestCaseError::fail(format!("{e}\n{text}")))?;
            prop_assert_eq!(shape(&cfg), model);
            // The writer's output parses back to the same sections and options.
            let again = parse_with(&cfg.to_string(), Path::new("/p/printer.cfg"), &mut no_fs);
            let again = again.map_err(|e| TestCaseError::fail(format!("{e}\n{cfg}")))?;
            prop_assert_eq!(shape(&again), shape(&cfg));
        }
    }
}
