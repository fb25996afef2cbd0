//! Typed, consumption-tracking access to a parsed [`ConfigFile`], like Klipper's config
//! wrapper: every getter marks its option as used; after the typed config is built,
//! [`Reader::finish`] turns every option nothing read into an error, and every section nothing
//! read into an error unless it is on the accept-and-ignore list (then a warning).
//!
//! Bounds follow Klipper's `getfloat(minval=, maxval=, above=, below=)`: `min`/`max` inclusive,
//! `above`/`below` exclusive. Defaults are returned as given, unchecked (Klipper does the same),
//! so a derived default never fails a bound meant for user input.

use std::cell::Cell;
use std::ops::RangeInclusive;
use std::path::Path;

use crate::ini::{ConfigFile, Location, Section, Value};

use super::error::{ConfigError, ValueProblem};
use super::pins::{PinKind, PinRef, PinRegistry, Share};

/// Inclusive (`min`, `max`) and exclusive (`above`, `below`) limits for a float option.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Bounds {
    min: Option<f64>,
    max: Option<f64>,
    above: Option<f64>,
    below: Option<f64>,
}

impl Bounds {
    pub(crate) const ANY: Bounds = Bounds {
        min: None,
        max: None,
        above: None,
        below: None,
    };

    pub(crate) const fn min(mut self, v: f64) -> Self {
        self.min = Some(v);
        self
    }
    pub(crate) const fn max(mut self, v: f64) -> Self {
        self.max = Some(v);
        self
    }
    pub(crate) const fn above(mut self, v: f64) -> Self {
        self.above = Some(v);
        self
    }
    pub(crate) const fn below(mut self, v: f64) -> Self {
        self.below = Some(v);
        self
    }

    pub(crate) fn check(&self, got: f64) -> Result<f64, ValueProblem> {
        if let Some(min) = self.min.filter(|&m| got < m) {
            return Err(ValueProblem::BelowMinimum { min, got });
        }
        if let Some(max) = self.max.filter(|&m| got > m) {
            return Err(ValueProblem::AboveMaximum { max, got });
        }
        if let Some(bound) = self.above.filter(|&b| got <= b) {
            return Err(ValueProblem::NotAbove { bound, got });
        }
        if let Some(bound) = self.below.filter(|&b| got >= b) {
            return Err(ValueProblem::NotBelow { bound, got });
        }
        Ok(got)
    }
}

/// Parses a finite float.
pub(crate) fn parse_float(text: &str) -> Result<f64, ValueProblem> {
    let v: f64 = text
        .trim()
        .parse()
        .map_err(|_| ValueProblem::NotANumber(text.to_string()))?;
    if v.is_finite() {
        Ok(v)
    } else {
        Err(ValueProblem::NotFinite(text.to_string()))
    }
}

/// Parses configparser's booleans.
fn parse_bool(text: &str) -> Result<bool, ValueProblem> {
    match text.trim().to_ascii_lowercase().as_str() {
        "1" | "yes" | "true" | "on" => Ok(true),
        "0" | "no" | "false" | "off" => Ok(false),
        _ => Err(ValueProblem::NotABoolean(text.to_string())),
    }
}

/// The config being read, and which sections and options have been read.
#[derive(Debug)]
pub(crate) struct Reader<'a> {
    file: &'a ConfigFile,
    section_read: Vec<Cell<bool>>,
    option_used: Vec<Vec<Cell<bool>>>,
}

impl<'a> Reader<'a> {
    pub(crate) fn new(file: &'a ConfigFile) -> Self {
        Reader {
            file,
            section_read: file.sections().iter().map(|_| Cell::new(false)).collect(),
            option_used: file
                .sections()
                .iter()
                .map(|s| s.options().map(|_| Cell::new(false)).collect())
                .collect(),
        }
    }

    /// The main file, for errors without a line.
    pub(crate) fn main_file(&self) -> &'a Path {
        self.file.main_file()
    }

    fn view(&self, index: usize) -> Option<SectionReader<'_>> {
        let section = self.file.sections().get(index)?;
        let used = self.option_used.get(index)?;
        if let Some(read) = self.section_read.get(index) {
            read.set(true);
        }
        Some(SectionReader { section, used })
    }

    /// The section named `name`, marked as read.
    pub(crate) fn section(&self, name: &str) -> Option<SectionReader<'_>> {
        let index = self.file.sections().iter().position(|s| s.name() == name)?;
        self.view(index)
    }

    /// The optional section `name` built by `read`, or `T`'s defaults when it is absent.
    pub(crate) fn section_or_default<T: Default>(
        &self,
        name: &str,
        read: impl FnOnce(&SectionReader<'_>) -> Result<T, ConfigError>,
    ) -> Result<T, ConfigError> {
        self.section(name).map_or_else(|| Ok(T::default()), |s| read(&s))
    }

    /// Every `[kind]` and `[kind NAME]` section, in file order, marked as read.
    pub(crate) fn sections_of_kind(&self, kind: &str) -> Vec<SectionReader<'_>> {
        let indices = self.file.sections().iter().enumerate();
        let wanted = indices.filter(|(_, s)| s.kind() == kind).map(|(i, _)| i);
        wanted
            .collect::<Vec<_>>()
            .into_iter()
            .filter_map(|i| self.view(i))
            .collect()
    }

    /// Every section whose kind is one of `kinds`, in file order, marked as read.
    pub(crate) fn sections_of_kinds(&self, kinds: &[&str]) -> Vec<SectionReader<'_>> {
        let indices = self.file.sections().iter().enumerate();
        let wanted = indices.filter(|(_, s)| kinds.contains(&s.kind())).map(|(i, _)| i);
        wanted
            .collect::<Vec<_>>()
            .into_iter()
            .filter_map(|i| self.view(i))
            .collect()
    }

    /// The names of every `[kind …]` section, in file order (not marked as read).
    pub(crate) fn section_names_of_kind(&self, kind: &str) -> Vec<String> {
        self.file
            .sections()
            .iter()
            .filter(|s| s.kind() == kind)
            .map(|s| s.name().to_string())
            .collect()
    }

    /// Every `[kind NAME]` section (with an argument), in file order, marked as read.
    pub(crate) fn sections_with_arg(&self, kind: &str) -> Vec<SectionReader<'_>> {
        let indices = self.file.sections().iter().enumerate();
        let wanted = indices
            .filter(|(_, s)| s.kind() == kind && s.arg().is_some())
            .map(|(i, _)| i);
        wanted
            .collect::<Vec<_>>()
            .into_iter()
            .filter_map(|i| self.view(i))
            .collect()
    }

    /// After building: the first section nobody read (unless `ignored(kind)`) or option nobody
    /// read is an error, in file order; otherwise one warning per kind of ignored section.
    pub(crate) fn finish(&self, ignored: impl Fn(&str) -> bool) -> Result<Vec<String>, ConfigError> {
        let mut ignored_kinds: Vec<(&str, &Location, usize)> = Vec::new();
        for (i, section) in self.file.sections().iter().enumerate() {
            let read = self.section_read.get(i).is_some_and(Cell::get);
            if !read {
                if !ignored(section.kind()) {
                    return Err(ConfigError::UnknownSection {
                        at: section.at().clone(),
                        section: section.name().to_string(),
                    });
                }
                match ignored_kinds.iter_mut().find(|(k, _, _)| *k == section.kind()) {
                    Some(entry) => entry.2 += 1,
                    None => ignored_kinds.push((section.kind(), section.at(), 1)),
                }
                continue;
            }
            let used = self.option_used.get(i).map_or(&[][..], Vec::as_slice);
            for (j, (key, value)) in section.options().enumerate() {
                if !used.get(j).is_some_and(Cell::get) {
                    return Err(ConfigError::UnknownOption {
                        at: value.at.clone(),
                        section: section.name().to_string(),
                        option: key.to_string(),
                    });
                }
            }
        }
        Ok(ignored_kinds
            .into_iter()
            .map(|(kind, at, count)| {
                let what = if count == 1 {
                    "section".to_string()
                } else {
                    format!("{count} sections")
                };
                format!("{at}: [{kind}] is not implemented by Cadence yet; {what} ignored")
            })
            .collect())
    }
}

/// One section being read.
#[derive(Debug, Clone, Copy)]
pub(crate) struct SectionReader<'r> {
    section: &'r Section,
    used: &'r [Cell<bool>],
}

impl<'r> SectionReader<'r> {
    pub(crate) fn name(&self) -> &'r str {
        self.section.name()
    }

    pub(crate) fn arg(&self) -> Option<&'r str> {
        self.section.arg()
    }

    /// The section's kind: the first word of its name.
    pub(crate) fn kind(&self) -> &'r str {
        self.section.kind()
    }

    pub(crate) fn at(&self) -> &'r Location {
        self.section.at()
    }

    /// The raw value of `option`, marking it used.
    pub(crate) fn value(&self, option: &str) -> Option<&'r Value> {
        let index = self.section.options().position(|(k, _)| k == option)?;
        if let Some(used) = self.used.get(index) {
            used.set(true);
        }
        self.section.get(option)
    }

    /// Every option named `prefix…` with the rest of its name, marking them used
    /// (`variable_count` → `("count", value)`).
    pub(crate) fn options_with_prefix(&self, prefix: &str) -> Vec<(&'r str, &'r Value)> {
        let mut out = Vec::new();
        for (i, (key, value)) in self.section.options().enumerate() {
            if let Some(rest) = key.strip_prefix(prefix) {
                if let Some(used) = self.used.get(i) {
                    used.set(true);
                }
                out.push((rest, value));
            }
        }
        out
    }

    /// The raw value of a required option.
    pub(crate) fn required(&self, option: &str) -> Result<&'r Value, ConfigError> {
        self.value(option).ok_or_else(|| ConfigError::MissingOption {
            at: self.at().clone(),
            section: self.name().to_string(),
            option: option.to_string(),
        })
    }

    /// The error for `option`'s value `value`.
    pub(crate) fn bad(&self, option: &str, value: &Value, problem: ValueProblem) -> ConfigError {
        ConfigError::BadValue {
            at: value.at.clone(),
            section: self.name().to_string(),
            option: option.to_string(),
            problem: Box::new(problem),
        }
    }

    /// Applies `parse` to the option's text, turning its problem into an error at the value.
    fn parse<T>(
        &self,
        option: &str,
        parse: impl FnOnce(&str) -> Result<T, ValueProblem>,
    ) -> Result<Option<T>, ConfigError> {
        match self.value(option) {
            None => Ok(None),
            Some(v) => parse(&v.text).map(Some).map_err(|p| self.bad(option, v, p)),
        }
    }

    fn or_missing<T>(&self, option: &str, v: Option<T>) -> Result<T, ConfigError> {
        v.ok_or_else(|| ConfigError::MissingOption {
            at: self.at().clone(),
            section: self.name().to_string(),
            option: option.to_string(),
        })
    }

    pub(crate) fn string(&self, option: &str) -> Result<String, ConfigError> {
        Ok(self.required(option)?.text.clone())
    }

    pub(crate) fn opt_float(&self, option: &str, bounds: Bounds) -> Result<Option<f64>, ConfigError> {
        self.parse(option, |t| bounds.check(parse_float(t)?))
    }

    pub(crate) fn float(&self, option: &str, bounds: Bounds) -> Result<f64, ConfigError> {
        let v = self.opt_float(option, bounds)?;
        self.or_missing(option, v)
    }

    pub(crate) fn float_or(&self, option: &str, default: f64, bounds: Bounds) -> Result<f64, ConfigError> {
        Ok(self.opt_float(option, bounds)?.unwrap_or(default))
    }

    /// An integer in `range`, converted to `T`; `default` when absent (`None`: required).
    pub(crate) fn int<T: TryFrom<i64>>(
        &self,
        option: &str,
        default: Option<T>,
        range: RangeInclusive<i64>,
    ) -> Result<T, ConfigError> {
        let parsed = self.parse(option, |t| {
            let v: i64 = t
                .trim()
                .parse()
                .map_err(|_| ValueProblem::NotAnInteger(t.to_string()))?;
            if v < *range.start() {
                return Err(ValueProblem::BelowMinimum {
                    min: *range.start() as f64,
                    got: v as f64,
                });
            }
            if v > *range.end() {
                return Err(ValueProblem::AboveMaximum {
                    max: *range.end() as f64,
                    got: v as f64,
                });
            }
            T::try_from(v).map_err(|_| ValueProblem::AboveMaximum {
                max: *range.end() as f64,
                got: v as f64,
            })
        })?;
        match (parsed, default) {
            (Some(v), _) | (None, Some(v)) => Ok(v),
            (None, None) => self.or_missing(option, None),
        }
    }

    pub(crate) fn opt_bool(&self, option: &str) -> Result<Option<bool>, ConfigError> {
        self.parse(option, parse_bool)
    }

    /// One of `choices` (exact match); `default` when absent (`None`: required).
    pub(crate) fn choice<T: Copy>(
        &self,
        option: &str,
        choices: &[(&str, T)],
        default: Option<T>,
    ) -> Result<T, ConfigError> {
        let parsed = self.parse(option, |t| {
            choices
                .iter()
                .find(|(name, _)| *name == t)
                .map(|(_, v)| *v)
                .ok_or_else(|| ValueProblem::NotAChoice {
                    got: t.to_string(),
                    expected: choices.iter().map(|(name, _)| name.to_string()).collect(),
                })
        })?;
        match (parsed, default) {
            (Some(v), _) | (None, Some(v)) => Ok(v),
            (None, None) => self.or_missing(option, None),
        }
    }

    /// A pin description, checked against the declared MCUs and earlier uses.
    pub(crate) fn opt_pin(
        &self,
        option: &str,
        kind: PinKind,
        pins: &mut PinRegistry,
        share: Share,
    ) -> Result<Option<PinRef>, ConfigError> {
        let Some(v) = self.value(option) else {
            return Ok(None);
        };
        let pin = PinRef::parse(&v.text, kind).map_err(|problem| {
            self.bad(
                option,
                v,
                ValueProblem::BadPin {
                    pin: v.text.clone(),
                    problem,
                },
            )
        })?;
        let pin = pins.resolve(pin).map_err(|p| self.bad(option, v, p))?;
        if kind != PinKind::Output && pin.mcu == super::multi_pin::MULTI_PIN_CHIP {
            let why = format!("pin '{pin}': multi_pin only supports output pins");
            return Err(self.bad(option, v, ValueProblem::Invalid(why)));
        }
        if kind != PinKind::Analog && pins.scaled_mcu(&pin.mcu).is_some() {
            let why = format!("pin '{pin}': adc_scaled only supports adc pins");
            return Err(self.bad(option, v, ValueProblem::Invalid(why)));
        }
        pins.claim(&pin, self.name(), option, share)
            .map_err(|p| self.bad(option, v, p))?;
        Ok(Some(pin))
    }

    pub(crate) fn pin(
        &self,
        option: &str,
        kind: PinKind,
        pins: &mut PinRegistry,
        share: Share,
    ) -> Result<PinRef, ConfigError> {
        let v = self.opt_pin(option, kind, pins, share)?;
        self.or_missing(option, v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ini;

    fn file(text: &str) -> ConfigFile {
        ini::parse_str(text, Path::new("printer.cfg")).unwrap_or_else(|e| panic!("{e}"))
    }

    fn msg<T: std::fmt::Debug>(r: Result<T, ConfigError>) -> String {
        match r {
            Ok(v) => panic!("expected an error, got {v:?}"),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn bounds_follow_klipper() {
        let b = Bounds::ANY.min(1.0).max(2.0);
        assert!(b.check(1.0).is_ok() && b.check(2.0).is_ok());
        assert_eq!(
            b.check(0.5),
            Err(ValueProblem::BelowMinimum { min: 1.0, got: 0.5 })
        );
        assert_eq!(
            b.check(2.5),
            Err(ValueProblem::AboveMaximum { max: 2.0, got: 2.5 })
        );
        let b = Bounds::ANY.above(0.0).below(1.0);
        assert_eq!(b.check(0.0), Err(ValueProblem::NotAbove { bound: 0.0, got: 0.0 }));
        assert_eq!(b.check(1.0), Err(ValueProblem::NotBelow { bound: 1.0, got: 1.0 }));
        assert_eq!(b.check(0.5), Ok(0.5));
    }

    #[test]
    fn typed_getters_and_their_errors() {
        let f = file("[s]\nf: 1.5\nbad: x\ninf: inf\ni: 16\nneg: -3\nb: Yes\nc: corexy\n");
        let r = Reader::new(&f);
        let s = r.section("s").unwrap_or_else(|| panic!("no [s]"));
        assert_eq!(s.float("f", Bounds::ANY.above(0.0)).ok(), Some(1.5));
        assert_eq!(s.float_or("absent", 7.0, Bounds::ANY.above(10.0)).ok(), Some(7.0));
        assert_eq!(
            msg(s.float("bad", Bounds::ANY)),
            "printer.cfg:3: [s] bad: expected a number, got 'x'"
        );
        assert_eq!(
            msg(s.float("inf", Bounds::ANY)),
            "printer.cfg:4: [s] inf: expected a finite number, got 'inf'"
        );
        assert_eq!(
            msg(s.float("f", Bounds::ANY.above(2.0))),
            "printer.cfg:2: [s] f: must be above 2, got 1.5"
        );
        assert_eq!(s.int::<u32>("i", None, 1..=i64::MAX).ok(), Some(16));
        assert_eq!(
            msg(s.int::<u32>("f", None, 1..=100)),
            "printer.cfg:2: [s] f: expected an integer, got '1.5'"
        );
        assert_eq!(
            msg(s.int::<u32>("neg", None, 1..=100)),
            "printer.cfg:6: [s] neg: must have minimum of 1, got -3"
        );
        assert_eq!(s.int::<u8>("i", None, 0..=1000).ok(), Some(16));
        assert_eq!(
            msg(s.int::<u32>("absent", None, 0..=1)),
            "printer.cfg:1: Option 'absent' in section 's' must be specified"
        );
        assert_eq!(s.opt_bool("b").ok(), Some(Some(true)));
        assert_eq!(
            msg(s.opt_bool("i")),
            "printer.cfg:5: [s] i: expected a boolean (true/false, yes/no, on/off, 1/0), got '16'"
        );
        assert_eq!(
            s.choice("c", &[("cartesian", 1), ("corexy", 2)], None).ok(),
            Some(2)
        );
        assert_eq!(
            msg(s.choice("bad", &[("cartesian", 1), ("corexy", 2)], None)),
            "printer.cfg:3: [s] bad: expected one of cartesian, corexy, got 'x'"
        );
        assert_eq!(r.finish(|_| false).map_err(|e| e.to_string()), Ok(vec![]));
    }

    #[test]
    fn pins_are_parsed_and_checked() {
        let f = file("[s]\na: ^PA0\nb: PA0\nc: nope:PA1\nd: ^PA2\n");
        let r = Reader::new(&f);
        let s = r.section("s").unwrap_or_else(|| panic!("no [s]"));
        let mut pins = PinRegistry::new(vec!["mcu".into()]);
        assert!(s.pin("a", PinKind::Input, &mut pins, Share::Exclusive).is_ok());
        assert_eq!(
            msg(s.pin("b", PinKind::Output, &mut pins, Share::Exclusive)),
            "printer.cfg:3: [s] b: pin 'PA0' is also used by [s] a"
        );
        assert_eq!(
            msg(s.pin("c", PinKind::Output, &mut pins, Share::Exclusive)),
            "printer.cfg:4: [s] c: pin 'nope:PA1' refers to mcu 'nope', but there is no [mcu nope] section"
        );
        assert_eq!(
            msg(s.pin("d", PinKind::Output, &mut pins, Share::Exclusive)),
            "printer.cfg:5: [s] d: invalid pin '^PA2': pull-up '^' / pull-down '~' is not allowed on this pin"
        );
        assert_eq!(
            s.opt_pin("zz", PinKind::Output, &mut pins, Share::Exclusive).ok(),
            Some(None)
        );
    }

    #[test]
    fn finish_reports_unread_options_and_sections() {
        let f = file("[a]\nx: 1\ny: 2\n[fan]\npin: PA0\n[fan]\n[gcode_macro A]\n[gcode_macro B]\n[weird]\n");
        let r = Reader::new(&f);
        let a = r.section("a").unwrap_or_else(|| panic!("no [a]"));
        let _ = a.value("x");
        assert_eq!(
            msg(r.finish(|k| k == "fan" || k == "gcode_macro")),
            "printer.cfg:3: Option 'y' is not valid in section 'a'"
        );
        let _ = a.value("y");
        assert_eq!(
            msg(r.finish(|k| k == "fan" || k == "gcode_macro")),
            "printer.cfg:9: Section 'weird' is not a valid config section"
        );
        let _ = r.section("weird");
        assert_eq!(
            r.finish(|k| k == "fan" || k == "gcode_macro")
                .map_err(|e| e.to_string()),
            Ok(vec![
                "printer.cfg:4: [fan] is not implemented by Cadence yet; section ignored".to_string(),
                "printer.cfg:7: [gcode_macro] is not implemented by Cadence yet; 2 sections ignored"
                    .to_string(),
            ])
        );
    }
}
