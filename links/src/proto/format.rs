//! Message format strings (`"queue_step oid=%c interval=%u count=%hu add=%hi"`) and the
//! encoding of a message's parameters after its VLQ id.
//!
//! Integer types (`%u %i %hu %hi %c`) travel as VLQ; `%s`, `%.*s` and `%*s` as one length byte
//! followed by raw bytes. Decoded unsigned values are masked to their width, signed ones are
//! sign-extended, so a [`Value::Int`] always holds what the sender meant.

use super::vlq;

/// One parameter's wire type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ParamType {
    /// `%u`: 32-bit unsigned.
    U32,
    /// `%i`: 32-bit signed.
    I32,
    /// `%hu`: 16-bit unsigned.
    U16,
    /// `%hi`: 16-bit signed.
    I16,
    /// `%c`: 8-bit unsigned.
    Byte,
    /// `%s`: a string.
    Str,
    /// `%.*s` / `%*s`: a byte buffer.
    Buffer,
}

impl ParamType {
    /// Parses a `%…` conversion.
    pub fn parse(spec: &str) -> Option<ParamType> {
        Some(match spec {
            "%u" => ParamType::U32,
            "%i" => ParamType::I32,
            "%hu" => ParamType::U16,
            "%hi" => ParamType::I16,
            "%c" => ParamType::Byte,
            "%s" => ParamType::Str,
            "%.*s" | "%*s" => ParamType::Buffer,
            _ => return None,
        })
    }

    /// True for the length-prefixed byte types.
    pub const fn is_bytes(self) -> bool {
        matches!(self, ParamType::Str | ParamType::Buffer)
    }

    /// Reads the raw 32-bit VLQ value as this type means it.
    pub const fn from_raw(self, raw: u32) -> i64 {
        match self {
            ParamType::U32 => raw as i64,
            ParamType::I32 => raw as i32 as i64,
            ParamType::U16 => (raw & 0xFFFF) as i64,
            ParamType::I16 => raw as i16 as i64,
            ParamType::Byte => (raw & 0xFF) as i64,
            ParamType::Str | ParamType::Buffer => raw as i64,
        }
    }
}

/// A parameter value.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Value<'a> {
    /// Any integer type, already masked or sign-extended.
    Int(i64),
    /// A string or buffer.
    Bytes(&'a [u8]),
}

impl Value<'_> {
    /// The integer, or 0 for bytes.
    pub fn int(&self) -> i64 {
        match *self {
            Value::Int(v) => v,
            Value::Bytes(_) => 0,
        }
    }
}

/// Errors of format parsing, encoding and decoding.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FormatError {
    /// A parameter is not `name=%x` with a known conversion.
    BadFormat,
    /// Fewer or more values than the format has parameters, or an int where bytes belong.
    ArgMismatch,
    /// The output buffer is full.
    NoSpace,
    /// The input ended inside a parameter.
    Truncated,
    /// A byte parameter longer than 255 bytes.
    TooLong,
}

impl core::fmt::Display for FormatError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            FormatError::BadFormat => "bad message format string",
            FormatError::ArgMismatch => "arguments do not match the message format",
            FormatError::NoSpace => "message does not fit its buffer",
            FormatError::Truncated => "message ends inside a parameter",
            FormatError::TooLong => "byte parameter longer than 255 bytes",
        })
    }
}

/// The message name: the format string's first word.
pub fn message_name(format: &str) -> &str {
    format.split(' ').next().unwrap_or("")
}

/// Iterator over a format string's parameters as `(name, type)`.
#[derive(Debug, Clone)]
pub struct Params<'a> {
    rest: core::str::SplitAsciiWhitespace<'a>,
}

impl<'a> Params<'a> {
    /// The parameters of `format` (its first word, the name, is skipped).
    pub fn of(format: &'a str) -> Params<'a> {
        let mut rest = format.split_ascii_whitespace();
        rest.next();
        Params { rest }
    }
}

impl<'a> Iterator for Params<'a> {
    type Item = Result<(&'a str, ParamType), FormatError>;
    fn next(&mut self) -> Option<Self::Item> {
        let tok = self.rest.next()?;
        Some(match tok.split_once('=') {
            Some((name, spec)) if !name.is_empty() => ParamType::parse(spec)
                .map(|t| (name, t))
                .ok_or(FormatError::BadFormat),
            _ => Err(FormatError::BadFormat),
        })
    }
}

/// Writes message `id` with `args` (in the order of `format`'s parameters) into `out`.
/// Returns the bytes written.
pub fn encode_message(
    id: u32,
    format: &str,
    args: &[Value<'_>],
    out: &mut [u8],
) -> Result<usize, FormatError> {
    let mut pos = vlq::encode(id, out).ok_or(FormatError::NoSpace)?;
    let mut args_iter = args.iter();
    for param in Params::of(format) {
        let (_, ty) = param?;
        let arg = args_iter.next().ok_or(FormatError::ArgMismatch)?;
        match (ty.is_bytes(), arg) {
            (false, Value::Int(v)) => {
                let dst = out.get_mut(pos..).ok_or(FormatError::NoSpace)?;
                pos += vlq::encode(*v as u32, dst).ok_or(FormatError::NoSpace)?;
            }
            (true, Value::Bytes(b)) => {
                let n = u8::try_from(b.len()).map_err(|_| FormatError::TooLong)?;
                let dst = out.get_mut(pos..pos + 1 + b.len()).ok_or(FormatError::NoSpace)?;
                dst[0] = n;
                dst[1..].copy_from_slice(b);
                pos += 1 + b.len();
            }
            _ => return Err(FormatError::ArgMismatch),
        }
    }
    if args_iter.next().is_some() {
        return Err(FormatError::ArgMismatch);
    }
    Ok(pos)
}

/// Decodes the parameters of one message of `format` from `data` (which starts right after
/// the message id) into `out`. Returns `(parameter count, bytes consumed)`.
pub fn decode_params<'d>(
    format: &str,
    data: &'d [u8],
    out: &mut [Value<'d>],
) -> Result<(usize, usize), FormatError> {
    let mut pos = 0;
    let mut count = 0;
    for param in Params::of(format) {
        let (_, ty) = param?;
        let slot = out.get_mut(count).ok_or(FormatError::NoSpace)?;
        let rest = data.get(pos..).ok_or(FormatError::Truncated)?;
        if ty.is_bytes() {
            let n = *rest.first().ok_or(FormatError::Truncated)? as usize;
            let bytes = rest.get(1..1 + n).ok_or(FormatError::Truncated)?;
            *slot = Value::Bytes(bytes);
            pos += 1 + n;
        } else {
            let (raw, used) = vlq::decode(rest).ok_or(FormatError::Truncated)?;
            *slot = Value::Int(ty.from_raw(raw));
            pos += used;
        }
        count += 1;
    }
    Ok((count, pos))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const QUEUE_STEP: &str = "queue_step oid=%c interval=%u count=%hu add=%hi";

    #[test]
    fn queue_step_golden_bytes() {
        let mut out = [0u8; 64];
        let args = [Value::Int(2), Value::Int(40_000), Value::Int(20), Value::Int(-3)];
        let n = encode_message(17, QUEUE_STEP, &args, &mut out).unwrap();
        assert_eq!(&out[..n], &[0x11, 0x02, 0x82, 0xB8, 0x40, 0x14, 0x7D]);
        let mut vals = [Value::Int(0); 8];
        let (cnt, used) = decode_params(QUEUE_STEP, &out[1..n], &mut vals).unwrap();
        assert_eq!((cnt, used), (4, n - 1));
        assert_eq!(&vals[..4], &args);
    }

    #[test]
    fn names_and_params() {
        assert_eq!(message_name(QUEUE_STEP), "queue_step");
        let p: Result<heapless_vec::V, _> = Params::of(QUEUE_STEP).collect();
        assert_eq!(p.unwrap().0, 4);
        assert!(Params::of("x a=%q").any(|r| r.is_err()));
        assert!(Params::of("x =%u").any(|r| r.is_err()));
    }

    /// A tiny counter so the test needs no allocation.
    mod heapless_vec {
        pub struct V(pub usize);
        impl<'a> FromIterator<(&'a str, super::ParamType)> for V {
            fn from_iter<I: IntoIterator<Item = (&'a str, super::ParamType)>>(i: I) -> Self {
                V(i.into_iter().count())
            }
        }
    }

    #[test]
    fn bytes_and_mismatch() {
        let fmt = "identify_response offset=%u data=%.*s";
        let mut out = [0u8; 64];
        let n = encode_message(0, fmt, &[Value::Int(40), Value::Bytes(b"abc")], &mut out).unwrap();
        assert_eq!(&out[..n], &[0x00, 0x28, 0x03, b'a', b'b', b'c']);
        assert_eq!(
            encode_message(0, fmt, &[Value::Int(40)], &mut out),
            Err(FormatError::ArgMismatch)
        );
        assert_eq!(
            encode_message(0, fmt, &[Value::Int(1), Value::Int(2)], &mut out),
            Err(FormatError::ArgMismatch)
        );
        let mut vals = [Value::Int(0); 2];
        assert_eq!(
            decode_params(fmt, &[0x28, 0x05, b'a'], &mut vals),
            Err(FormatError::Truncated)
        );
    }

    proptest! {
        #[test]
        fn round_trip(oid in any::<u8>(), interval in any::<u32>(), count in any::<u16>(), add in any::<i16>()) {
            let args = [Value::Int(oid as i64), Value::Int(interval as i64), Value::Int(count as i64), Value::Int(add as i64)];
            let mut out = [0u8; 64];
            let n = encode_message(300, QUEUE_STEP, &args, &mut out).unwrap();
            let (id, used) = vlq::decode(&out[..n]).unwrap();
            prop_assert_eq!(id, 300);
            let mut vals = [Value::Int(0); 4];
            let (cnt, used2) = decode_params(QUEUE_STEP, &out[used..n], &mut vals).unwrap();
            prop_assert_eq!(cnt, 4);
            prop_assert_eq!(used + used2, n);
            prop_assert_eq!(&vals[..], &args[..]);
        }

        #[test]
        fn decode_never_panics(data in proptest::collection::vec(any::<u8>(), 0..40)) {
            let mut vals = [Value::Int(0); 8];
            let _ = decode_params(QUEUE_STEP, &data, &mut vals);
            let _ = decode_params("identify_response offset=%u data=%.*s", &data, &mut vals);
        }
    }
}
