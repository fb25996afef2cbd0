//! A tiny fake MCU for the link's end-to-end tests, built on the `no_std` [`crate::proto`]
//! only (plus flate2 to compress its dictionary): it serves a small dictionary, answers
//! `get_uptime`/`get_clock`/`get_config`, acks good blocks, NAKs bad or out-of-order ones, and
//! on request shuts down, goes silent or hangs up.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use crate::proto::format::{decode_params, encode_message, Value};
use crate::proto::{encode_block, find_block, vlq, Frame, MESSAGE_MAX};
use crate::transport::Transport;

/// The fake's command table: (id, format).
pub(crate) const COMMANDS: &[(u32, &str)] = &[
    (1, "identify offset=%u count=%c"),
    (5, "get_uptime"),
    (6, "get_clock"),
    (7, "get_config"),
    (8, "emergency_stop"),
    (20, "queue_step oid=%c interval=%u count=%hu add=%hi"),
    (21, "set_next_step_dir oid=%c dir=%c"),
    (22, "stepper_get_position oid=%c"),
    (30, "trsync_set_timeout oid=%c clock=%u"),
    (31, "trsync_trigger oid=%c reason=%c"),
];
/// The fake's response table.
pub(crate) const RESPONSES: &[(u32, &str)] = &[
    (0, "identify_response offset=%u data=%.*s"),
    (80, "uptime high=%u clock=%u"),
    (81, "clock clock=%u"),
    (82, "config is_config=%c crc=%u is_shutdown=%c move_count=%hu"),
    (83, "shutdown clock=%u static_string_id=%hu"),
    (84, "is_shutdown static_string_id=%hu"),
    (85, "stats count=%u sum=%u sumsq=%u"),
    (86, "stepper_position oid=%c pos=%i"),
    (87, "starting"),
    (
        88,
        "trsync_state oid=%c can_trigger=%c trigger_reason=%c clock=%u",
    ),
];
const TIMER_TOO_CLOSE: i64 = 3;
const EMERGENCY: i64 = 2;

/// The fake's dictionary as JSON.
pub(crate) fn dict_json(nominal_freq: f64) -> String {
    let table = |t: &[(u32, &str)]| {
        t.iter()
            .map(|(id, f)| format!("\"{f}\": {id}"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    format!(
        r#"{{"app": "fake", "commands": {{{}}}, "responses": {{{}}},
            "enumerations": {{"static_string_id": {{"Emergency stop": {EMERGENCY},
                "Timer too close": {TIMER_TOO_CLOSE}}}, "pin": {{"PA0": [0, 8]}}}},
            "config": {{"CLOCK_FREQ": {nominal_freq}, "RECEIVE_WINDOW": 192, "MCU": "fake"}}}}"#,
        table(COMMANDS),
        table(RESPONSES)
    )
}

/// Remote control of a running fake.
#[derive(Debug, Default)]
pub(crate) struct Control {
    /// Stop answering and acking anything.
    pub silent: AtomicBool,
    /// Close the transport.
    pub hang_up: AtomicBool,
    /// Raw bytes of every `queue_step` / `set_next_step_dir` accepted, in order.
    pub received: Mutex<Vec<Vec<u8>>>,
    /// Serve bytes that are not zlib data as the dictionary.
    pub corrupt_dict: AtomicBool,
    /// Be shut down without having said so (answer with `is_shutdown` only).
    pub shut_silently: AtomicBool,
    /// Reboot now: sequence back to 0, shutdown cleared, receive buffer lost.
    pub reset: AtomicBool,
    /// Send `starting` after a reset.
    pub send_starting: AtomicBool,
    /// `trsync_set_timeout` / `trsync_trigger` received: (command id, oid, clock or reason).
    pub trsync_log: Mutex<Vec<(u32, i64, i64)>>,
    /// `trsync_state` reports to send: (oid, can_trigger, reason, clock).
    pub send_states: Mutex<Vec<[i64; 4]>>,
}

/// The fake MCU.
pub(crate) struct FakeMcu {
    t: Box<dyn Transport>,
    zdict: Vec<u8>,
    /// Ticks per system second (nominal × time scale).
    freq: f64,
    t0: f64,
    c0: u64,
    expected: u8,
    rx: Vec<u8>,
    shut: Option<i64>,
    ctl: Arc<Control>,
}

impl FakeMcu {
    /// Starts a fake on `t` whose clock runs at `freq` ticks per system second from `c0`.
    pub(crate) fn spawn(
        t: Box<dyn Transport>,
        nominal: f64,
        freq: f64,
        c0: u64,
    ) -> (Arc<Control>, JoinHandle<()>) {
        FakeMcu::spawn_with(t, nominal, freq, c0, Arc::new(Control::default()))
    }

    /// [`Self::spawn`] with control flags set beforehand.
    pub(crate) fn spawn_with(
        t: Box<dyn Transport>,
        nominal: f64,
        freq: f64,
        c0: u64,
        ctl: Arc<Control>,
    ) -> (Arc<Control>, JoinHandle<()>) {
        let fake = FakeMcu {
            t,
            zdict: crate::dict::tests::compress(&dict_json(nominal)),
            freq,
            t0: super::io::system_now(),
            c0,
            expected: 0,
            rx: Vec::new(),
            shut: None,
            ctl: ctl.clone(),
        };
        (ctl, std::thread::spawn(move || fake.run()))
    }

    /// The fake's 64-bit clock at system time `t`.
    pub(crate) fn clock_at(freq: f64, c0: u64, t0: f64, t: f64) -> u64 {
        c0 + ((t - t0) * freq) as u64
    }

    fn clock(&self) -> u64 {
        FakeMcu::clock_at(self.freq, self.c0, self.t0, super::io::system_now())
    }

    fn run(mut self) {
        let mut buf = [0u8; 1024];
        loop {
            if self.ctl.hang_up.load(Ordering::Acquire) {
                return;
            }
            if self.ctl.shut_silently.swap(false, Ordering::AcqRel) {
                self.shut = Some(TIMER_TOO_CLOSE);
            }
            let states = self.ctl.send_states.lock().map(|mut v| std::mem::take(&mut *v));
            for st in states.unwrap_or_default() {
                let args = st.map(Value::Int);
                self.respond(88, &args);
            }
            if self.ctl.reset.swap(false, Ordering::AcqRel) {
                self.expected = 0;
                self.shut = None;
                self.rx.clear();
                if self.ctl.send_starting.load(Ordering::Acquire) {
                    self.respond(87, &[]);
                }
            }
            match self.t.read(&mut buf, Duration::from_millis(5)) {
                Ok(n) => self.feed(&buf[..n]),
                Err(_) => return,
            }
        }
    }

    fn feed(&mut self, data: &[u8]) {
        self.rx.extend_from_slice(data);
        loop {
            let silent = self.ctl.silent.load(Ordering::Acquire);
            match find_block(&self.rx) {
                Frame::Incomplete => break,
                Frame::Skip(n) => drop(self.rx.drain(..n)),
                Frame::Bad(n) => {
                    self.rx.drain(..n);
                    if !silent {
                        self.send(&[]);
                    }
                }
                Frame::Block { len, seq } => {
                    let block: Vec<u8> = self.rx.drain(..len).collect();
                    if silent {
                        continue;
                    }
                    if seq == self.expected {
                        self.expected = (self.expected + 1) & 0x0F;
                        self.process(crate::proto::block::block_payload(&block));
                    }
                    self.send(&[]);
                }
            }
        }
    }

    fn send(&mut self, payload: &[u8]) {
        let mut buf = [0u8; MESSAGE_MAX];
        if let Some(n) = encode_block(self.expected, payload, &mut buf) {
            let _ = self.t.write_all(&buf[..n]);
        }
    }

    fn respond(&mut self, id: u32, args: &[Value<'_>]) {
        let Some((_, fmt)) = RESPONSES.iter().find(|(i, _)| *i == id) else {
            return;
        };
        let mut out = [0u8; 64];
        if let Ok(n) = encode_message(id, fmt, args, &mut out) {
            self.send(&out[..n]);
        }
    }

    fn process(&mut self, mut payload: &[u8]) {
        while let Some((id, used)) = vlq::decode(payload) {
            let Some((_, fmt)) = COMMANDS.iter().find(|(i, _)| *i == id) else {
                return;
            };
            let mut vals = [Value::Int(0); 8];
            let Ok((_, n)) = decode_params(fmt, &payload[used..], &mut vals) else {
                return;
            };
            let raw = payload[..used + n].to_vec();
            payload = &payload[used + n..];
            let v = |i: usize| vals[i].int();
            match id {
                1 => {
                    let (off, count) = (v(0).max(0) as usize, v(1).max(0) as usize);
                    let end = (off + count).min(self.zdict.len());
                    let mut chunk = self.zdict.get(off.min(end)..end).unwrap_or(&[]).to_vec();
                    if self.ctl.corrupt_dict.load(Ordering::Acquire) {
                        chunk.iter_mut().for_each(|b| *b = 0xA5);
                    }
                    self.respond(0, &[Value::Int(v(0)), Value::Bytes(&chunk)]);
                }
                5 => {
                    let c = self.clock();
                    self.respond(80, &[Value::Int((c >> 32) as i64), Value::Int(c as u32 as i64)]);
                }
                6 => {
                    let c = self.clock();
                    self.respond(81, &[Value::Int(c as u32 as i64)]);
                }
                7 => {
                    let shut = self.shut.is_some() as i64;
                    self.respond(
                        82,
                        &[Value::Int(0), Value::Int(0), Value::Int(shut), Value::Int(16)],
                    );
                }
                8 => self.shutdown(EMERGENCY),
                20 | 21 => {
                    if let Some(reason) = self.shut {
                        self.respond(84, &[Value::Int(reason)]);
                    } else if id == 20 && v(0) == 99 {
                        self.shutdown(TIMER_TOO_CLOSE);
                    } else if let Ok(mut r) = self.ctl.received.lock() {
                        r.push(raw);
                    }
                }
                22 => self.respond(86, &[Value::Int(v(0)), Value::Int(-5)]),
                30 | 31 => {
                    if let Ok(mut log) = self.ctl.trsync_log.lock() {
                        log.push((id, v(0), v(1)));
                    }
                }
                _ => {}
            }
        }
    }

    fn shutdown(&mut self, reason: i64) {
        if self.shut.is_none() {
            self.shut = Some(reason);
            let c = self.clock();
            self.respond(83, &[Value::Int(c as u32 as i64), Value::Int(reason)]);
        }
    }
}
