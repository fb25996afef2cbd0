//! Counts the step commands of a host→MCU wire stream, per stepper object: the other side of
//! `cadence bench plan --compare STREAM` (a batch file of the same G-code written by Klipper's
//! `klippy.py -o`, or by `cadence print --batch`).
//!
//! Each `config_stepper` names its object id's step pin; `queue_step` adds one command and
//! `count` steps to its object, `set_next_step_dir` and `reset_step_clock` one each. The step
//! commands' wire bytes are counted as [`crate::plan`] counts Cadence's own (every message's
//! encoded length, packed in order into blocks), so the two figures compare like for like
//! whatever else (configuration, heaters, queries) the stream carries; the whole file's length
//! is kept beside them.

use std::collections::BTreeMap;

use links::dict::{DictError, Dictionary, Message};
use links::proto::{blocks, StreamItem};

use crate::plan::WireCounter;

/// Why a stream could not be counted (`pos`: the byte offset of the block).
#[derive(Debug, thiserror::Error)]
pub enum StreamError {
    /// A block does not decode with the dictionary.
    #[error("block at byte {pos}: {source}")]
    Decode {
        pos: usize,
        #[source]
        source: DictError,
    },
    /// Bytes that are not a block.
    #[error("block at byte {pos}: not a valid block")]
    BadBlock { pos: usize },
    /// The stream ends inside a block.
    #[error("block at byte {pos}: truncated block ({left} bytes left)")]
    Truncated { pos: usize, left: usize },
    /// A step message without a field it must have, or with one out of range.
    #[error("block at byte {pos}: {msg}: bad or missing field '{field}'")]
    Field {
        pos: usize,
        msg: String,
        field: &'static str,
    },
}

/// One stepper object of the stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct StepperCounts {
    /// The step pin its `config_stepper` gave (`None`: step commands without one).
    pub step_pin: Option<u32>,
    pub queue_steps: u64,
    pub steps: u64,
    pub set_dirs: u64,
    pub resets: u64,
}

impl StepperCounts {
    /// The counts of several steppers added up (`step_pin` unset).
    pub fn sum<'a>(all: impl IntoIterator<Item = &'a StepperCounts>) -> StepperCounts {
        all.into_iter()
            .fold(StepperCounts::default(), |a, s| StepperCounts {
                step_pin: None,
                queue_steps: a.queue_steps + s.queue_steps,
                steps: a.steps + s.steps,
                set_dirs: a.set_dirs + s.set_dirs,
                resets: a.resets + s.resets,
            })
    }
}

/// What a stream holds.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct StreamCounts {
    /// The whole stream's length.
    pub bytes: u64,
    /// Messages of every kind.
    pub messages: u64,
    /// The step commands' bytes, packed alone into blocks (see the module docs).
    pub step_cmd_bytes: u64,
    /// By object id.
    pub steppers: BTreeMap<u8, StepperCounts>,
}

impl StreamCounts {
    /// The totals over every stepper.
    pub fn total(&self) -> StepperCounts {
        StepperCounts::sum(self.steppers.values())
    }

    /// The stepper whose `config_stepper` named `step_pin`.
    pub fn by_step_pin(&self, step_pin: u32) -> Option<&StepperCounts> {
        self.steppers.values().find(|s| s.step_pin == Some(step_pin))
    }
}

/// Counts `data`, a stream encoded with `dict`.
pub fn count_stream(data: &[u8], dict: &Dictionary) -> Result<StreamCounts, StreamError> {
    let ids = [
        step_id(dict, "queue_step")?,
        step_id(dict, "set_next_step_dir")?,
        step_id(dict, "reset_step_clock")?,
    ];
    let mut counts = StreamCounts {
        bytes: data.len() as u64,
        ..StreamCounts::default()
    };
    let mut wire = WireCounter::default();
    for item in blocks(data) {
        match item {
            StreamItem::Block { pos, payload, .. } => {
                let msgs = dict
                    .decode(payload)
                    .map_err(|source| StreamError::Decode { pos, source })?;
                for m in &msgs {
                    counts.messages += 1;
                    count_message(m, &ids, &mut counts, &mut wire).map_err(|field| StreamError::Field {
                        pos,
                        msg: m.to_string(),
                        field,
                    })?;
                }
            }
            StreamItem::Bad { pos, .. } => return Err(StreamError::BadBlock { pos }),
            StreamItem::Truncated { pos, left } => return Err(StreamError::Truncated { pos, left }),
        }
    }
    wire.flush();
    counts.step_cmd_bytes = wire.bytes;
    Ok(counts)
}

/// The message id of a step command; a dictionary without it has no steppers to count, which
/// is an error worth naming.
fn step_id(dict: &Dictionary, name: &str) -> Result<u32, StreamError> {
    dict.encoder(name)
        .map(|e| e.id())
        .map_err(|source| StreamError::Decode { pos: 0, source })
}

/// The counts of the stepper whose `oid` message `m` names.
fn stepper_of<'c>(m: &Message, counts: &'c mut StreamCounts) -> Result<&'c mut StepperCounts, &'static str> {
    let oid = m.get("oid").ok_or("oid")?;
    let o = u8::try_from(oid).map_err(|_| "oid")?;
    Ok(counts.steppers.entry(o).or_default())
}

/// Adds one message; `Err(field)` names a missing or out-of-range field.
fn count_message(
    m: &Message,
    ids: &[u32; 3],
    counts: &mut StreamCounts,
    wire: &mut WireCounter,
) -> Result<(), &'static str> {
    let int = |field: &'static str| m.get(field).ok_or(field);
    let stepper = |counts| stepper_of(m, counts);
    // The fields as the wire carries them (signed values as their 32-bit pattern).
    let fields = |names: &[&'static str]| -> Result<Vec<u32>, &'static str> {
        names.iter().map(|&n| int(n).map(|v| v as i32 as u32)).collect()
    };
    match m.name.as_str() {
        "config_stepper" => {
            let step_pin = u32::try_from(int("step_pin")?).map_err(|_| "step_pin")?;
            stepper(counts)?.step_pin = Some(step_pin);
        }
        "queue_step" => {
            let count = u64::try_from(int("count")?).map_err(|_| "count")?;
            let s = stepper(counts)?;
            s.queue_steps += 1;
            s.steps += count;
            let f = fields(&["oid", "interval", "count", "add"])?;
            wire.msg(&[ids[0], f[0], f[1], f[2], f[3]]);
        }
        "set_next_step_dir" => {
            stepper(counts)?.set_dirs += 1;
            let f = fields(&["oid", "dir"])?;
            wire.msg(&[ids[1], f[0], f[1]]);
        }
        "reset_step_clock" => {
            stepper(counts)?.resets += 1;
            let f = fields(&["oid", "clock"])?;
            wire.msg(&[ids[2], f[0], f[1]]);
        }
        _ => {}
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use links::proto::block::encode_block;

    /// A small dictionary with the step commands (the bench crate does not build firmware).
    fn dict() -> Dictionary {
        Dictionary::from_json(
            r#"{"version":"t","build_versions":"","config":{"CLOCK_FREQ":50000000},
            "enumerations":{"pin":{"PA0":0,"PA3":3}},
            "commands":{"config_stepper oid=%c step_pin=%c dir_pin=%c invert_step=%c step_pulse_ticks=%u":10,
              "queue_step oid=%c interval=%u count=%hu add=%hi":11,
              "set_next_step_dir oid=%c dir=%c":12,
              "reset_step_clock oid=%c clock=%u":13,
              "get_uptime":14},
            "responses":{"identify_response offset=%u data=%.*s":0}}"#,
        )
        .unwrap()
    }

    fn stream(d: &Dictionary, msgs: &[(&str, &[i64])]) -> Vec<u8> {
        let mut out = Vec::new();
        for (i, (name, args)) in msgs.iter().enumerate() {
            let cmd = d.encode(name, args).unwrap();
            let mut buf = [0u8; 64];
            let n = encode_block((i % 16) as u8, cmd.as_bytes(), &mut buf).unwrap();
            out.extend_from_slice(&buf[..n]);
        }
        out
    }

    #[test]
    fn counts_steps_and_commands_per_step_pin() {
        let d = dict();
        let s = stream(
            &d,
            &[
                ("config_stepper", &[0, 3, 0, 0, 0]),
                ("config_stepper", &[1, 0, 0, 0, 0]),
                ("get_uptime", &[]),
                ("set_next_step_dir", &[1, 1]),
                ("queue_step", &[1, 1000, 5, -2]),
                ("reset_step_clock", &[0, 123_456]),
                ("queue_step", &[0, 2000, 7, 0]),
                ("queue_step", &[1, 900, 3, 0]),
            ],
        );
        let c = count_stream(&s, &d).unwrap();
        assert_eq!((c.bytes, c.messages), (s.len() as u64, 8));
        let pa3 = c.by_step_pin(3).unwrap();
        assert_eq!(
            (pa3.queue_steps, pa3.steps, pa3.set_dirs, pa3.resets),
            (1, 7, 0, 1)
        );
        let pa0 = c.by_step_pin(0).unwrap();
        assert_eq!(
            (pa0.queue_steps, pa0.steps, pa0.set_dirs, pa0.resets),
            (2, 8, 1, 0)
        );
        let t = c.total();
        assert_eq!((t.queue_steps, t.steps, t.set_dirs, t.resets), (3, 15, 1, 1));
        // Five step commands packed into one block: their payload plus the framing.
        let payload: usize = [
            [12u32, 1, 1]
                .iter()
                .map(|&v| links::proto::vlq::encoded_len(v))
                .sum::<usize>(),
            [11u32, 1, 1000, 5, -2i32 as u32]
                .iter()
                .map(|&v| links::proto::vlq::encoded_len(v))
                .sum(),
            [13u32, 0, 123_456]
                .iter()
                .map(|&v| links::proto::vlq::encoded_len(v))
                .sum(),
            [11u32, 0, 2000, 7, 0]
                .iter()
                .map(|&v| links::proto::vlq::encoded_len(v))
                .sum(),
            [11u32, 1, 900, 3, 0]
                .iter()
                .map(|&v| links::proto::vlq::encoded_len(v))
                .sum(),
        ]
        .iter()
        .sum();
        assert_eq!(c.step_cmd_bytes, (payload + links::proto::MESSAGE_MIN) as u64);
    }

    #[test]
    fn bad_streams_name_the_byte() {
        let d = dict();
        let s = stream(
            &d,
            &[("queue_step", &[0, 2000, 7, 0]), ("queue_step", &[0, 2000, 7, 0])],
        );
        let half = s.len() / 2 + 2;
        let e = count_stream(&s[..half], &d).unwrap_err();
        assert!(matches!(e, StreamError::Truncated { .. }), "{e}");
        assert!(e.to_string().starts_with("block at byte "), "{e}");
        let mut bad = s.clone();
        let last = bad.len() - 1;
        bad[last - 2] ^= 0xff; // the first block's CRC no longer matches
        assert!(count_stream(&bad, &d).is_err());
    }
}
