//! Decoding block payloads into named messages.
//!
//! A payload is a run of messages, each a VLQ id followed by its parameters as the dictionary's
//! format for that id says. Decoding allocates (names and fields are owned), so the IO thread
//! only uses it for rare responses; hot paths use [`Dictionary::peek_id`] and
//! [`crate::proto::format::decode_params`] on the stack.

use std::fmt;

use super::{output_specs, DictError, Dictionary, MsgDef, MsgKind, OUTPUT_NAME};
use crate::proto::format::{ParamType, Value};
use crate::proto::vlq;

/// A decoded parameter value.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum FieldValue {
    /// Any integer type, masked or sign-extended as the type says.
    Int(i64),
    /// A string or buffer.
    Bytes(Vec<u8>),
}

impl fmt::Display for FieldValue {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            FieldValue::Int(v) => write!(f, "{v}"),
            FieldValue::Bytes(b) => write!(f, "\"{}\"", b.escape_ascii()),
        }
    }
}

/// One decoded message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Message {
    /// The message name (`#output` for debug output).
    pub name: String,
    /// Parameters in wire order.
    pub fields: Vec<(String, FieldValue)>,
}

impl Message {
    /// The integer field `field`.
    pub fn get(&self, field: &str) -> Option<i64> {
        self.fields.iter().find_map(|(n, v)| match v {
            FieldValue::Int(i) if n == field => Some(*i),
            _ => None,
        })
    }

    /// The byte field `field`.
    pub fn bytes(&self, field: &str) -> Option<&[u8]> {
        self.fields.iter().find_map(|(n, v)| match v {
            FieldValue::Bytes(b) if n == field => Some(b.as_slice()),
            _ => None,
        })
    }
}

/// `name a=1 b="x\n"`; output messages show their formatted text.
impl fmt::Display for Message {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.name)?;
        if self.name == OUTPUT_NAME {
            if let Some(text) = self.bytes("text") {
                return write!(f, " {}", text.escape_ascii());
            }
        }
        for (n, v) in &self.fields {
            write!(f, " {n}={v}")?;
        }
        Ok(())
    }
}

impl Dictionary {
    /// The id at the front of `data` and the bytes it takes (no allocation).
    pub fn peek_id(data: &[u8]) -> Option<(u32, usize)> {
        vlq::decode(data)
    }

    /// Decodes the message at the front of `data`: the message and the bytes it used.
    pub fn decode_one(&self, data: &[u8]) -> Result<(Message, usize), DictError> {
        let (id, used) = vlq::decode(data).ok_or_else(|| DictError::Truncated("<id>".into()))?;
        let (kind, def) = self.message_by_id(id).ok_or(DictError::UnknownId(id))?;
        let (fields, n) = decode_fields(def, &data[used..])?;
        let msg = if kind == MsgKind::Output {
            Message {
                name: OUTPUT_NAME.to_owned(),
                fields: vec![(
                    "text".to_owned(),
                    FieldValue::Bytes(render_output(&def.format, &fields)),
                )],
            }
        } else {
            Message {
                name: def.name.clone(),
                fields,
            }
        };
        Ok((msg, used + n))
    }

    /// Splits a block payload into its messages (commands, responses or output).
    pub fn decode(&self, payload: &[u8]) -> Result<Vec<Message>, DictError> {
        self.decode_filtered(payload, false)
    }

    /// Like [`Self::decode`], but every message must be a command (host → MCU traffic).
    pub fn decode_command(&self, payload: &[u8]) -> Result<Vec<Message>, DictError> {
        self.decode_filtered(payload, true)
    }

    fn decode_filtered(&self, payload: &[u8], commands_only: bool) -> Result<Vec<Message>, DictError> {
        let mut out = Vec::new();
        let mut rest = payload;
        while !rest.is_empty() {
            if commands_only {
                let (id, _) = vlq::decode(rest).ok_or_else(|| DictError::Truncated("<id>".into()))?;
                match self.message_by_id(id) {
                    Some((MsgKind::Command, _)) => {}
                    Some((_, def)) => return Err(DictError::NotACommand(id, def.name.clone())),
                    None => return Err(DictError::UnknownId(id)),
                }
            }
            let (msg, used) = self.decode_one(rest)?;
            out.push(msg);
            rest = &rest[used..];
        }
        Ok(out)
    }
}

fn decode_fields(def: &MsgDef, data: &[u8]) -> Result<(Vec<(String, FieldValue)>, usize), DictError> {
    let truncated = || DictError::Truncated(def.name.clone());
    let mut fields = Vec::with_capacity(def.params.len());
    let mut pos = 0;
    for (name, ty) in &def.params {
        let rest = data.get(pos..).ok_or_else(truncated)?;
        let value = if ty.is_bytes() {
            let n = *rest.first().ok_or_else(truncated)? as usize;
            pos += 1 + n;
            FieldValue::Bytes(rest.get(1..1 + n).ok_or_else(truncated)?.to_vec())
        } else {
            let (raw, used) = vlq::decode(rest).ok_or_else(truncated)?;
            pos += used;
            FieldValue::Int(ty.from_raw(raw))
        };
        fields.push((name.clone(), value));
    }
    Ok((fields, pos))
}

/// Substitutes decoded values into a printf-style output format.
fn render_output(format: &str, fields: &[(String, FieldValue)]) -> Vec<u8> {
    let mut out = Vec::with_capacity(format.len() + 16);
    let mut last = 0;
    let mut values = fields.iter();
    for ((start, end), _) in output_specs(format) {
        out.extend_from_slice(&format.as_bytes()[last..start]);
        match values.next() {
            Some((_, FieldValue::Int(v))) => out.extend_from_slice(v.to_string().as_bytes()),
            Some((_, FieldValue::Bytes(b))) => out.extend_from_slice(b),
            None => out.extend_from_slice(&format.as_bytes()[start..end]),
        }
        last = end;
    }
    out.extend_from_slice(&format.as_bytes()[last..]);
    out
}

/// Decodes the parameters of a message with a known definition into a stack array: the
/// allocation-free path for hot responses (`clock`, `stats`). Returns the parameter count and
/// the bytes used after the id.
pub fn decode_params_into<'d>(
    def_params: &[(String, ParamType)],
    data: &'d [u8],
    out: &mut [Value<'d>],
) -> Option<(usize, usize)> {
    let mut pos = 0;
    for (i, (_, ty)) in def_params.iter().enumerate() {
        let rest = data.get(pos..)?;
        let slot = out.get_mut(i)?;
        if ty.is_bytes() {
            let n = *rest.first()? as usize;
            *slot = Value::Bytes(rest.get(1..1 + n)?);
            pos += 1 + n;
        } else {
            let (raw, used) = vlq::decode(rest)?;
            *slot = Value::Int(ty.from_raw(raw));
            pos += used;
        }
    }
    Some((def_params.len(), pos))
}

#[cfg(test)]
mod tests {
    use super::super::tests::test_dict;
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn decode_several_messages() {
        let d = test_dict();
        let mut payload = Vec::new();
        payload.extend_from_slice(d.encode("queue_step", &[2, 40_000, 20, -3]).unwrap().as_bytes());
        payload.extend_from_slice(d.encode("set_next_step_dir", &[2, 1]).unwrap().as_bytes());
        let msgs = d.decode(&payload).unwrap();
        assert_eq!(msgs.len(), 2);
        assert_eq!(
            msgs[0].to_string(),
            "queue_step oid=2 interval=40000 count=20 add=-3"
        );
        assert_eq!(msgs[0].get("add"), Some(-3));
        assert_eq!(msgs[1].to_string(), "set_next_step_dir oid=2 dir=1");
        assert_eq!(d.decode_command(&payload).unwrap(), msgs);
    }

    #[test]
    fn decode_responses_and_output() {
        let d = test_dict();
        // identify_response offset=40 data="a\n"
        let msgs = d.decode(&[0, 40, 2, b'a', b'\n']).unwrap();
        assert_eq!(msgs[0].bytes("data"), Some(&b"a\n"[..]));
        assert_eq!(msgs[0].to_string(), "identify_response offset=40 data=\"a\\n\"");
        // stepper_position oid=1 pos=-5
        let msgs = d.decode(&[86, 1, 0x7B]).unwrap();
        assert_eq!(msgs[0].get("pos"), Some(-5));
        // output "Got %u bytes: %.*s"
        let msgs = d.decode(&[90, 3, 3, b'a', b'b', b'c']).unwrap();
        assert_eq!(msgs[0].to_string(), "#output Got 3 bytes: abc");
        assert!(matches!(
            d.decode_command(&[86, 1, 0]),
            Err(DictError::NotACommand(86, _))
        ));
    }

    #[test]
    fn decode_errors() {
        let d = test_dict();
        assert!(matches!(d.decode(&[200, 1]), Err(DictError::UnknownId(_))));
        assert!(matches!(d.decode(&[20, 1, 0x82]), Err(DictError::Truncated(_))));
        assert!(matches!(d.decode(&[0, 1, 5, b'a']), Err(DictError::Truncated(_))));
        assert_eq!(d.decode(&[]).unwrap(), vec![]);
    }

    #[test]
    fn params_on_the_stack() {
        let d = test_dict();
        let def = d.response("uptime").unwrap();
        let mut vals = [Value::Int(0); 4];
        let (n, used) = decode_params_into(&def.params, &[1, 0x82, 0xB8, 0x40], &mut vals).unwrap();
        assert_eq!((n, used), (2, 4));
        assert_eq!(vals[1], Value::Int(40_000));
        assert!(decode_params_into(&def.params, &[1], &mut vals).is_none());
    }

    proptest! {
        #[test]
        fn decode_never_panics(data in proptest::collection::vec(any::<u8>(), 0..64)) {
            let d = test_dict();
            let _ = d.decode(&data);
            let _ = d.decode_command(&data);
            let mut vals = [Value::Int(0); 8];
            let _ = decode_params_into(&d.response("config").unwrap().params, &data, &mut vals);
        }

        #[test]
        fn encode_decode_round_trip(oid in 0i64..256, interval in 0i64..(1 << 32), count in 0i64..65536, add in -32768i64..32768) {
            let d = test_dict();
            let cmd = d.encode("queue_step", &[oid, interval, count, add]).unwrap();
            let msgs = d.decode(cmd.as_bytes()).unwrap();
            prop_assert_eq!(msgs.len(), 1);
            prop_assert_eq!(msgs[0].get("oid"), Some(oid));
            prop_assert_eq!(msgs[0].get("interval"), Some(interval));
            prop_assert_eq!(msgs[0].get("count"), Some(count));
            prop_assert_eq!(msgs[0].get("add"), Some(add));
        }
    }
}
