//! Encoding commands by name into [`Cmd`], a fixed-size, `Copy`, allocation-free message.
//!
//! A message is its VLQ id followed by its parameters (see [`crate::proto::format`]); one
//! message must fit a block's payload (59 bytes). Integers are range-checked against their wire
//! type, accepting both the signed and the unsigned reading (`%u` takes `-2^31 ..= 2^32-1`),
//! so a planner bug shows up as an error instead of a silently truncated value.

use std::sync::Arc;

use super::{DictError, Dictionary, MsgDef};
use crate::proto::format::{encode_message, FormatError, ParamType, Value};
use crate::proto::{vlq, MESSAGE_PAYLOAD_MAX};

/// One encoded message (id and parameters), ready to be packed into a block.
#[derive(Clone, Copy, PartialEq, Eq)]
pub struct Cmd {
    len: u8,
    data: [u8; MESSAGE_PAYLOAD_MAX],
}

impl Cmd {
    /// The encoded bytes.
    pub fn as_bytes(&self) -> &[u8] {
        &self.data[..self.len as usize]
    }

    /// Number of encoded bytes.
    pub fn len(&self) -> usize {
        self.len as usize
    }

    /// True for an empty message (never produced by the encoders).
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Wraps already-encoded bytes; `None` if longer than one block's payload.
    pub fn from_bytes(bytes: &[u8]) -> Option<Cmd> {
        let mut cmd = Cmd {
            len: u8::try_from(bytes.len()).ok()?,
            data: [0; MESSAGE_PAYLOAD_MAX],
        };
        cmd.data.get_mut(..bytes.len())?.copy_from_slice(bytes);
        Some(cmd)
    }
}

impl std::fmt::Debug for Cmd {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Cmd({:02x?})", self.as_bytes())
    }
}

/// Most integer parameters a [`CmdEncoder`] handles (Klipper's largest command has 11).
pub const MAX_INT_PARAMS: usize = 16;

/// A command's id and parameter types looked up once, for encoding on a hot path without a
/// dictionary lookup or allocation (only the error path allocates).
#[derive(Debug, Clone)]
pub struct CmdEncoder {
    id: u32,
    types: [ParamType; MAX_INT_PARAMS],
    count: usize,
    def: Arc<MsgDef>,
}

impl CmdEncoder {
    /// The command's wire id.
    pub fn id(&self) -> u32 {
        self.id
    }

    /// Encodes the command with integer `args` in format order.
    pub fn encode(&self, args: &[i64]) -> Result<Cmd, DictError> {
        if args.len() != self.count {
            return Err(DictError::ArgCount {
                name: self.def.name.clone(),
                expected: self.count,
                got: args.len(),
            });
        }
        let mut cmd = Cmd {
            len: 0,
            data: [0; MESSAGE_PAYLOAD_MAX],
        };
        let too_long = || DictError::TooLong(self.def.name.clone());
        let mut pos = vlq::encode(self.id, &mut cmd.data).ok_or_else(too_long)?;
        for (i, (&ty, &v)) in self.types[..self.count].iter().zip(args).enumerate() {
            if !fits(ty, v) {
                return Err(DictError::OutOfRange {
                    name: self.def.name.clone(),
                    param: self.def.params[i].0.clone(),
                    value: v,
                });
            }
            let dst = cmd.data.get_mut(pos..).ok_or_else(too_long)?;
            pos += vlq::encode(v as u32, dst).ok_or_else(too_long)?;
        }
        cmd.len = pos as u8;
        Ok(cmd)
    }
}

/// True when `v` fits the wire type read either signed or unsigned.
///
/// `%c` is the exception: Klipper sends it as an ordinary VLQ sized for at most 2 bytes, and
/// its MCUs read a full 32-bit argument, so `%c` parameters such as pins carry values above 255
/// (a Linux-process MCU's `gpiochip1/gpio0` is pin 256). Accepted: what 2 VLQ bytes hold,
/// `-4096 ..= 12287`.
fn fits(ty: ParamType, v: i64) -> bool {
    let (min, max) = match ty {
        ParamType::U32 | ParamType::I32 => (-(1i64 << 31), (1i64 << 32) - 1),
        ParamType::U16 | ParamType::I16 => (-(1i64 << 15), (1i64 << 16) - 1),
        ParamType::Byte => (-(1i64 << 12), (3i64 << 12) - 1),
        ParamType::Str | ParamType::Buffer => return false,
    };
    (min..=max).contains(&v)
}

impl Dictionary {
    /// A reusable encoder for the integer-only command `name`.
    pub fn encoder(&self, name: &str) -> Result<CmdEncoder, DictError> {
        let def = self.command(name)?;
        let mut types = [ParamType::U32; MAX_INT_PARAMS];
        if def.params.len() > MAX_INT_PARAMS {
            return Err(DictError::TooLong(def.name.clone()));
        }
        for (slot, (pname, ty)) in types.iter_mut().zip(&def.params) {
            if ty.is_bytes() {
                return Err(DictError::ArgType {
                    name: def.name.clone(),
                    param: pname.clone(),
                });
            }
            *slot = *ty;
        }
        Ok(CmdEncoder {
            id: def.id,
            types,
            count: def.params.len(),
            def: Arc::new(def.clone()),
        })
    }

    /// Encodes the integer-only command `name` with `args` in format order.
    pub fn encode(&self, name: &str, args: &[i64]) -> Result<Cmd, DictError> {
        self.encoder(name)?.encode(args)
    }

    /// Encodes command `name` with any parameter values (strings and buffers included).
    pub fn encode_values(&self, name: &str, args: &[Value<'_>]) -> Result<Cmd, DictError> {
        let def = self.command(name)?;
        if args.len() != def.params.len() {
            return Err(DictError::ArgCount {
                name: def.name.clone(),
                expected: def.params.len(),
                got: args.len(),
            });
        }
        for ((pname, ty), arg) in def.params.iter().zip(args) {
            let ok = match arg {
                Value::Int(v) => !ty.is_bytes() && fits(*ty, *v),
                Value::Bytes(_) => ty.is_bytes(),
            };
            if !ok {
                return Err(match arg {
                    Value::Int(v) if !ty.is_bytes() => DictError::OutOfRange {
                        name: def.name.clone(),
                        param: pname.clone(),
                        value: *v,
                    },
                    _ => DictError::ArgType {
                        name: def.name.clone(),
                        param: pname.clone(),
                    },
                });
            }
        }
        let mut data = [0; MESSAGE_PAYLOAD_MAX];
        let len = encode_message(def.id, &def.format, args, &mut data).map_err(|e| match e {
            FormatError::NoSpace | FormatError::TooLong => DictError::TooLong(def.name.clone()),
            _ => DictError::BadFormat(def.format.clone()),
        })?;
        Ok(Cmd { len: len as u8, data })
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::test_dict;
    use super::*;

    #[test]
    fn encode_queue_step_golden() {
        let d = test_dict();
        let cmd = d.encode("queue_step", &[2, 40_000, 20, -3]).unwrap();
        assert_eq!(cmd.as_bytes(), &[20, 0x02, 0x82, 0xB8, 0x40, 0x14, 0x7D]);
        let enc = d.encoder("queue_step").unwrap();
        assert_eq!(enc.encode(&[2, 40_000, 20, -3]).unwrap(), cmd);
        assert_eq!(d.encode("get_clock", &[]).unwrap().as_bytes(), &[6]);
    }

    #[test]
    fn encode_errors_name_the_problem() {
        let d = test_dict();
        assert_eq!(
            d.encode("queue_stepp", &[]).unwrap_err().to_string(),
            "MCU dictionary has no command 'queue_stepp'"
        );
        assert!(matches!(
            d.encode("queue_step", &[1]),
            Err(DictError::ArgCount { expected: 4, .. })
        ));
        let e = d.encode("queue_step", &[1, 1, 70_000, 0]).unwrap_err();
        assert_eq!(
            e.to_string(),
            "command 'queue_step' parameter 'count' value 70000 does not fit its type"
        );
        assert!(d.encode("queue_step", &[1, u32::MAX as i64, 1, -32768]).is_ok());
        assert!(d.encode("queue_step", &[1, 1 << 32, 1, 0]).is_err());
        assert!(matches!(
            d.encode("debug_write", &[1]),
            Err(DictError::ArgType { .. })
        ));
    }

    /// A Linux-process MCU's pins run past 255 (`gpiochip1/gpio0` = 256) yet its
    /// `config_stepper` declares `step_pin=%c`: Klipper sends such values as plain 2-byte VLQs.
    #[test]
    fn byte_params_carry_pins_above_255() {
        let d = Dictionary::from_json(
            r#"{"commands": {"config_stepper oid=%c step_pin=%c dir_pin=%c invert_step=%c step_pulse_ticks=%u": 14}}"#,
        )
        .unwrap();
        let cmd = d.encode("config_stepper", &[0, 256, 2047, -1, 100]).unwrap();
        assert_eq!(
            cmd.as_bytes(),
            &[14, 0x00, 0x82, 0x00, 0x8F, 0x7F, 0x7F, 0x80, 0x64]
        );
        assert!(d.encode("config_stepper", &[0, 12287, 0, -4096, 0]).is_ok());
        assert!(d.encode("config_stepper", &[0, 12288, 0, 0, 0]).is_err());
        assert!(d.encode("config_stepper", &[0, 0, 0, -4097, 0]).is_err());
    }

    #[test]
    fn encode_values_with_bytes() {
        let d = test_dict();
        let cmd = d.encode_values("debug_write", &[Value::Bytes(b"hi")]).unwrap();
        assert_eq!(cmd.as_bytes(), &[22, 2, b'h', b'i']);
        assert!(d.encode_values("debug_write", &[Value::Bytes(&[0; 58])]).is_err());
        assert!(d.encode_values("debug_write", &[Value::Int(1)]).is_err());
        let same = d
            .encode_values(
                "queue_step",
                &[Value::Int(2), Value::Int(40_000), Value::Int(20), Value::Int(-3)],
            )
            .unwrap();
        assert_eq!(same, d.encode("queue_step", &[2, 40_000, 20, -3]).unwrap());
    }

    #[test]
    fn cmd_is_small_and_copy() {
        fn is_copy<T: Copy>() {}
        is_copy::<Cmd>();
        assert_eq!(std::mem::size_of::<Cmd>(), 1 + MESSAGE_PAYLOAD_MAX);
        assert!(Cmd::from_bytes(&[0; 60]).is_none());
        assert_eq!(Cmd::from_bytes(&[1, 2]).unwrap().as_bytes(), &[1, 2]);
    }
}
