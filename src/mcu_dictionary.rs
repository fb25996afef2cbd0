//! An MCU's data dictionary for `cadence dictionary`: taken from a running simulated MCU or a
//! serial device (through `identify`, as a print connects), from a saved file (plain JSON as
//! Klipper's `out/klipper.dict`, or zlib data as `identify` serves it), or the Cadence
//! firmware's own (what batch mode uses when no `--dictionary` is given); written out as
//! JSON that `--dictionary` takes back, or as a readable table.

use std::fmt::Write as _;
use std::path::Path;
use std::time::Duration;

use links::dict::Dictionary;
use links::mcu::{LinkOptions, McuLink};
use links::transport::{PtyTransport, SerialTransport, Transport};
use serde_json::Value;

use crate::sim_mcu::{SimMcu, SimOptions};

/// Where a dictionary comes from.
#[derive(Debug, Clone, Copy)]
pub enum DictSource<'a> {
    /// The Cadence firmware's own, built in (batch mode's default).
    Builtin,
    /// A saved dictionary file.
    File(&'a Path),
    /// A simulated MCU started for the purpose (`clock_freq` Hz), asked through `identify`.
    Simulator { clock_freq: u64 },
    /// An MCU on a serial device (or pty), asked through `identify`.
    Serial { path: &'a str, baud: u32 },
}

/// Why a dictionary could not be had or written out.
#[derive(Debug, thiserror::Error)]
pub enum FetchError {
    /// The built-in dictionary or a dictionary file.
    #[error(transparent)]
    Load(#[from] crate::wire_check::DictionaryError),
    /// The simulated MCU did not start.
    #[error(transparent)]
    Simulator(#[from] crate::sim_mcu::SimError),
    /// The device (`what`: the simulated MCU or the serial path) did not open.
    #[error("{what}: {source}")]
    Open {
        what: String,
        #[source]
        source: std::io::Error,
    },
    /// The MCU did not answer `identify`.
    #[error("{what}: {source}")]
    Identify {
        what: String,
        #[source]
        source: links::mcu::LinkError,
    },
    /// The dictionary it served does not parse.
    #[error("{what}: {source}")]
    Dictionary {
        what: String,
        #[source]
        source: links::dict::DictError,
    },
    /// The dictionary's JSON.
    #[error("dictionary JSON: {0}")]
    Json(#[from] serde_json::Error),
}

/// The CLI's view (the message as shown).
impl From<FetchError> for String {
    fn from(e: FetchError) -> String {
        e.to_string()
    }
}

/// The dictionary from `source`.
pub fn fetch(source: DictSource<'_>) -> Result<Dictionary, FetchError> {
    match source {
        DictSource::Builtin => Ok(crate::wire_check::load_dictionary(None)?),
        DictSource::File(p) => Ok(crate::wire_check::load_dictionary(Some(p))?),
        DictSource::Simulator { clock_freq } => {
            let opts = SimOptions {
                clock_freq,
                time_scale: 1.0,
                trace: None,
                extra: Vec::new(),
            };
            let sim = SimMcu::spawn("mcu", &opts)?;
            let result = PtyTransport::open(&sim.pty)
                .map_err(|source| FetchError::Open {
                    what: "simulated MCU".to_string(),
                    source,
                })
                .and_then(|t| identify(Box::new(t), "simulated MCU"));
            sim.finish(Duration::from_secs(2));
            result
        }
        DictSource::Serial { path, baud } => {
            let t = SerialTransport::open(path, baud).map_err(|source| FetchError::Open {
                what: path.to_string(),
                source,
            })?;
            identify(Box::new(t), path)
        }
    }
}

/// Connects (identify, clock sync), keeps the dictionary and closes the link.
fn identify(transport: Box<dyn Transport>, what: &str) -> Result<Dictionary, FetchError> {
    let link =
        McuLink::connect(transport, LinkOptions::default()).map_err(|source| FetchError::Identify {
            what: what.to_string(),
            source,
        })?;
    let dict = Dictionary::from_compressed(link.dictionary().compressed()).map_err(|source| {
        FetchError::Dictionary {
            what: what.to_string(),
            source,
        }
    });
    link.close();
    dict
}

/// The dictionary as indented JSON (the MCU's own text re-indented; keys as served).
pub fn to_json(dict: &Dictionary) -> Result<String, FetchError> {
    let v: Value = serde_json::from_str(dict.json())?;
    Ok(serde_json::to_string_pretty(&v)?)
}

/// A readable listing: version, constants, commands and responses by id, enumerations with
/// ranges shown as `PA0..PA15`.
pub fn to_table(dict: &Dictionary) -> Result<String, FetchError> {
    let v: Value = serde_json::from_str(dict.json())?;
    let mut out = String::new();
    for key in ["app", "version", "build_versions", "license"] {
        if let Some(s) = v.get(key).and_then(Value::as_str) {
            let _ = writeln!(out, "{key}: {s}");
        }
    }
    if let Some(Value::Object(config)) = v.get("config") {
        let _ = writeln!(out, "\nconfig ({}):", config.len());
        for (k, val) in config {
            let _ = writeln!(out, "  {k:<28} {}", plain(val));
        }
    }
    for section in ["commands", "responses", "output"] {
        let Some(Value::Object(msgs)) = v.get(section) else {
            continue;
        };
        let mut by_id: Vec<(i64, &str)> = msgs
            .iter()
            .map(|(fmt, id)| (id.as_i64().unwrap_or(-1), fmt.as_str()))
            .collect();
        by_id.sort();
        let _ = writeln!(out, "\n{section} ({}):", by_id.len());
        for (id, fmt) in by_id {
            let _ = writeln!(out, "  {id:>4}  {fmt}");
        }
    }
    if let Some(Value::Object(enums)) = v.get("enumerations") {
        for (name, symbols) in enums {
            let Value::Object(symbols) = symbols else {
                continue;
            };
            let entries: Vec<String> = symbols.iter().map(|(s, val)| enum_entry(s, val)).collect();
            let _ = writeln!(out, "\nenumeration {name} ({} entries):", entries.len());
            for chunk in entries.chunks(4) {
                let _ = writeln!(out, "  {}", chunk.join(", "));
            }
        }
    }
    Ok(out)
}

/// A constant as text (strings without quotes).
fn plain(v: &Value) -> String {
    match v {
        Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

/// One enumeration entry: `name=value`, or a range `[first, count]` of numbered names as
/// `PA0..PA15=0..15`.
fn enum_entry(symbol: &str, v: &Value) -> String {
    if let Some([first, count]) = v.as_array().map(Vec::as_slice) {
        if let (Some(first), Some(count)) = (first.as_i64(), count.as_i64()) {
            let digits = symbol.len() - symbol.trim_end_matches(|c: char| c.is_ascii_digit()).len();
            let (stem, start) = symbol.split_at(symbol.len() - digits);
            let last = start
                .parse::<i64>()
                .map_or(String::from("?"), |n| (n + count - 1).to_string());
            return format!("{symbol}..{stem}{last}={first}..{}", first + count - 1);
        }
    }
    format!("{symbol}={}", plain(v))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_builtin_dictionary_lists_as_table_and_json() {
        let dict = fetch(DictSource::Builtin).unwrap();
        let table = to_table(&dict).unwrap();
        assert!(table.contains("CLOCK_FREQ"), "{table}");
        assert!(
            table.contains("queue_step oid=%c interval=%u count=%hu add=%hi"),
            "{table}"
        );
        assert!(table.contains("enumeration pin"), "{table}");
        let json = to_json(&dict).unwrap();
        // What is written reads back as the same dictionary.
        let back = Dictionary::from_file_bytes(json.as_bytes()).unwrap();
        assert_eq!(back.clock_freq().unwrap(), dict.clock_freq().unwrap());
        assert_eq!(back.pin("PA3").unwrap(), dict.pin("PA3").unwrap());
        assert_eq!(back.messages().count(), dict.messages().count());
    }

    #[test]
    fn ranges_are_shown_as_first_and_last_name() {
        assert_eq!(enum_entry("PA0", &serde_json::json!([0, 16])), "PA0..PA15=0..15");
        assert_eq!(
            enum_entry("gpio0", &serde_json::json!([100, 30])),
            "gpio0..gpio29=100..129"
        );
        assert_eq!(enum_entry("ADC_REF", &serde_json::json!(7)), "ADC_REF=7");
    }
}
