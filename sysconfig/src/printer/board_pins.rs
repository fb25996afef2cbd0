//! `[board_pins]` and `[board_pins NAME]`: pin aliases as Klipper reads them. `aliases:` (and any
//! `aliases_*` option) lists `NAME=PIN` pairs separated by commas (lines may carry `#`
//! comments); a value in angle brackets (`EXP1_9=<GND>`) reserves the name: a pin option naming
//! it is an error. `mcu:` lists the MCUs (comma-separated, default `mcu`) the aliases apply to.
//! Pin options are resolved through the aliases before they are checked and claimed, so the
//! typed config carries the MCU's own pin names.

use std::collections::HashMap;

use super::error::{ConfigError, ValueProblem};
use super::pins::MAIN_MCU;
use super::reader::{Reader, SectionReader};

/// What an alias stands for.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Alias {
    /// The MCU's pin name.
    Pin(String),
    /// A reserved name (`<GND>`): not a pin.
    Reserved(String),
}

/// Aliases by (MCU name, alias).
pub(crate) type Aliases = HashMap<(String, String), Alias>;

/// Every `[board_pins …]` section's aliases.
pub(crate) fn read_board_pins(reader: &Reader<'_>) -> Result<Aliases, ConfigError> {
    let mut out = Aliases::new();
    for s in reader.sections_of_kind("board_pins") {
        let mcus: Vec<String> = match s.value("mcu") {
            Some(v) => v
                .text
                .split(',')
                .map(|m| m.trim().to_string())
                .filter(|m| !m.is_empty())
                .collect(),
            None => vec![MAIN_MCU.to_string()],
        };
        for (option, value) in aliases_options(&s) {
            for (name, alias) in
                parse_aliases(&value.text).map_err(|why| s.bad(&option, value, ValueProblem::Invalid(why)))?
            {
                for mcu in &mcus {
                    if out.insert((mcu.clone(), name.clone()), alias.clone()).is_some() {
                        let why = format!("alias '{name}' is defined twice");
                        return Err(s.bad(&option, value, ValueProblem::Invalid(why)));
                    }
                }
            }
        }
    }
    Ok(out)
}

/// `aliases` and every `aliases_*` option of a section, marked used.
fn aliases_options<'r>(s: &SectionReader<'r>) -> Vec<(String, &'r crate::ini::Value)> {
    s.options_with_prefix("aliases")
        .into_iter()
        .filter(|(rest, _)| rest.is_empty() || rest.starts_with('_'))
        .map(|(rest, v)| (format!("aliases{rest}"), v))
        .collect()
}

/// `NAME=PIN, NAME=<RESERVED>, …` (comments after `#` or `;` on each line removed).
fn parse_aliases(text: &str) -> Result<Vec<(String, Alias)>, String> {
    let mut out = Vec::new();
    let code: Vec<&str> = text
        .lines()
        .map(|l| l.split(['#', ';']).next().unwrap_or(""))
        .collect();
    for item in code.join(",").split(',') {
        let item = item.trim();
        if item.is_empty() {
            continue;
        }
        let (name, pin) = item
            .split_once('=')
            .map(|(n, p)| (n.trim(), p.trim()))
            .ok_or_else(|| format!("'{item}' is not NAME=PIN"))?;
        if name.is_empty()
            || pin.is_empty()
            || name.contains(char::is_whitespace)
            || pin.contains(char::is_whitespace)
        {
            return Err(format!("'{item}' is not NAME=PIN"));
        }
        let alias = match pin.strip_prefix('<').and_then(|p| p.strip_suffix('>')) {
            Some(reserved) => Alias::Reserved(reserved.to_string()),
            None => Alias::Pin(pin.to_string()),
        };
        out.push((name.to_string(), alias));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn aliases_parse_with_comments_and_reserved_names() {
        let got = parse_aliases("\n# EXP1 header\nEXP1_1=PB5, EXP1_9=<GND>,\nEXP1_2=PA8 ; end\n").unwrap();
        assert_eq!(
            got,
            [
                ("EXP1_1".to_string(), Alias::Pin("PB5".into())),
                ("EXP1_9".to_string(), Alias::Reserved("GND".into())),
                ("EXP1_2".to_string(), Alias::Pin("PA8".into())),
            ]
        );
        assert_eq!(parse_aliases("A=PB5, B"), Err("'B' is not NAME=PIN".into()));
        assert_eq!(parse_aliases("A B=PB5"), Err("'A B=PB5' is not NAME=PIN".into()));
    }

    proptest! {
        #[test]
        fn parse_never_panics(text in "(?s).{0,80}") {
            let _ = parse_aliases(&text);
        }
    }
}
