//! Protocol tests of the core with a virtual clock and a fake board. The test host learns every
//! id from the dictionary it downloads through `identify` (only ids 0 and 1 are hard-coded).

use super::*;
use crate::core::constants::reason;
use crate::core::TriggerSource;
use crate::core::IDENTIFY_CHUNK_MAX;
use links::proto::block::{block_payload, encode_block, find_block, Frame};
use links::proto::format::{decode_params, encode_message, message_name, Value};
use links::proto::vlq;
use proptest::prelude::*;
use serde_json::Value as Json;
use std::collections::HashMap;
use std::io::Read;

const FREQ: u32 = 1_000_000;

#[derive(Debug, Default)]
struct FakeBoard {
    steps: Vec<(u8, bool, u32)>,
    out: Vec<u8>,
    queued: Vec<(u8, u32, u32)>,
    shutdowns: Vec<(u32, u16, &'static str)>,
    /// Net steps per stepper oid.
    pos: HashMap<u8, i32>,
    /// An endstop input: (pin, stepper oid, position at or above which the pin reads 1).
    endstop: Option<(u8, u8, i32)>,
    adc: HashMap<u8, u16>,
    pin_sets: Vec<(u8, bool, u32)>,
    /// `config_input` calls: (pin, pull_up).
    inputs: Vec<(u8, bool)>,
    triggers: Vec<(TriggerSource, u8, u8, u32)>,
    /// The host's clock at the current call (kept by [`Host::advance`]).
    now: u64,
    /// A simulated heater: its pin's sets drive it, its sensor pin reads it.
    thermal: Option<crate::sim::heater::Heater>,
}

impl Board for FakeBoard {
    fn step(&mut self, oid: u8, dir: bool, clock: WireClock) {
        self.steps.push((oid, dir, clock.0));
        *self.pos.entry(oid).or_default() += if dir { 1 } else { -1 };
    }
    fn read_pin(&mut self, pin: u8, _at: WireClock) -> bool {
        match self.endstop {
            Some((p, oid, at)) if p == pin => self.pos.get(&oid).copied().unwrap_or(0) >= at,
            _ => false,
        }
    }
    fn read_adc(&mut self, pin: u8) -> u16 {
        let t = self.now as f64 / FREQ as f64;
        match self.thermal.as_mut() {
            Some(h) if h.sensor_pin == pin => h.adc(t),
            _ => self.adc.get(&pin).copied().unwrap_or(0),
        }
    }
    fn set_pin(&mut self, pin: u8, value: bool, clock: WireClock) {
        let t = rt_core::McuClock(self.now).extend(clock).0 as f64 / FREQ as f64;
        if let Some(h) = self.thermal.as_mut().filter(|h| h.heater_pin == pin) {
            h.set(value, t);
        }
        self.pin_sets.push((pin, value, clock.0));
    }
    fn config_input(&mut self, pin: u8, pull_up: bool) {
        self.inputs.push((pin, pull_up));
    }
    fn triggered(&mut self, source: TriggerSource, oid: u8, reason: u8, clock: WireClock) {
        self.triggers.push((source, oid, reason, clock.0));
    }
    fn lateness(&self) -> crate::core::Lateness {
        crate::core::Lateness {
            count: 7,
            p50: 1,
            p99: 2,
            p999: 3,
            max: 4,
        }
    }
    fn write(&mut self, bytes: &[u8]) {
        self.out.extend_from_slice(bytes);
    }
    fn queue_step_received(&mut self, oid: u8, first_clock: WireClock, now: WireClock) {
        self.queued.push((oid, first_clock.0, now.0));
    }
    fn shutdown(&mut self, clock: WireClock, id: u16, reason: &'static str) {
        self.shutdowns.push((clock.0, id, reason));
    }
}

/// A decoded response: its name and integer parameters (byte parameters as the bytes).
#[derive(Debug, Clone, PartialEq)]
struct Resp {
    name: String,
    ints: Vec<i64>,
    bytes: Vec<u8>,
}

/// A block from the MCU: its sequence and its messages (empty = ack/nak).
#[derive(Debug, Clone, PartialEq)]
struct Block {
    seq: u8,
    msgs: Vec<Resp>,
}

type TestMcu = Mcu<FakeBoard, 8, 64>;

struct Host {
    mcu: TestMcu,
    now: u64,
    seq: u8,
    commands: HashMap<String, (u32, String)>,
    responses: HashMap<u32, String>,
    dict: Json,
}

fn leaked_dictionary() -> &'static [u8] {
    Box::leak(crate::dict::dictionary_bytes(FREQ).into_boxed_slice())
}

impl Host {
    fn new(move_count: u16, start: u64) -> Host {
        Host::with_late_limit(move_count, start, 0)
    }

    fn with_late_limit(move_count: u16, start: u64, late_limit: u32) -> Host {
        let config = McuConfig {
            clock_freq: FREQ,
            move_count,
            late_limit,
        };
        let mcu = Mcu::new(
            FakeBoard::default(),
            leaked_dictionary(),
            config,
            WireClock(start as u32),
        );
        let mut host = Host {
            mcu,
            now: start,
            seq: 0,
            commands: HashMap::new(),
            responses: HashMap::new(),
            dict: Json::Null,
        };
        host.responses
            .insert(0, links::proto::FMT_IDENTIFY_RESPONSE.into());
        host.commands
            .insert("identify".into(), (1, links::proto::FMT_IDENTIFY.into()));
        host.identify();
        host
    }

    /// Downloads the dictionary in 40-byte chunks and learns the ids.
    fn identify(&mut self) {
        let mut data = Vec::new();
        loop {
            let offset = data.len() as i64;
            let blocks = self.exchange(&[("identify", &[offset, 40])]);
            let r = &blocks[0].msgs[0];
            assert_eq!(r.name, "identify_response");
            assert_eq!(r.ints[0], offset);
            if r.bytes.is_empty() {
                break;
            }
            assert!(r.bytes.len() <= 40);
            data.extend_from_slice(&r.bytes);
        }
        let mut text = String::new();
        flate2::read::ZlibDecoder::new(&data[..])
            .read_to_string(&mut text)
            .unwrap();
        self.dict = serde_json::from_str(&text).unwrap();
        for (fmt, id) in self.dict["commands"].as_object().unwrap() {
            let id = id.as_u64().unwrap() as u32;
            self.commands.insert(message_name(fmt).into(), (id, fmt.clone()));
        }
        for (fmt, id) in self.dict["responses"].as_object().unwrap() {
            self.responses.insert(id.as_u64().unwrap() as u32, fmt.clone());
        }
    }

    fn reason_id(&self, reason: &str) -> i64 {
        self.dict["enumerations"]["static_string_id"][reason]
            .as_i64()
            .unwrap()
    }

    fn wire_now(&self) -> WireClock {
        WireClock(self.now as u32)
    }

    fn encode(&self, msgs: &[(&str, &[i64])]) -> Vec<u8> {
        let mut payload = Vec::new();
        for (name, args) in msgs {
            let (id, fmt) = &self.commands[*name];
            let vals: Vec<Value> = args.iter().map(|&a| Value::Int(a)).collect();
            let mut buf = [0u8; 64];
            let n = encode_message(*id, fmt, &vals, &mut buf).unwrap();
            payload.extend_from_slice(&buf[..n]);
        }
        payload
    }

    fn block(&mut self, payload: &[u8]) -> Vec<u8> {
        let mut out = [0u8; 64];
        let n = encode_block(self.seq, payload, &mut out).unwrap();
        self.seq = (self.seq + 1) & 0x0F;
        out[..n].to_vec()
    }

    /// Sends one block and returns the response blocks; the empty ack block the MCU always
    /// sends after a dispatched block is checked and removed (unless it is the only one).
    fn exchange(&mut self, msgs: &[(&str, &[i64])]) -> Vec<Block> {
        let payload = self.encode(msgs);
        let bytes = self.block(&payload);
        let mut blocks = self.raw(&bytes);
        let ack = blocks
            .iter()
            .rposition(|b| b.msgs.is_empty())
            .expect("an empty ack block");
        assert_eq!(
            blocks[ack].seq, self.seq,
            "the ack carries the next expected sequence"
        );
        if blocks.len() > 1 {
            blocks.remove(ack);
        }
        blocks
    }

    fn raw(&mut self, bytes: &[u8]) -> Vec<Block> {
        self.mcu.board_mut().now = self.now;
        self.mcu.receive(self.wire_now(), bytes);
        self.take()
    }

    /// Advances virtual time to `until`, running timers at every wake time on the way.
    fn advance(&mut self, until: u64) -> Vec<Block> {
        loop {
            let wake = rt_core::McuClock(self.now).extend(self.mcu.next_wake()).0;
            if wake > until {
                break;
            }
            self.now = wake.max(self.now);
            self.mcu.board_mut().now = self.now;
            self.mcu.run_timers(self.wire_now());
        }
        self.now = until;
        self.mcu.board_mut().now = self.now;
        self.mcu.run_timers(self.wire_now());
        self.take()
    }

    fn take(&mut self) -> Vec<Block> {
        let out = std::mem::take(&mut self.mcu.board_mut().out);
        let mut rest = &out[..];
        let mut blocks = Vec::new();
        while !rest.is_empty() {
            let Frame::Block { len, seq } = find_block(rest) else {
                panic!("MCU sent a malformed block: {rest:?}");
            };
            let mut msgs = Vec::new();
            let mut p = block_payload(&rest[..len]);
            while !p.is_empty() {
                let (id, used) = vlq::decode(p).unwrap();
                let fmt = &self.responses[&id];
                let mut vals = [Value::Int(0); 8];
                let (cnt, used2) = decode_params(fmt, &p[used..], &mut vals).unwrap();
                let mut r = Resp {
                    name: message_name(fmt).into(),
                    ints: Vec::new(),
                    bytes: Vec::new(),
                };
                for v in &vals[..cnt] {
                    match v {
                        Value::Int(i) => r.ints.push(*i),
                        Value::Bytes(b) => r.bytes.extend_from_slice(b),
                    }
                }
                msgs.push(r);
                p = &p[used + used2..];
            }
            blocks.push(Block { seq, msgs });
            rest = &rest[len..];
        }
        blocks
    }

    fn configure(&mut self, steppers: u8) {
        self.exchange(&[("allocate_oids", &[steppers as i64])]);
        for oid in 0..steppers as i64 {
            self.exchange(&[("config_stepper", &[oid, oid * 2, oid * 2 + 1, 0, 2])]);
        }
        self.exchange(&[("finalize_config", &[0xC0FFEE])]);
    }
}

/// A command by name with its integer arguments.
type Msg<'a> = (&'a str, &'a [i64]);

fn all_msgs(blocks: &[Block]) -> Vec<Resp> {
    blocks.iter().flat_map(|b| b.msgs.clone()).collect()
}

fn find<'a>(msgs: &'a [Resp], name: &str) -> Option<&'a Resp> {
    msgs.iter().find(|r| r.name == name)
}

#[test]
fn identify_dictionary_is_usable_by_links_proto() {
    let host = Host::new(64, 0);
    for fmt in host.dict["commands"].as_object().unwrap().keys() {
        assert!(links::proto::format::Params::of(fmt).all(|p| p.is_ok()), "{fmt}");
    }
    assert_eq!(
        host.commands["queue_step"].1,
        "queue_step oid=%c interval=%u count=%hu add=%hi"
    );
    assert_eq!(host.dict["config"]["CLOCK_FREQ"], FREQ);
    assert_eq!(
        host.dict["enumerations"]["pin"]["PC0"],
        serde_json::json!([16, 8])
    );
}

#[test]
fn identify_past_the_end_is_empty_and_chunks_are_clipped() {
    let mut host = Host::new(64, 0);
    let len = host.mcu.dictionary.len() as i64;
    let r = all_msgs(&host.exchange(&[("identify", &[len + 100, 40])]));
    assert_eq!((r[0].ints[0], r[0].bytes.len()), (len + 100, 0));
    let r = all_msgs(&host.exchange(&[("identify", &[0, 255])]));
    assert_eq!(r[0].bytes.len(), IDENTIFY_CHUNK_MAX);
}

#[test]
fn config_flow_and_every_response_acks() {
    let mut host = Host::new(40, 0);
    let blocks = host.exchange(&[("get_config", &[])]);
    assert_eq!(blocks.len(), 1);
    assert_eq!(
        blocks[0].seq, host.seq,
        "a response carries the next expected sequence"
    );
    assert_eq!(blocks[0].msgs[0].ints, [0, 0, 0, 40]);
    host.configure(2);
    let blocks = host.exchange(&[("get_config", &[]), ("get_clock", &[])]);
    let msgs = all_msgs(&blocks);
    assert_eq!(find(&msgs, "config").unwrap().ints, [1, 0xC0FFEE, 0, 40]);
    assert_eq!(find(&msgs, "clock").unwrap().ints, [0]);
    // A command without a response is acked by an empty block.
    let blocks = host.exchange(&[("set_next_step_dir", &[0, 1])]);
    assert_eq!(
        blocks,
        [Block {
            seq: host.seq,
            msgs: vec![]
        }]
    );
}

#[test]
fn steps_replay_exactly_and_position_is_reported() {
    let mut host = Host::new(64, 0);
    host.configure(2);
    host.now = 1000;
    host.exchange(&[
        ("reset_step_clock", &[0, 50_000]),
        ("set_next_step_dir", &[0, 1]),
        ("queue_step", &[0, 1000, 3, 100]),
        ("queue_step", &[0, 500, 2, 0]),
        ("set_next_step_dir", &[0, 0]),
        ("queue_step", &[0, 700, 1, 0]),
        ("reset_step_clock", &[1, 50_100]),
        ("queue_step", &[1, 10, 2, -5]),
    ]);
    assert_eq!(
        host.mcu.board().queued,
        [
            (0, 51_000, 1000),
            (0, 53_800, 1000),
            (0, 55_000, 1000),
            (1, 50_110, 1000)
        ]
    );
    host.advance(100_000);
    let steps = &host.mcu.board().steps;
    let expect = [
        (1, false, 50_110),
        (1, false, 50_115),
        (0, true, 51_000),
        (0, true, 52_100),
        (0, true, 53_300),
        (0, true, 53_800),
        (0, true, 54_300),
        (0, false, 55_000),
    ];
    assert_eq!(steps, &expect);
    let msgs = all_msgs(&host.exchange(&[("stepper_get_position", &[0])]));
    assert_eq!(msgs[0].ints, [0, 4]);
}

#[test]
fn steps_cross_the_clock_wrap() {
    let start = u32::MAX as u64 - 10_000;
    let mut host = Host::new(64, start);
    host.configure(1);
    let base = (start + 5_000) as u32 as i64;
    host.exchange(&[
        ("reset_step_clock", &[0, base]),
        ("queue_step", &[0, 4_000, 4, 0]),
    ]);
    host.advance(start + 30_000);
    let clocks: Vec<u32> = host.mcu.board().steps.iter().map(|s| s.2).collect();
    let expect: Vec<u32> = (1..=4).map(|k| (start + 5_000 + 4_000 * k) as u32).collect();
    assert_eq!(clocks, expect);
    let up = all_msgs(&host.exchange(&[("get_uptime", &[])]));
    assert_eq!(up[0].ints, [1, (start + 30_000) as u32 as i64]);
}

#[test]
fn late_queue_step_shuts_down_with_timer_too_close() {
    let mut host = Host::new(64, 0);
    host.configure(1);
    host.now = 20_000;
    let blocks = host.exchange(&[
        ("reset_step_clock", &[0, 10_000]),
        ("queue_step", &[0, 5_000, 2, 0]),
    ]);
    let msgs = all_msgs(&blocks);
    let ttc = host.reason_id("Timer too close");
    assert_eq!(find(&msgs, "shutdown").unwrap().ints, [20_000, ttc]);
    assert_eq!(host.mcu.shutdown_reason(), Some(reason::TIMER_TOO_CLOSE));
    assert_eq!(host.mcu.board().queued, [(0, 15_000, 20_000)]);
    // Live commands now get is_shutdown; identify/get_config/get_clock still work.
    let msgs = all_msgs(&host.exchange(&[("queue_step", &[0, 50_000, 1, 0]), ("get_clock", &[])]));
    assert_eq!(find(&msgs, "is_shutdown").unwrap().ints, [ttc]);
    assert_eq!(find(&msgs, "clock").unwrap().ints, [20_000]);
    let msgs = all_msgs(&host.exchange(&[("get_config", &[])]));
    assert_eq!(msgs[0].ints[2], 1);
    host.advance(200_000);
    assert!(host.mcu.board().steps.is_empty());
    // clear_shutdown brings the MCU back.
    host.exchange(&[("clear_shutdown", &[])]);
    assert_eq!(host.mcu.shutdown_reason(), None);
}

#[test]
fn shutdown_stops_running_steppers() {
    let mut host = Host::new(64, 0);
    host.configure(1);
    host.exchange(&[
        ("reset_step_clock", &[0, 1000]),
        ("set_next_step_dir", &[0, 1]),
        ("queue_step", &[0, 1000, 10, 0]),
    ]);
    host.advance(4_500);
    let msgs = all_msgs(&host.exchange(&[("emergency_stop", &[])]));
    assert_eq!(
        find(&msgs, "shutdown").unwrap().ints[1],
        host.reason_id("Command request")
    );
    host.advance(50_000);
    assert_eq!(host.mcu.board().steps.len(), 3);
    assert_eq!(host.mcu.stepper_position(0), Some(3));
}

#[test]
fn count_zero_shuts_down() {
    let mut host = Host::new(64, 0);
    host.configure(1);
    let msgs = all_msgs(&host.exchange(&[("queue_step", &[0, 1000, 0, 0])]));
    assert_eq!(
        find(&msgs, "shutdown").unwrap().ints[1],
        host.reason_id("Invalid count parameter")
    );
}

#[test]
fn other_shutdown_reasons() {
    let cases: &[(&[Msg], &str)] = &[
        (&[("queue_step", &[5, 1000, 1, 0])], "Invalid oid"),
        (&[("set_next_step_dir", &[3, 1])], "Invalid oid"),
        (&[("allocate_oids", &[1])], "oids already allocated"),
        (&[("config_stepper", &[0, 1, 2, 0, 0])], "Already configured"),
        (&[("finalize_config", &[1])], "Already configured"),
        (
            &[
                ("reset_step_clock", &[0, 1000]),
                ("queue_step", &[0, 1000, 5, 0]),
                ("reset_step_clock", &[0, 0]),
            ],
            "Can't reset time when stepper active",
        ),
        (
            &[
                ("reset_step_clock", &[0, 1000]),
                ("queue_step", &[0, 1000, 5, 0]),
                ("queue_step", &[0, 1000, 5, 0]),
                ("queue_step", &[0, 1000, 5, 0]),
                ("queue_step", &[0, 1000, 5, 0]),
            ],
            "Move queue overflow",
        ),
    ];
    for (msgs, reason) in cases {
        let mut host = Host::new(2, 0);
        host.configure(1);
        let got = all_msgs(&host.exchange(msgs));
        let expect = host.reason_id(reason);
        assert_eq!(
            find(&got, "shutdown").map(|r| r.ints[1]),
            Some(expect),
            "{reason}"
        );
    }
    let mut host = Host::new(2, 0);
    let got = all_msgs(&host.exchange(&[("allocate_oids", &[9])]));
    assert_eq!(
        find(&got, "shutdown").unwrap().ints[1],
        host.reason_id("Too many oids")
    );
    let mut host = Host::new(2, 0);
    host.exchange(&[("allocate_oids", &[2])]);
    let got = all_msgs(&host.exchange(&[
        ("config_stepper", &[0, 1, 2, 0, 0]),
        ("config_stepper", &[0, 1, 2, 0, 0]),
    ]));
    assert_eq!(
        find(&got, "shutdown").unwrap().ints[1],
        host.reason_id("Can't assign oid")
    );
}

#[test]
fn undecodable_messages_shut_down() {
    let mut host = Host::new(64, 0);
    let (qid, _) = host.commands["queue_step"].clone();
    // queue_step with its parameters cut off.
    let bytes = host.block(&[qid as u8, 0x01]);
    let got = all_msgs(&host.raw(&bytes));
    assert_eq!(
        find(&got, "shutdown").unwrap().ints[1],
        host.reason_id("Command parser error")
    );
    let mut host = Host::new(64, 0);
    // A response id sent as a command.
    let bytes = host.block(&[0x00, 0x00, 0x00]);
    let got = all_msgs(&host.raw(&bytes));
    assert_eq!(
        find(&got, "shutdown").unwrap().ints[1],
        host.reason_id("Invalid command")
    );
}

#[test]
fn corrupt_block_gets_one_nak() {
    let mut host = Host::new(64, 0);
    let expected = host.seq;
    let payload = host.encode(&[("get_clock", &[])]);
    let mut bad = host.block(&payload);
    host.seq = expected; // the host will retransmit with the same sequence
    bad[2] ^= 0x01;
    let blocks = host.raw(&bad);
    assert_eq!(
        blocks,
        [Block {
            seq: expected,
            msgs: vec![]
        }]
    );
    // More garbage before a valid block: no second NAK.
    assert_eq!(host.raw(&[0x03, 0x11, 0x22, 0x7E]), []);
    // The retransmission is answered.
    let blocks = host.exchange(&[("get_clock", &[])]);
    assert_eq!(blocks[0].seq, (expected + 1) & 0x0F);
    assert_eq!(blocks[0].msgs[0].name, "clock");
}

#[test]
fn out_of_order_block_gets_a_nak_and_is_dropped() {
    let mut host = Host::new(64, 0);
    let expected = host.seq;
    host.seq = (expected + 1) & 0x0F; // skip one: the MCU must not run this block
    let payload = host.encode(&[("get_clock", &[])]);
    let bytes = host.block(&payload);
    let blocks = host.raw(&bytes);
    assert_eq!(
        blocks,
        [Block {
            seq: expected,
            msgs: vec![]
        }]
    );
    host.seq = expected;
    let blocks = host.exchange(&[("get_clock", &[])]);
    assert_eq!(blocks[0].msgs[0].name, "clock");
    // Stray sync bytes are skipped silently.
    assert_eq!(host.raw(&[0x7E, 0x7E]), []);
}

#[test]
fn blocks_split_across_receive_calls() {
    let mut host = Host::new(64, 0);
    let payload = host.encode(&[("get_clock", &[]), ("get_config", &[])]);
    let bytes = host.block(&payload);
    let mut msgs = Vec::new();
    for b in &bytes {
        msgs.extend(all_msgs(&host.raw(std::slice::from_ref(b))));
    }
    let names: Vec<&str> = msgs.iter().map(|r| r.name.as_str()).collect();
    assert_eq!(names, ["clock", "config"]);
}

/// Klipper's host parses exactly one response per MCU block ("Extra data at end of message"
/// otherwise, and klippy stayed in `startup`): a host block asking `get_config` and `get_clock`
/// is answered with two blocks of one response each, then the empty ack.
#[test]
fn one_response_per_block() {
    let mut host = Host::new(64, 0);
    let payload = host.encode(&[("get_config", &[]), ("get_clock", &[]), ("get_uptime", &[])]);
    let bytes = host.block(&payload);
    let blocks = host.raw(&bytes);
    let shape: Vec<(usize, Option<&str>)> = blocks
        .iter()
        .map(|b| (b.msgs.len(), b.msgs.first().map(|r| r.name.as_str())))
        .collect();
    assert_eq!(
        shape,
        [
            (1, Some("config")),
            (1, Some("clock")),
            (1, Some("uptime")),
            (0, None)
        ]
    );
    // Golden bytes of the first block: `config is_config=0 crc=0 is_shutdown=0 move_count=64`
    // with sequence 1 (it acks the host's block 0): length 10, 0x11, id, 0 0 0 64, CRC, sync.
    let mut first = Vec::new();
    let mut h2 = Host::new(64, 0);
    let get_config = h2.encode(&[("get_config", &[])]);
    let b = h2.block(&get_config);
    h2.mcu.receive(h2.wire_now(), &b);
    first.extend(std::mem::take(&mut h2.mcu.board_mut().out));
    let id = h2.dict["responses"]
        .as_object()
        .unwrap()
        .iter()
        .find(|(f, _)| f.starts_with("config "))
        .map(|(_, id)| id.as_u64().unwrap() as u8)
        .unwrap();
    assert!(id < 96, "a one-byte VLQ id");
    let body = [10u8, 0x10 | h2.seq, id, 0, 0, 0, 64];
    let crc = links::proto::crc::crc16_ccitt(&body);
    let mut golden = body.to_vec();
    golden.extend_from_slice(&[(crc >> 8) as u8, crc as u8, 0x7E]);
    assert_eq!(&first[..golden.len()], &golden[..]);
    // Every block the MCU wrote in a startup exchange holds at most one response.
    let mut host = Host::new(64, 0);
    host.configure(3);
    let blocks = host.exchange(&[("get_config", &[]), ("get_clock", &[])]);
    assert!(blocks.iter().all(|b| b.msgs.len() <= 1), "{:?}", blocks.len());
}

/// Klipper's host does FIRMWARE_RESTART on an MCU without `reset` by `emergency_stop` then
/// `config_reset`, reconnects and configures it again: the MCU must forget its configuration
/// (it had no `config_reset`: "Unable to issue reset command", klippy stuck in startup).
#[test]
fn config_reset_forgets_the_configuration_only_while_shut_down() {
    let mut host = Host::new(64, 0);
    host.configure(2);
    host.exchange(&[("reset_step_clock", &[0, 1000]), ("queue_step", &[0, 100, 3, 0])]);
    host.advance(2000);
    assert_eq!(host.mcu.stepper_position(0), Some(-3));
    let msgs = all_msgs(&host.exchange(&[("config_reset", &[])]));
    let id = host.reason_id(reason::CONFIG_RESET_NOT_SHUTDOWN);
    assert_eq!(
        find(&msgs, "shutdown").unwrap().ints[1],
        id,
        "not shut down: refused"
    );
    assert!(
        host.mcu.is_config(),
        "a refused config_reset keeps the configuration"
    );
    let msgs = all_msgs(&host.exchange(&[("config_reset", &[]), ("get_config", &[])]));
    assert_eq!(find(&msgs, "config").unwrap().ints, [0, 0, 0, 64]);
    assert_eq!(host.mcu.shutdown_reason(), None);
    assert_eq!(host.mcu.stepper_position(0), None);
    // Configured again from scratch, as after a power cycle.
    host.configure(3);
    let msgs = all_msgs(&host.exchange(&[("get_config", &[]), ("stepper_get_position", &[2])]));
    assert_eq!(find(&msgs, "config").unwrap().ints, [1, 0xC0FFEE, 0, 64]);
    assert_eq!(find(&msgs, "stepper_position").unwrap().ints, [2, 0]);
}

#[test]
fn stats_every_five_seconds() {
    let mut host = Host::new(64, 0);
    host.mcu.record_loop(300);
    host.mcu.record_loop(100);
    let msgs = all_msgs(&host.advance(5 * FREQ as u64 - 1));
    assert!(find(&msgs, "stats").is_none());
    let msgs = all_msgs(&host.advance(5 * FREQ as u64));
    // sumsq: ceil(300²/256) + ceil(100²/256) = 352 + 40
    assert_eq!(find(&msgs, "stats").unwrap().ints, [2, 400, 392]);
    let msgs = all_msgs(&host.advance(10 * FREQ as u64));
    assert_eq!(find(&msgs, "stats").unwrap().ints, [0, 0, 0]);
}

proptest! {
    /// No byte stream makes the core panic, and it only ever writes well-formed blocks.
    #[test]
    fn random_bytes_never_panic(data in proptest::collection::vec(any::<u8>(), 0..600), split in 1usize..70) {
        let mut host = Host::new(4, 0);
        for chunk in data.chunks(split) {
            host.now += 10;
            host.raw(chunk);
        }
        host.advance(host.now + 10 * FREQ as u64);
    }

    /// Well-framed blocks with random payloads (any ids, any parameters) never panic either.
    #[test]
    fn random_payloads_never_panic(payloads in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..59), 1..20)) {
        let mut host = Host::new(4, 0);
        host.configure(2);
        for p in payloads {
            let mut p = p;
            if let Some(first) = p.first_mut() {
                *first %= 16; // mostly valid ids
            }
            let bytes = host.block(&p);
            host.now += 1000;
            host.raw(&bytes);
        }
        host.advance(host.now + 10 * FREQ as u64);
    }
}

#[path = "objects_tests.rs"]
mod objects;
