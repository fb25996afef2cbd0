//! The MCU's data dictionary: which id each message has, the format of its parameters, the
//! enumerations (pins, shutdown reasons) and the build's constants (`CLOCK_FREQ`, …).
//!
//! The dictionary is a zlib-compressed JSON object the MCU serves through `identify`; a file may
//! also hold it as plain JSON, as Klipper's build writes `out/klipper.dict`
//! ([`Dictionary::from_file_bytes`] takes both). Nothing
//! here hard-codes a message id except the two fixed ones (0 `identify_response`, 1 `identify`),
//! which are added when the JSON leaves them out. Commands and responses are looked up by their
//! name (the format string's first word); ids share one space across commands, responses and
//! `output` (printf-style debug messages, decoded under the name `#output`).
//!
//! Enumeration values are either a number or `[start, count]`: `"PA0": [0, 8]` names the run
//! `PA0..PA7` with values `0..8` (the symbol's trailing digits are the run's first index).

mod encode;
pub mod message;
mod stream;

pub use encode::{Cmd, CmdEncoder};
pub use message::{FieldValue, Message};
pub use stream::StreamItem;

use std::collections::HashMap;
use std::io::Read;

use serde_json::Value as Json;

use crate::proto::format::{message_name, ParamType, Params};
use crate::proto::{FMT_IDENTIFY, FMT_IDENTIFY_RESPONSE, ID_IDENTIFY, ID_IDENTIFY_RESPONSE};

/// Largest dictionary accepted after decompression (a real one is ~12 KB of JSON).
pub const MAX_DICT_JSON: usize = 4 << 20;
/// Largest `[start, count]` run accepted in an enumeration.
const MAX_ENUM_RUN: i64 = 1 << 16;
/// Name under which `output` (debug printf) messages are decoded.
pub const OUTPUT_NAME: &str = "#output";

/// Errors of building, querying and using a dictionary. Every message says what is missing.
#[derive(Debug, thiserror::Error)]
pub enum DictError {
    /// The identify data did not inflate.
    #[error("MCU dictionary is not valid zlib data: {0}")]
    Decompress(std::io::Error),
    /// A dictionary file is neither JSON text nor zlib data.
    #[error("MCU dictionary is neither JSON text (as Klipper's out/klipper.dict) nor zlib data (as served by identify): {0}")]
    NotJsonOrZlib(std::io::Error),
    /// The inflated data is larger than [`MAX_DICT_JSON`].
    #[error("MCU dictionary is larger than {MAX_DICT_JSON} bytes")]
    TooLarge,
    /// The data is not JSON or not an object.
    #[error("MCU dictionary is not valid JSON: {0}")]
    Json(String),
    /// A section has the wrong shape.
    #[error("MCU dictionary section '{section}' is malformed: {detail}")]
    Malformed { section: &'static str, detail: String },
    /// A format string with an unknown conversion.
    #[error("MCU dictionary has a bad message format '{0}'")]
    BadFormat(String),
    /// Two messages claim the same id.
    #[error("MCU dictionary gives id {id} to both '{first}' and '{second}'")]
    DuplicateId { id: u32, first: String, second: String },
    /// No command of that name.
    #[error("MCU dictionary has no command '{0}'")]
    NoCommand(String),
    /// No response of that name.
    #[error("MCU dictionary has no response '{0}'")]
    NoResponse(String),
    /// A received id the dictionary does not define.
    #[error("MCU dictionary has no message with id {0}")]
    UnknownId(u32),
    /// An id that is defined, but not as a command.
    #[error("message id {0} ('{1}') is not a command")]
    NotACommand(u32, String),
    /// An id that is defined, but as a command.
    #[error("message id {0} ('{1}') is a command, not a response")]
    NotAResponse(u32, String),
    /// No such constant in `config`.
    #[error("MCU dictionary has no config constant '{0}'")]
    NoConfig(String),
    /// A constant of the wrong type.
    #[error("MCU dictionary config constant '{name}' is not {want}")]
    ConfigType { name: String, want: &'static str },
    /// No such enumeration.
    #[error("MCU dictionary has no enumeration '{0}'")]
    NoEnumeration(String),
    /// No such symbol in an enumeration.
    #[error("MCU dictionary has no {enumeration} '{symbol}'")]
    NoSymbol { enumeration: String, symbol: String },
    /// An enumeration value outside the range the caller needs.
    #[error("MCU dictionary value of {enumeration} '{symbol}' is out of range: {value}")]
    SymbolRange {
        enumeration: String,
        symbol: String,
        value: i64,
    },
    /// Wrong number of arguments.
    #[error("command '{name}' takes {expected} parameters, got {got}")]
    ArgCount {
        name: String,
        expected: usize,
        got: usize,
    },
    /// An integer where bytes belong, or the reverse.
    #[error("command '{name}' parameter '{param}' has the wrong type")]
    ArgType { name: String, param: String },
    /// An integer that does not fit its parameter's wire type.
    #[error("command '{name}' parameter '{param}' value {value} does not fit its type")]
    OutOfRange { name: String, param: String, value: i64 },
    /// The encoded message does not fit one block.
    #[error("message '{0}' does not fit in one block")]
    TooLong(String),
    /// A received message ended inside a parameter.
    #[error("message '{0}' is truncated")]
    Truncated(String),
}

/// Which section of the dictionary a message comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MsgKind {
    /// Host → MCU.
    Command,
    /// MCU → host.
    Response,
    /// MCU → host debug printf.
    Output,
}

/// One message definition.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MsgDef {
    /// The message id on the wire.
    pub id: u32,
    /// The full format string.
    pub format: String,
    /// The first word of the format (`#output` for output messages).
    pub name: String,
    /// Parameter names and types, in wire order (`arg0`, `arg1`, … for output messages).
    pub params: Vec<(String, ParamType)>,
}

/// A parsed data dictionary.
#[derive(Clone)]
pub struct Dictionary {
    json: String,
    compressed: Vec<u8>,
    defs: Vec<(MsgKind, MsgDef)>,
    by_id: HashMap<u32, usize>,
    commands: HashMap<String, usize>,
    responses: HashMap<String, usize>,
    enumerations: HashMap<String, HashMap<String, i64>>,
    static_strings: HashMap<u32, String>,
    config: serde_json::Map<String, Json>,
}

/// A summary: the JSON itself is large.
impl std::fmt::Debug for Dictionary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Dictionary")
            .field("json_bytes", &self.json.len())
            .field("commands", &self.commands.len())
            .field("responses", &self.responses.len())
            .field("enumerations", &self.enumerations.len())
            .field("config", &self.config.len())
            .finish()
    }
}

impl Dictionary {
    /// Inflates and parses the bytes the MCU served through `identify`.
    pub fn from_compressed(zlib_bytes: &[u8]) -> Result<Dictionary, DictError> {
        let mut json = Vec::new();
        flate2::read::ZlibDecoder::new(zlib_bytes)
            .take(MAX_DICT_JSON as u64 + 1)
            .read_to_end(&mut json)
            .map_err(DictError::Decompress)?;
        if json.len() > MAX_DICT_JSON {
            return Err(DictError::TooLarge);
        }
        let json = String::from_utf8(json).map_err(|e| DictError::Json(e.to_string()))?;
        let mut dict = Dictionary::from_json(&json)?;
        dict.compressed = zlib_bytes.to_vec();
        Ok(dict)
    }

    /// A dictionary file's bytes: plain JSON text (Klipper's `out/klipper.dict`; leading
    /// whitespace allowed) or zlib data (as served by `identify`). A JSON file is compressed
    /// here so that [`Dictionary::compressed`] holds what an MCU would serve.
    pub fn from_file_bytes(bytes: &[u8]) -> Result<Dictionary, DictError> {
        let start = bytes.iter().position(|b| !b.is_ascii_whitespace());
        if start.is_some_and(|i| bytes[i] == b'{') {
            if bytes.len() > MAX_DICT_JSON {
                return Err(DictError::TooLarge);
            }
            let json = std::str::from_utf8(bytes).map_err(|e| DictError::Json(e.to_string()))?;
            let mut dict = Dictionary::from_json(json)?;
            let mut enc = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
            std::io::Write::write_all(&mut enc, bytes).map_err(DictError::Decompress)?;
            dict.compressed = enc.finish().map_err(DictError::Decompress)?;
            return Ok(dict);
        }
        Dictionary::from_compressed(bytes).map_err(|e| match e {
            DictError::Decompress(io) => DictError::NotJsonOrZlib(io),
            e => e,
        })
    }

    /// Parses a dictionary's JSON text.
    pub fn from_json(json: &str) -> Result<Dictionary, DictError> {
        let root: Json = serde_json::from_str(json).map_err(|e| DictError::Json(e.to_string()))?;
        let Json::Object(root) = root else {
            return Err(DictError::Json("top level is not an object".into()));
        };
        let mut dict = Dictionary::empty(json.to_owned());
        for (section, kind) in [
            ("commands", MsgKind::Command),
            ("responses", MsgKind::Response),
            ("output", MsgKind::Output),
        ] {
            if let Some(map) = root.get(section) {
                let map = map
                    .as_object()
                    .ok_or_else(|| malformed(section, "not an object"))?;
                for (format, id) in map {
                    let id = id
                        .as_i64()
                        .and_then(wire_id)
                        .ok_or_else(|| malformed(section, format!("id of '{format}' is not a message id")))?;
                    dict.add(kind, id, format)?;
                }
            }
        }
        if !dict.by_id.contains_key(&ID_IDENTIFY) {
            dict.add(MsgKind::Command, ID_IDENTIFY, FMT_IDENTIFY)?;
        }
        if !dict.by_id.contains_key(&ID_IDENTIFY_RESPONSE) {
            dict.add(MsgKind::Response, ID_IDENTIFY_RESPONSE, FMT_IDENTIFY_RESPONSE)?;
        }
        if let Some(enums) = root.get("enumerations") {
            let enums = enums
                .as_object()
                .ok_or_else(|| malformed("enumerations", "not an object"))?;
            for (name, symbols) in enums {
                dict.enumerations
                    .insert(name.clone(), parse_enumeration(name, symbols)?);
            }
        }
        if let Some(strings) = dict.enumerations.get("static_string_id") {
            for (text, &id) in strings {
                if let Ok(id) = u32::try_from(id) {
                    dict.static_strings.insert(id, text.clone());
                }
            }
        }
        if let Some(config) = root.get("config") {
            dict.config = config
                .as_object()
                .ok_or_else(|| malformed("config", "not an object"))?
                .clone();
        }
        Ok(dict)
    }

    /// The minimal dictionary every MCU has before identify: only ids 0 and 1.
    pub fn bootstrap() -> Dictionary {
        // The two fixed formats are valid, so this cannot fail; fall back to an empty one anyway.
        Dictionary::from_json("{}").unwrap_or_else(|_| Dictionary::empty(String::new()))
    }

    /// A dictionary with nothing in it but its JSON text.
    fn empty(json: String) -> Dictionary {
        Dictionary {
            json,
            compressed: Vec::new(),
            defs: Vec::new(),
            by_id: HashMap::new(),
            commands: HashMap::new(),
            responses: HashMap::new(),
            enumerations: HashMap::new(),
            static_strings: HashMap::new(),
            config: serde_json::Map::new(),
        }
    }

    fn add(&mut self, kind: MsgKind, id: u32, format: &str) -> Result<(), DictError> {
        let (name, params) = match kind {
            MsgKind::Output => (OUTPUT_NAME.to_owned(), output_params(format)?),
            _ => {
                let params = Params::of(format)
                    .map(|p| p.map(|(n, t)| (n.to_owned(), t)))
                    .collect::<Result<Vec<_>, _>>()
                    .map_err(|_| DictError::BadFormat(format.to_owned()))?;
                (message_name(format).to_owned(), params)
            }
        };
        if name.is_empty() {
            return Err(DictError::BadFormat(format.to_owned()));
        }
        if let Some(&other) = self.by_id.get(&id) {
            return Err(DictError::DuplicateId {
                id,
                first: self.defs[other].1.format.clone(),
                second: format.to_owned(),
            });
        }
        let index = self.defs.len();
        match kind {
            MsgKind::Command => self.commands.insert(name.clone(), index),
            MsgKind::Response => self.responses.insert(name.clone(), index),
            MsgKind::Output => None,
        };
        self.by_id.insert(id, index);
        self.defs.push((
            kind,
            MsgDef {
                id,
                format: format.to_owned(),
                name,
                params,
            },
        ));
        Ok(())
    }

    /// The JSON text.
    pub fn json(&self) -> &str {
        &self.json
    }

    /// The compressed bytes this dictionary was built from (empty if built from JSON).
    pub fn compressed(&self) -> &[u8] {
        &self.compressed
    }

    /// The command named `name`.
    pub fn command(&self, name: &str) -> Result<&MsgDef, DictError> {
        self.commands
            .get(name)
            .map(|&i| &self.defs[i].1)
            .ok_or_else(|| DictError::NoCommand(name.to_owned()))
    }

    /// The response named `name`.
    pub fn response(&self, name: &str) -> Result<&MsgDef, DictError> {
        self.responses
            .get(name)
            .map(|&i| &self.defs[i].1)
            .ok_or_else(|| DictError::NoResponse(name.to_owned()))
    }

    /// The response or output message with wire id `id`.
    pub fn response_by_id(&self, id: u32) -> Result<&MsgDef, DictError> {
        match self.message_by_id(id) {
            Some((MsgKind::Command, def)) => Err(DictError::NotAResponse(id, def.name.clone())),
            Some((_, def)) => Ok(def),
            None => Err(DictError::UnknownId(id)),
        }
    }

    /// Any message with wire id `id`, with its section.
    pub fn message_by_id(&self, id: u32) -> Option<(MsgKind, &MsgDef)> {
        self.by_id.get(&id).map(|&i| (self.defs[i].0, &self.defs[i].1))
    }

    /// Every message definition with its section, in dictionary order.
    pub fn messages(&self) -> impl Iterator<Item = (MsgKind, &MsgDef)> {
        self.defs.iter().map(|(k, d)| (*k, d))
    }

    /// A config constant as a number (numbers, and strings holding one, are accepted).
    pub fn config_f64(&self, name: &str) -> Result<f64, DictError> {
        match self.config.get(name) {
            None => Err(DictError::NoConfig(name.to_owned())),
            Some(Json::Number(n)) => n.as_f64().ok_or_else(|| config_type(name, "a number")),
            Some(Json::String(s)) => s.trim().parse().map_err(|_| config_type(name, "a number")),
            Some(_) => Err(config_type(name, "a number")),
        }
    }

    /// A config constant as text (numbers are formatted).
    pub fn config_str(&self, name: &str) -> Result<String, DictError> {
        match self.config.get(name) {
            None => Err(DictError::NoConfig(name.to_owned())),
            Some(Json::String(s)) => Ok(s.clone()),
            Some(Json::Number(n)) => Ok(n.to_string()),
            Some(_) => Err(config_type(name, "a string")),
        }
    }

    /// `CLOCK_FREQ`: the MCU's nominal clock rate in Hz.
    pub fn clock_freq(&self) -> Result<f64, DictError> {
        let f = self.config_f64("CLOCK_FREQ")?;
        if f.is_finite() && f > 0.0 {
            Ok(f)
        } else {
            Err(config_type("CLOCK_FREQ", "a positive number"))
        }
    }

    /// `RECEIVE_WINDOW`: the MCU's receive buffer in bytes, if it states one.
    pub fn receive_window(&self) -> Option<usize> {
        let w = self.config_f64("RECEIVE_WINDOW").ok()?;
        (w.is_finite() && w >= 1.0 && w <= usize::MAX as f64).then_some(w as usize)
    }

    /// The value of `symbol` in enumeration `name`.
    pub fn enumeration(&self, name: &str, symbol: &str) -> Result<i64, DictError> {
        let symbols = self
            .enumerations
            .get(name)
            .ok_or_else(|| DictError::NoEnumeration(name.to_owned()))?;
        symbols.get(symbol).copied().ok_or_else(|| DictError::NoSymbol {
            enumeration: name.to_owned(),
            symbol: symbol.to_owned(),
        })
    }

    /// The symbols of enumeration `name` (empty if absent).
    pub fn enumeration_symbols(&self, name: &str) -> impl Iterator<Item = (&str, i64)> {
        self.enumerations
            .get(name)
            .into_iter()
            .flat_map(|m| m.iter().map(|(k, v)| (k.as_str(), *v)))
    }

    /// The pin number of `name` (enumeration `pin`).
    pub fn pin(&self, name: &str) -> Result<u32, DictError> {
        let v = self.enumeration("pin", name)?;
        u32::try_from(v).map_err(|_| DictError::SymbolRange {
            enumeration: "pin".into(),
            symbol: name.to_owned(),
            value: v,
        })
    }

    /// The text of a `static_string_id` (shutdown reasons).
    pub fn static_string(&self, id: u32) -> Option<&str> {
        self.static_strings.get(&id).map(String::as_str)
    }
}

/// A dictionary message id as its raw 32-bit VLQ value. Klipper builds with more than ~94
/// messages number them in "standard form": ids whose one-byte VLQ has bits 5–6 set are
/// written negative (encoded 96..127 → -32..-1), others from 128 on take two VLQ bytes. A
/// negative id is kept as its 32-bit two's complement, which is exactly what [`vlq::encode`]
/// sends and [`vlq::decode`] returns for it.
///
/// [`vlq::encode`]: crate::proto::vlq::encode
/// [`vlq::decode`]: crate::proto::vlq::decode
fn wire_id(v: i64) -> Option<u32> {
    if v < 0 {
        i32::try_from(v).ok().map(|v| v as u32)
    } else {
        u32::try_from(v).ok()
    }
}

fn malformed(section: &'static str, detail: impl Into<String>) -> DictError {
    DictError::Malformed {
        section,
        detail: detail.into(),
    }
}

fn config_type(name: &str, want: &'static str) -> DictError {
    DictError::ConfigType {
        name: name.to_owned(),
        want,
    }
}

/// Expands one enumeration: numbers map directly, `[start, count]` runs expand by index.
fn parse_enumeration(name: &str, symbols: &Json) -> Result<HashMap<String, i64>, DictError> {
    let symbols = symbols
        .as_object()
        .ok_or_else(|| malformed("enumerations", format!("'{name}' is not an object")))?;
    let mut out = HashMap::new();
    for (symbol, value) in symbols {
        let bad = || malformed("enumerations", format!("'{name}' value of '{symbol}'"));
        match value {
            Json::Number(n) => {
                out.insert(symbol.clone(), n.as_i64().ok_or_else(bad)?);
            }
            Json::Array(pair) => {
                let [start, count] = pair.as_slice() else {
                    return Err(bad());
                };
                let (start, count) = (start.as_i64().ok_or_else(bad)?, count.as_i64().ok_or_else(bad)?);
                if !(0..=MAX_ENUM_RUN).contains(&count) {
                    return Err(bad());
                }
                let root = symbol.trim_end_matches(|c: char| c.is_ascii_digit());
                let first: i64 = symbol[root.len()..].parse().map_err(|_| bad())?;
                for i in 0..count {
                    out.insert(format!("{root}{}", first + i), start + i);
                }
            }
            _ => return Err(bad()),
        }
    }
    Ok(out)
}

/// The `%` conversions of a printf-style output format, named `arg0`, `arg1`, ….
fn output_params(format: &str) -> Result<Vec<(String, ParamType)>, DictError> {
    let mut params = Vec::new();
    for (_, spec) in output_specs(format) {
        let ty = spec.ok_or_else(|| DictError::BadFormat(format.to_owned()))?;
        params.push((format!("arg{}", params.len()), ty));
    }
    Ok(params)
}

/// Iterates the `%` conversions of an output format: (byte range, type or None if unknown).
pub(crate) fn output_specs(format: &str) -> impl Iterator<Item = ((usize, usize), Option<ParamType>)> + '_ {
    const SPECS: [&str; 8] = ["%.*s", "%*s", "%hu", "%hi", "%u", "%i", "%c", "%s"];
    let mut pos = 0;
    std::iter::from_fn(move || {
        let start = pos + format.get(pos..)?.find('%')?;
        let rest = &format[start..];
        let spec = SPECS.iter().find(|s| rest.starts_with(**s));
        let len = spec.map_or(1, |s| s.len());
        pos = start + len;
        Some(((start, start + len), spec.and_then(|s| ParamType::parse(s))))
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A small hand-written dictionary used by the tests of this crate.
    pub(crate) const TEST_DICT: &str = r#"{
        "app": "Cadence", "version": "test",
        "commands": {
            "identify offset=%u count=%c": 1,
            "get_uptime": 5, "get_clock": 6, "get_config": 7,
            "queue_step oid=%c interval=%u count=%hu add=%hi": 20,
            "set_next_step_dir oid=%c dir=%c": 21,
            "debug_write buf=%*s": 22
        },
        "responses": {
            "identify_response offset=%u data=%.*s": 0,
            "uptime high=%u clock=%u": 80, "clock clock=%u": 81,
            "config is_config=%c crc=%u is_shutdown=%c move_count=%hu": 82,
            "shutdown clock=%u static_string_id=%hu": 83,
            "is_shutdown static_string_id=%hu": 84,
            "stats count=%u sum=%u sumsq=%u": 85,
            "stepper_position oid=%c pos=%i": 86
        },
        "output": { "Got %u bytes: %.*s": 90 },
        "enumerations": {
            "pin": {"PA0": [0, 8], "PB0": [8, 8], "PC10": [30, 2], "LED": 99},
            "static_string_id": {"Timer too close": 3, "Invalid count parameter": 4}
        },
        "config": {"CLOCK_FREQ": 50000000, "MCU": "linux-sim", "RECEIVE_WINDOW": 192,
                   "SERIAL_BAUD": "250000", "BAD": [1]}
    }"#;

    pub(crate) fn compress(json: &str) -> Vec<u8> {
        use std::io::Write;
        let mut enc = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
        enc.write_all(json.as_bytes()).unwrap();
        enc.finish().unwrap()
    }

    pub(crate) fn test_dict() -> Dictionary {
        Dictionary::from_compressed(&compress(TEST_DICT)).unwrap()
    }

    #[test]
    fn lookups_by_name_and_id() {
        let d = test_dict();
        assert_eq!(d.json(), TEST_DICT);
        assert!(!d.compressed().is_empty());
        let qs = d.command("queue_step").unwrap();
        assert_eq!(qs.id, 20);
        assert_eq!(qs.params.len(), 4);
        assert_eq!(qs.params[3], ("add".to_string(), ParamType::I16));
        assert_eq!(d.response("clock").unwrap().id, 81);
        assert_eq!(d.response_by_id(86).unwrap().name, "stepper_position");
        assert_eq!(d.response_by_id(90).unwrap().name, OUTPUT_NAME);
        assert!(d.response_by_id(20).is_err());
        assert_eq!(
            d.command("nope").unwrap_err().to_string(),
            "MCU dictionary has no command 'nope'"
        );
    }

    /// Ids as a Klipper build with many messages numbers them (scripts/buildcommands.py
    /// "standard form"): negative for the one-byte VLQs 0x60..0x7F, two bytes from 128.
    #[test]
    fn negative_and_two_byte_ids() {
        let d = Dictionary::from_json(
            r#"{"commands": {"queue_step oid=%c interval=%u count=%hu add=%hi": -5,
                             "trsync_start oid=%c report_clock=%u report_ticks=%u expire_reason=%c": 130},
                "responses": {"clock clock=%u": -32, "stepper_position oid=%c pos=%i": 140}}"#,
        )
        .unwrap();
        // Golden bytes: what Klipper's msgproto sends for these messages.
        let qs = d.encode("queue_step", &[2, 40_000, 20, -3]).unwrap();
        assert_eq!(qs.as_bytes(), &[0x7B, 0x02, 0x82, 0xB8, 0x40, 0x14, 0x7D]);
        let ts = d.encode("trsync_start", &[7, 0, 0, 4]).unwrap();
        assert_eq!(ts.as_bytes(), &[0x81, 0x02, 0x07, 0x00, 0x00, 0x04]);
        // Responses decode by the raw VLQ value of their id.
        let (id, _) = crate::proto::vlq::decode(&[0x60]).unwrap();
        assert_eq!(d.response_by_id(id).unwrap().name, "clock");
        let (id, _) = crate::proto::vlq::decode(&[0x81, 0x0C]).unwrap();
        assert_eq!(d.response_by_id(id).unwrap().name, "stepper_position");
        // Out of range either way.
        assert!(Dictionary::from_json(r#"{"commands": {"get_clock": -2147483649}}"#).is_err());
        assert!(Dictionary::from_json(r#"{"commands": {"get_clock": 4294967296}}"#).is_err());
    }

    #[test]
    fn implicit_identify() {
        let d = Dictionary::from_json(r#"{"commands": {"get_clock": 3}}"#).unwrap();
        assert_eq!(d.command("identify").unwrap().id, 1);
        assert_eq!(d.response("identify_response").unwrap().id, 0);
        let b = Dictionary::bootstrap();
        assert_eq!(b.command("identify").unwrap().id, 1);
    }

    #[test]
    fn config_and_enumerations() {
        let d = test_dict();
        assert_eq!(d.clock_freq().unwrap(), 50e6);
        assert_eq!(d.config_f64("SERIAL_BAUD").unwrap(), 250000.0);
        assert_eq!(d.config_str("MCU").unwrap(), "linux-sim");
        assert_eq!(d.config_str("CLOCK_FREQ").unwrap(), "50000000");
        assert!(d.config_f64("BAD").is_err());
        assert_eq!(
            d.config_f64("NOPE").unwrap_err().to_string(),
            "MCU dictionary has no config constant 'NOPE'"
        );
        assert_eq!(d.receive_window(), Some(192));
        assert_eq!(d.pin("PA0").unwrap(), 0);
        assert_eq!(d.pin("PA7").unwrap(), 7);
        assert_eq!(d.pin("PB3").unwrap(), 11);
        assert_eq!(d.pin("PC11").unwrap(), 31);
        assert_eq!(d.pin("LED").unwrap(), 99);
        assert!(d.pin("PA8").is_err());
        assert!(d.pin("PC9").is_err());
        assert_eq!(
            d.pin("PZ9").unwrap_err().to_string(),
            "MCU dictionary has no pin 'PZ9'"
        );
        assert_eq!(d.static_string(3), Some("Timer too close"));
        assert_eq!(d.static_string(77), None);
        assert_eq!(
            d.enumeration("static_string_id", "Invalid count parameter")
                .unwrap(),
            4
        );
        assert!(d.enumeration("spi_bus", "x").is_err());
    }

    #[test]
    fn rejects_bad_dictionaries() {
        assert!(matches!(
            Dictionary::from_compressed(b"not zlib"),
            Err(DictError::Decompress(_))
        ));
        assert!(matches!(Dictionary::from_json("[1]"), Err(DictError::Json(_))));
        assert!(matches!(
            Dictionary::from_json(r#"{"commands": {"a x=%q": 3}}"#),
            Err(DictError::BadFormat(_))
        ));
        assert!(matches!(
            Dictionary::from_json(r#"{"commands": {"a": 3}, "responses": {"b": 3}}"#),
            Err(DictError::DuplicateId { id: 3, .. })
        ));
        // Negative ids are valid (Klipper's standard form), fractions and strings are not.
        assert!(Dictionary::from_json(r#"{"commands": {"a": -1}}"#).is_ok());
        assert!(Dictionary::from_json(r#"{"commands": {"a": 1.5}}"#).is_err());
        assert!(Dictionary::from_json(r#"{"commands": {"a": "1"}}"#).is_err());
        assert!(Dictionary::from_json(r#"{"enumerations": {"pin": {"PA": [0, 2]}}}"#).is_err());
        assert!(Dictionary::from_json(r#"{"enumerations": {"pin": {"PA0": [0]}}}"#).is_err());
        assert!(Dictionary::from_json(r#"{"output": {"x %q": 9}}"#).is_err());
    }

    /// Klipper's build writes `out/klipper.dict` as plain JSON, `identify` serves zlib: a
    /// dictionary file may be either (`--dictionary` took only zlib).
    #[test]
    fn dictionary_files_are_json_or_zlib() {
        let plain = Dictionary::from_file_bytes(format!("\n {TEST_DICT}\n").as_bytes()).unwrap();
        let zlib = Dictionary::from_file_bytes(&compress(TEST_DICT)).unwrap();
        for d in [&plain, &zlib] {
            assert_eq!(d.command("queue_step").unwrap().id, 20);
            assert_eq!(d.response("clock").unwrap().id, 81);
        }
        let again = Dictionary::from_compressed(plain.compressed()).unwrap();
        assert_eq!(again.command("queue_step").unwrap().id, 20);
        let err = Dictionary::from_file_bytes(b"not a dictionary").unwrap_err();
        assert!(matches!(err, DictError::NotJsonOrZlib(_)), "{err}");
        assert!(err.to_string().contains("neither JSON"), "{err}");
        assert!(matches!(
            Dictionary::from_file_bytes(b"{\"commands\": 3}"),
            Err(DictError::Malformed { .. })
        ));
    }

    proptest::proptest! {
        #[test]
        fn from_file_bytes_never_panics(b in proptest::collection::vec(proptest::prelude::any::<u8>(), 0..200)) {
            let _ = Dictionary::from_file_bytes(&b);
        }

        #[test]
        fn from_json_never_panics(s in ".{0,200}") {
            let _ = Dictionary::from_json(&s);
        }

        #[test]
        fn from_compressed_never_panics(b in proptest::collection::vec(proptest::prelude::any::<u8>(), 0..200)) {
            let _ = Dictionary::from_compressed(&b);
        }
    }
}
