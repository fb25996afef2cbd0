//! Streaming G-code parser: one [`GcodeLine`] per command line of any `BufRead`, never holding
//! more than one line (at most [`MAX_LINE_LEN`] bytes) in memory.
//!
//! Syntax accepted (RepRap/Klipper dialect):
//! - `;` starts a comment to the end of the line; `( … )` is an inline comment.
//! - An optional `N<digits>` line number and an optional `*<0..255>` checksum; when a checksum is
//!   present it must equal the XOR of every byte before the `*`.
//! - Letters are case-insensitive; words may be packed (`G1X10Y-3`); numbers are
//!   `[+-]digits[.digits]` with either side of the point optional (`E.4`, `X-3.`).
//! - Traditional commands are a letter and a number (`G1`, `M104`, `G01` = `G1`); Klipper-style
//!   extended commands are one identifier (`SET_VELOCITY_LIMIT ACCEL=1000`). Commands the planner
//!   does not interpret become [`Command::Other`] with their text untouched.
//!
//! No-panic contract: any byte sequence yields `Ok` or `Err` items, never a panic. An error
//! concerns one line; iteration goes on with the next line (read errors end it).
//!
//! Allocation: the reader reuses its line buffer (and one for lines with `( … )` comments), and
//! a well-formed line becomes a [`GcodeLine`] without touching the heap as long as a
//! [`Command::Other`]'s name fits [`CommandName`] (47 bytes) and its text [`CommandText`] (176
//! bytes) inline (longer ones are boxed). [`OtherParams`] borrows the command text. Errors
//! allocate (their message).

pub mod bed_screws;
pub mod exclude;
pub mod host;
pub mod macros;
pub mod respond;
mod text;

use std::fmt;
use std::fmt::Write as _;
use std::io::BufRead;

pub use text::{InlineText, TextBuilder};

/// A command name (`M104`, `SET_VELOCITY_LIMIT`): inline up to 47 bytes.
pub type CommandName = InlineText<47>;
/// A command's text as written: inline up to 176 bytes.
pub type CommandText = InlineText<176>;

/// Longest line accepted (Klipper's `EXCLUDE_OBJECT_DEFINE` polygons can be a few KB).
pub const MAX_LINE_LEN: usize = 1 << 20;
/// Characters of the offending line quoted in an error.
const QUOTE_LEN: usize = 120;

/// One parsed command and the 1-based number of the file line it came from.
#[derive(Debug, Clone, PartialEq)]
pub struct GcodeLine {
    pub line_no: usize,
    pub cmd: Command,
}

/// The commands the planner interprets; everything else well-formed is [`Command::Other`].
#[derive(Debug, Clone, PartialEq)]
pub enum Command {
    /// G0 / G1: coordinates in the current modal frame, feedrate in mm/min.
    Move {
        x: Option<f64>,
        y: Option<f64>,
        z: Option<f64>,
        e: Option<f64>,
        f: Option<f64>,
    },
    /// G2 (clockwise) / G3 (counter-clockwise) arc in the XY plane: end point like G1, centre
    /// offset `i`, `j` from the start point (the `R` form is not supported).
    Arc {
        clockwise: bool,
        x: Option<f64>,
        y: Option<f64>,
        z: Option<f64>,
        e: Option<f64>,
        f: Option<f64>,
        i: Option<f64>,
        j: Option<f64>,
    },
    /// G28: axes to home (no axis letter = all).
    Home { x: bool, y: bool, z: bool },
    /// G90.
    AbsolutePositioning,
    /// G91.
    RelativePositioning,
    /// G92: redefine the current position (no axis = all axes become 0).
    SetPosition {
        x: Option<f64>,
        y: Option<f64>,
        z: Option<f64>,
        e: Option<f64>,
    },
    /// M82.
    AbsoluteExtrusion,
    /// M83.
    RelativeExtrusion,
    /// G4 (`P` milliseconds or `S` seconds; `S` wins when both are given).
    Dwell { seconds: f64 },
    /// M400.
    WaitMoves,
    /// Any other well-formed command: `name` upper-cased (`M104`, `SET_VELOCITY_LIMIT`), `raw`
    /// the command text as written (without line number, checksum and comments).
    Other { name: CommandName, raw: CommandText },
}

/// What is wrong with a line.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GcodeErrorKind {
    #[error("bad number '{0}'")]
    BadNumber(String),
    #[error("number out of range '{0}'")]
    NotFinite(String),
    #[error("missing value in '{0}'")]
    MissingValue(String),
    #[error("bad word '{0}'")]
    BadWord(String),
    #[error("bad command '{0}'")]
    BadCommand(String),
    #[error("duplicate parameter '{0}'")]
    DuplicateParameter(char),
    #[error("negative value '{0}'")]
    Negative(String),
    #[error("checksum mismatch: line says {stated}, computed {computed}")]
    ChecksumMismatch { stated: u8, computed: u8 },
    #[error("malformed checksum '{0}'")]
    BadChecksum(String),
    #[error("unterminated '(' comment")]
    UnterminatedComment,
    #[error("not valid UTF-8")]
    NotUtf8,
    #[error("binary data (control character {0:#04x})")]
    Binary(u8),
    #[error("line longer than {MAX_LINE_LEN} bytes")]
    LineTooLong,
    #[error("read error: {0}")]
    Io(String),
}

/// A parse error: the file line, its text (shortened) and what is wrong.
#[derive(Debug, Clone, PartialEq)]
pub struct GcodeError {
    pub line: usize,
    pub text: String,
    pub kind: GcodeErrorKind,
}

impl fmt::Display for GcodeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.text.is_empty() {
            write!(f, "line {}: {}", self.line, self.kind)
        } else {
            write!(f, "line {}: {} in `{}`", self.line, self.kind, self.text)
        }
    }
}

impl std::error::Error for GcodeError {}

/// Iterator of parsed commands over a `BufRead`; blank and comment-only lines are skipped.
#[derive(Debug)]
pub struct GcodeReader<R> {
    inner: R,
    buf: Vec<u8>,
    /// Reused for lines with `( … )` comments (the text without them).
    scratch: String,
    line_no: usize,
    done: bool,
}

impl<R: BufRead> GcodeReader<R> {
    pub fn new(inner: R) -> Self {
        GcodeReader {
            inner,
            // Room for any realistic line up front: growing later would allocate mid-print.
            buf: Vec::with_capacity(4096),
            scratch: String::with_capacity(4096),
            line_no: 0,
            done: false,
        }
    }

    /// Number of the last line read (1-based; 0 before the first).
    pub fn line_no(&self) -> usize {
        self.line_no
    }

    /// Reads the next line into `self.buf` (without the `\n`), keeping at most `MAX_LINE_LEN`
    /// bytes. Returns `None` at end of input, else whether the line was too long.
    fn read_line(&mut self) -> std::io::Result<Option<bool>> {
        self.buf.clear();
        let mut any = false;
        let mut too_long = false;
        loop {
            let avail = match self.inner.fill_buf() {
                Ok(b) => b,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                Err(e) => return Err(e),
            };
            if avail.is_empty() {
                return Ok(any.then_some(too_long));
            }
            any = true;
            let (chunk, used, end) = match avail.iter().position(|&b| b == b'\n') {
                Some(i) => (&avail[..i], i + 1, true),
                None => (avail, avail.len(), false),
            };
            let room = MAX_LINE_LEN - self.buf.len();
            if chunk.len() > room {
                too_long = true;
            }
            self.buf.extend_from_slice(&chunk[..chunk.len().min(room)]);
            self.inner.consume(used);
            if end {
                return Ok(Some(too_long));
            }
        }
    }
}

impl<R: BufRead> Iterator for GcodeReader<R> {
    type Item = Result<GcodeLine, GcodeError>;

    fn next(&mut self) -> Option<Self::Item> {
        while !self.done {
            let too_long = match self.read_line() {
                Ok(Some(t)) => t,
                Ok(None) => {
                    self.done = true;
                    return None;
                }
                Err(e) => {
                    self.done = true;
                    let kind = GcodeErrorKind::Io(e.to_string());
                    return Some(Err(GcodeError {
                        line: self.line_no + 1,
                        text: String::new(),
                        kind,
                    }));
                }
            };
            self.line_no += 1;
            if too_long {
                return Some(Err(error(self.line_no, &self.buf, GcodeErrorKind::LineTooLong)));
            }
            match parse_line_with(self.line_no, &self.buf, &mut self.scratch) {
                Ok(Some(cmd)) => {
                    return Some(Ok(GcodeLine {
                        line_no: self.line_no,
                        cmd,
                    }))
                }
                Ok(None) => continue,
                Err(e) => return Some(Err(e)),
            }
        }
        None
    }
}

fn error(line: usize, raw: &[u8], kind: GcodeErrorKind) -> GcodeError {
    let s = String::from_utf8_lossy(raw);
    let t = s.trim();
    let text = match t.char_indices().nth(QUOTE_LEN) {
        Some((i, _)) => format!("{}…", &t[..i]),
        None => t.to_string(),
    };
    GcodeError { line, text, kind }
}

/// Parses one line (without its `\n`). `Ok(None)` for blank, comment-only or number-only lines.
pub fn parse_line(line_no: usize, raw: &[u8]) -> Result<Option<Command>, GcodeError> {
    parse_line_with(line_no, raw, &mut String::new())
}

/// [`parse_line`] with a reusable buffer for the text of lines with `( … )` comments.
fn parse_line_with(line_no: usize, raw: &[u8], scratch: &mut String) -> Result<Option<Command>, GcodeError> {
    let err = |kind| error(line_no, raw, kind);
    let text = std::str::from_utf8(raw).map_err(|_| err(GcodeErrorKind::NotUtf8))?;
    let text = text.strip_suffix('\r').unwrap_or(text);
    if let Some(&b) = text
        .as_bytes()
        .iter()
        .find(|&&b| (b < 0x20 && b != b'\t') || b == 0x7f)
    {
        return Err(err(GcodeErrorKind::Binary(b)));
    }
    let body = strip_comments_and_checksum(text, scratch).map_err(err)?;
    parse_body(body.trim()).map_err(err)
}

/// Removes the `;` comment, verifies and removes the `*NN` checksum, removes `( … )` comments
/// (then the text is built in `scratch`).
fn strip_comments_and_checksum<'a>(
    text: &'a str,
    scratch: &'a mut String,
) -> Result<&'a str, GcodeErrorKind> {
    let bytes = text.as_bytes();
    let mut depth_open = false;
    let mut has_paren = false;
    let mut end = bytes.len();
    let mut star = None;
    for (i, &b) in bytes.iter().enumerate() {
        match b {
            b'(' if !depth_open => {
                depth_open = true;
                has_paren = true;
            }
            b')' if depth_open => depth_open = false,
            b';' if !depth_open => {
                end = i;
                break;
            }
            b'*' if !depth_open && star.is_none() => star = Some(i),
            _ => {}
        }
    }
    if depth_open {
        return Err(GcodeErrorKind::UnterminatedComment);
    }
    let mut body_end = end;
    if let Some(s) = star {
        let digits = text[s + 1..end].trim();
        let stated = match digits.parse::<u8>() {
            Ok(v) if !digits.is_empty() && digits.bytes().all(|b| b.is_ascii_digit()) => v,
            _ => return Err(GcodeErrorKind::BadChecksum(text[s..end].trim().to_string())),
        };
        let computed = bytes[..s].iter().fold(0u8, |acc, &b| acc ^ b);
        if stated != computed {
            return Err(GcodeErrorKind::ChecksumMismatch { stated, computed });
        }
        body_end = s;
    }
    let body = &text[..body_end];
    if !has_paren {
        return Ok(body);
    }
    let out = scratch;
    out.clear();
    let mut open = false;
    for c in body.chars() {
        match c {
            '(' if !open => {
                open = true;
                out.push(' ');
            }
            ')' if open => open = false,
            _ if !open => out.push(c),
            _ => {}
        }
    }
    Ok(out.as_str())
}

/// Parses the command part of a line (comments, checksum removed; trimmed).
fn parse_body(body: &str) -> Result<Option<Command>, GcodeErrorKind> {
    let mut rest = body;
    // Line number.
    if let Some(after) = rest.strip_prefix(['N', 'n']) {
        if after.starts_with(|c: char| c.is_ascii_digit()) {
            let n = after.find(|c: char| !c.is_ascii_digit()).unwrap_or(after.len());
            let next = &after[n..];
            if !(next.is_empty()
                || next.starts_with(|c: char| c.is_ascii_whitespace() || c.is_ascii_alphabetic()))
            {
                return Err(GcodeErrorKind::BadWord(first_word(rest).to_string()));
            }
            rest = next.trim_start();
        }
    }
    if rest.is_empty() || rest == "%" {
        return Ok(None);
    }
    let first = rest.as_bytes()[0];
    if !first.is_ascii_alphabetic() {
        return Err(GcodeErrorKind::BadCommand(first_word(rest).to_string()));
    }
    let second = rest.as_bytes().get(1).copied();
    if !matches!(second, Some(b) if b.is_ascii_digit()) {
        return parse_extended(rest);
    }
    // Traditional command: letter + number.
    let num_len = rest[1..]
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .map_or(rest.len() - 1, |n| n);
    let num = &rest[1..1 + num_len];
    let (int_part, frac) = match num.split_once('.') {
        Some((i, f)) => (i, Some(f)),
        None => (num, None),
    };
    if int_part.is_empty()
        || frac.is_some_and(|f| f.is_empty() || !f.bytes().all(|b| b.is_ascii_digit()))
        || int_part.len() > 9
    {
        return Err(GcodeErrorKind::BadCommand(first_word(rest).to_string()));
    }
    let code: u32 = int_part
        .parse()
        .map_err(|_| GcodeErrorKind::BadCommand(first_word(rest).to_string()))?;
    let letter = first.to_ascii_uppercase();
    let params = &rest[1 + num_len..];
    let known = frac.is_none();
    let cmd = match (letter, code) {
        (b'G', 0 | 1) if known => {
            let p = Params::parse(params)?;
            Command::Move {
                x: p.value('X')?,
                y: p.value('Y')?,
                z: p.value('Z')?,
                e: p.value('E')?,
                f: p.value('F')?,
            }
        }
        (b'G', 2 | 3) if known => {
            let p = Params::parse(params)?;
            if p.has('R') {
                return Err(GcodeErrorKind::BadWord(
                    "R (radius arcs are not supported: use I/J)".to_string(),
                ));
            }
            Command::Arc {
                clockwise: code == 2,
                x: p.value('X')?,
                y: p.value('Y')?,
                z: p.value('Z')?,
                e: p.value('E')?,
                f: p.value('F')?,
                i: p.value('I')?,
                j: p.value('J')?,
            }
        }
        (b'G', 28) if known => {
            let p = Params::parse(params)?;
            let (x, y, z) = (p.has('X'), p.has('Y'), p.has('Z'));
            if !(x || y || z) {
                Command::Home {
                    x: true,
                    y: true,
                    z: true,
                }
            } else {
                Command::Home { x, y, z }
            }
        }
        (b'G', 90) if known => Command::AbsolutePositioning,
        (b'G', 91) if known => Command::RelativePositioning,
        (b'G', 92) if known => {
            let p = Params::parse(params)?;
            Command::SetPosition {
                x: p.value('X')?,
                y: p.value('Y')?,
                z: p.value('Z')?,
                e: p.value('E')?,
            }
        }
        (b'G', 4) if known => {
            let p = Params::parse(params)?;
            let seconds = match (p.value('S')?, p.value('P')?) {
                (Some(s), _) => p.non_negative('S', s)?,
                (None, Some(ms)) => p.non_negative('P', ms)? / 1000.0,
                (None, None) => 0.0,
            };
            Command::Dwell { seconds }
        }
        (b'M', 82) if known => Command::AbsoluteExtrusion,
        (b'M', 83) if known => Command::RelativeExtrusion,
        (b'M', 400) if known => Command::WaitMoves,
        _ => {
            let mut name = TextBuilder::new();
            // Writing to a TextBuilder cannot fail.
            let _ = write!(name, "{}{}", letter as char, code);
            if let Some(f) = frac {
                name.push_str(".");
                name.push_str(f);
            }
            Command::Other {
                name: name.finish(),
                raw: CommandText::new(rest),
            }
        }
    };
    Ok(Some(cmd))
}

/// A Klipper extended command: an identifier, then free-form `KEY=value` arguments.
fn parse_extended(rest: &str) -> Result<Option<Command>, GcodeErrorKind> {
    let name = first_word(rest);
    if !name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_') {
        return Err(GcodeErrorKind::BadCommand(name.to_string()));
    }
    let mut upper = CommandName::new(name);
    upper.make_ascii_uppercase();
    Ok(Some(Command::Other {
        name: upper,
        raw: CommandText::new(rest),
    }))
}

/// The parameters of an [`Command::Other`] command's `raw` text: `S200 T0` words for
/// traditional commands, `KEY=value` for extended ones (keys compared upper-cased). Borrows the
/// text and allocates nothing: [`Self::parse`] checks every word, lookups scan the text again
/// (commands have a handful of parameters). A key given twice: the first one counts.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct OtherParams<'a> {
    /// A traditional command's words by letter (`S215`).
    words: [Option<&'a str>; 26],
    /// An extended command's text after the name (`KEY=value …`, already checked).
    extended: Option<&'a str>,
}

/// The one-letter keys of traditional commands.
const LETTERS: [&str; 26] = [
    "A", "B", "C", "D", "E", "F", "G", "H", "I", "J", "K", "L", "M", "N", "O", "P", "Q", "R", "S", "T", "U",
    "V", "W", "X", "Y", "Z",
];

impl<'a> OtherParams<'a> {
    /// Parses `raw` (as in [`Command::Other`]); the command word itself is skipped.
    pub fn parse(raw: &'a str) -> Result<OtherParams<'a>, GcodeErrorKind> {
        let raw = raw.trim();
        let name = first_word(raw);
        let rest = &raw[name.len()..];
        let extended = !name.as_bytes().get(1).is_some_and(|b| b.is_ascii_digit());
        let mut params = OtherParams {
            words: [None; 26],
            extended: None,
        };
        if extended {
            for tok in extended_words(rest) {
                let Some((k, _)) = tok.split_once('=') else {
                    return Err(GcodeErrorKind::BadWord(tok.to_string()));
                };
                if k.is_empty() || !k.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_') {
                    return Err(GcodeErrorKind::BadWord(tok.to_string()));
                }
            }
            params.extended = Some(rest);
        } else {
            params.words = Params::parse(rest)?.words;
        }
        Ok(params)
    }

    /// The text of `key` (upper case, as the keys are compared).
    pub fn get(&self, key: &str) -> Option<&'a str> {
        match self.extended {
            None => {
                let i = LETTERS.iter().position(|&l| l == key)?;
                self.words[i].map(|w| &w[1..])
            }
            Some(rest) => extended_words(rest)
                .filter_map(|tok| tok.split_once('='))
                .find(|(k, _)| upper_eq(k, key))
                .map(|(_, v)| unquote(v)),
        }
    }

    /// The number of `key` (finite), `None` when absent.
    pub fn float(&self, key: &str) -> Result<Option<f64>, GcodeErrorKind> {
        let Some(v) = self.get(key) else {
            return Ok(None);
        };
        let x: f64 = v
            .trim()
            .parse()
            .map_err(|_| GcodeErrorKind::BadNumber(format!("{key}={v}")))?;
        if !x.is_finite() {
            return Err(GcodeErrorKind::NotFinite(format!("{key}={v}")));
        }
        Ok(Some(x))
    }

    /// Every key given, upper-cased (extended keys written in lower case are copied, inline).
    pub fn keys(&self) -> impl Iterator<Item = CommandName> + '_ {
        let letters = self
            .words
            .iter()
            .zip(LETTERS)
            .filter(|(w, _)| w.is_some())
            .map(|(_, l)| CommandName::new(l));
        let extended = self.extended.into_iter().flat_map(|rest| {
            extended_words(rest)
                .filter_map(|tok| tok.split_once('='))
                .map(|(k, _)| {
                    let mut k = CommandName::new(k);
                    k.make_ascii_uppercase();
                    k
                })
        });
        letters.chain(extended)
    }
}

/// The `KEY=value` words of an extended command: split at whitespace outside double quotes, as
/// Klipper's shell-style parsing does (`MSG="two words"` is one word).
fn extended_words(rest: &str) -> impl Iterator<Item = &str> {
    let mut left = rest;
    std::iter::from_fn(move || {
        left = left.trim_start_matches(|c: char| c.is_ascii_whitespace());
        if left.is_empty() {
            return None;
        }
        let mut quoted = false;
        let end = left
            .char_indices()
            .find(|&(_, c)| {
                if c == '"' {
                    quoted = !quoted;
                }
                c.is_ascii_whitespace() && !quoted
            })
            .map_or(left.len(), |(i, _)| i);
        let (word, next) = left.split_at(end);
        left = next;
        Some(word)
    })
}

/// A value without the double quotes around it (`"two words"` → `two words`).
fn unquote(v: &str) -> &str {
    v.strip_prefix('"').and_then(|v| v.strip_suffix('"')).unwrap_or(v)
}

/// Whether `k` upper-cased equals `key`.
fn upper_eq(k: &str, key: &str) -> bool {
    k.len() == key.len()
        && k.bytes()
            .zip(key.bytes())
            .all(|(a, b)| a.to_ascii_uppercase() == b)
}

fn first_word(s: &str) -> &str {
    s.split(|c: char| c.is_ascii_whitespace()).next().unwrap_or(s)
}

/// Parameters of a traditional command: at most one per letter; the word text is kept for
/// error messages, its number as parsed when the syntax was checked (not parsed again).
struct Params<'a> {
    words: [Option<&'a str>; 26],
    /// The number of each word that has one (0 for none).
    values: [f64; 26],
}

impl<'a> Params<'a> {
    fn parse(s: &'a str) -> Result<Params<'a>, GcodeErrorKind> {
        let mut words = [None; 26];
        let mut values = [0.0; 26];
        let bytes = s.as_bytes();
        let mut i = 0;
        while i < bytes.len() {
            let b = bytes[i];
            if b.is_ascii_whitespace() {
                i += 1;
                continue;
            }
            let start = i;
            i += 1;
            while i < bytes.len() && !bytes[i].is_ascii_whitespace() && !bytes[i].is_ascii_alphabetic() {
                i += 1;
            }
            // `start` and `i` sit on ASCII bytes (or the end), so slicing is on char boundaries.
            let word = &s[start..i];
            if !b.is_ascii_alphabetic() {
                let end = s[start..]
                    .find(|c: char| c.is_ascii_whitespace())
                    .map_or(s.len(), |n| start + n);
                return Err(GcodeErrorKind::BadWord(s[start..end].to_string()));
            }
            let idx = (b.to_ascii_uppercase() - b'A') as usize;
            let slot = &mut words[idx];
            if slot.is_some() {
                return Err(GcodeErrorKind::DuplicateParameter(b.to_ascii_uppercase() as char));
            }
            // Empty is allowed here (`G28 X`); `value` refuses it where a number is needed.
            if word.len() > 1 {
                values[idx] = number(word)?;
            }
            *slot = Some(word);
        }
        Ok(Params { words, values })
    }

    fn word(&self, letter: char) -> Option<&'a str> {
        self.words
            .get((letter as u8).wrapping_sub(b'A') as usize)
            .copied()
            .flatten()
    }

    fn has(&self, letter: char) -> bool {
        self.word(letter).is_some()
    }

    /// The value of `letter`, which must have one if present.
    fn value(&self, letter: char) -> Result<Option<f64>, GcodeErrorKind> {
        match self.word(letter) {
            None => Ok(None),
            Some(w) if w.len() == 1 => Err(GcodeErrorKind::MissingValue(w.to_string())),
            Some(_) => Ok(self
                .values
                .get((letter as u8).wrapping_sub(b'A') as usize)
                .copied()),
        }
    }

    fn non_negative(&self, letter: char, v: f64) -> Result<f64, GcodeErrorKind> {
        if v < 0.0 {
            return Err(GcodeErrorKind::Negative(
                self.word(letter).unwrap_or_default().to_string(),
            ));
        }
        Ok(v)
    }
}

/// The number of a word `L<number>`: `[+-]digits[.digits]`, at least one digit, finite.
///
/// Fast path (Clinger's): with at most 15 significant digits and 22 decimals, the digits form
/// an exact integer m < 2^53 and 10^d is exact, so m / 10^d is one correctly rounded division:
/// the same value `str::parse` gives (a test compares them), several times cheaper. Longer
/// numbers go through `str::parse`.
fn number(word: &str) -> Result<f64, GcodeErrorKind> {
    const POW10: [f64; 23] = [
        1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14, 1e15, 1e16, 1e17,
        1e18, 1e19, 1e20, 1e21, 1e22,
    ];
    let text = &word[1..];
    let negative = text.starts_with('-');
    let unsigned = text.strip_prefix(['+', '-']).unwrap_or(text);
    let mut digits = 0usize;
    let mut points = 0;
    let mut decimals = 0usize;
    let mut mantissa: u64 = 0;
    for b in unsigned.bytes() {
        match b {
            b'0'..=b'9' => {
                digits += 1;
                decimals += points;
                mantissa = mantissa.wrapping_mul(10).wrapping_add(u64::from(b - b'0'));
            }
            b'.' => points += 1,
            _ => return Err(GcodeErrorKind::BadNumber(word.to_string())),
        }
    }
    if digits == 0 || points > 1 {
        return Err(GcodeErrorKind::BadNumber(word.to_string()));
    }
    if digits <= 15 && decimals < POW10.len() {
        let v = mantissa as f64 / POW10[decimals];
        return Ok(if negative { -v } else { v });
    }
    let v: f64 = text
        .parse()
        .map_err(|_| GcodeErrorKind::BadNumber(word.to_string()))?;
    if !v.is_finite() {
        return Err(GcodeErrorKind::NotFinite(word.to_string()));
    }
    Ok(v)
}

impl fmt::Display for Command {
    /// G-code text that parses back to the same command.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fn opt(f: &mut fmt::Formatter<'_>, letter: char, v: Option<f64>) -> fmt::Result {
            match v {
                Some(v) => write!(f, " {letter}{v}"),
                None => Ok(()),
            }
        }
        match self {
            Command::Move { x, y, z, e, f: feed } => {
                write!(f, "G1")?;
                opt(f, 'X', *x)?;
                opt(f, 'Y', *y)?;
                opt(f, 'Z', *z)?;
                opt(f, 'E', *e)?;
                opt(f, 'F', *feed)
            }
            Command::Arc {
                clockwise,
                x,
                y,
                z,
                e,
                f: feed,
                i,
                j,
            } => {
                write!(f, "{}", if *clockwise { "G2" } else { "G3" })?;
                for (l, v) in [
                    ('X', x),
                    ('Y', y),
                    ('Z', z),
                    ('E', e),
                    ('F', feed),
                    ('I', i),
                    ('J', j),
                ] {
                    opt(f, l, *v)?;
                }
                Ok(())
            }
            Command::Home { x, y, z } => {
                write!(f, "G28")?;
                for (on, l) in [(x, 'X'), (y, 'Y'), (z, 'Z')] {
                    if *on && !(*x && *y && *z) {
                        write!(f, " {l}")?;
                    }
                }
                Ok(())
            }
            Command::AbsolutePositioning => write!(f, "G90"),
            Command::RelativePositioning => write!(f, "G91"),
            Command::SetPosition { x, y, z, e } => {
                write!(f, "G92")?;
                opt(f, 'X', *x)?;
                opt(f, 'Y', *y)?;
                opt(f, 'Z', *z)?;
                opt(f, 'E', *e)
            }
            Command::AbsoluteExtrusion => write!(f, "M82"),
            Command::RelativeExtrusion => write!(f, "M83"),
            Command::Dwell { seconds } => write!(f, "G4 S{seconds}"),
            Command::WaitMoves => write!(f, "M400"),
            Command::Other { raw, .. } => write!(f, "{raw}"),
        }
    }
}

#[cfg(test)]
mod tests;
