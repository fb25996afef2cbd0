//! A minimal host for the process tests: spawns `cadence-mcu`, identifies it over its pty and
//! exchanges messages by name. Timeouts only guard against hangs.
#![allow(dead_code)]

use links::proto::block::{block_payload, encode_block, find_block, Frame};
use links::proto::format::{decode_params, encode_message, message_name, Value};
use links::proto::vlq;
use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
use std::collections::HashMap;
use std::fs::{File, OpenOptions};
use std::io::{BufRead, BufReader, Read, Write};
use std::os::fd::AsFd;
use std::os::unix::fs::OpenOptionsExt;
use std::process::{Child, Command, Stdio};

pub const FREQ: u64 = 1_000_000;

pub struct Host {
    pub child: Child,
    /// The pty slave's path.
    pub path: String,
    /// A `shutdown` response is expected (else [`Host::wait_for`] fails on one).
    pub shutdown_ok: bool,
    pub slave: File,
    pub seq: u8,
    pub rx: Vec<u8>,
    pub commands: HashMap<String, (u32, String)>,
    pub responses: HashMap<u32, String>,
}

impl Host {
    pub fn send(&mut self, msgs: &[(&str, &[i64])]) {
        let mut payload = Vec::new();
        for (name, args) in msgs {
            let (id, fmt) = &self.commands[*name];
            let vals: Vec<Value> = args.iter().map(|&a| Value::Int(a)).collect();
            let mut buf = [0u8; 64];
            let n = encode_message(*id, fmt, &vals, &mut buf).unwrap();
            payload.extend_from_slice(&buf[..n]);
        }
        let mut block = [0u8; 64];
        let n = encode_block(self.seq, &payload, &mut block).unwrap();
        self.seq = (self.seq + 1) & 0x0F;
        self.slave.write_all(&block[..n]).unwrap();
    }

    /// Reads until a response named `name` arrives; returns its ints and bytes. A shutdown
    /// fails the test.
    pub fn wait_for(&mut self, name: &str) -> (Vec<i64>, Vec<u8>) {
        self.wait_for_any(name, false)
    }

    /// Reads until the MCU reports its shutdown; returns `[clock, static_string_id]`.
    pub fn wait_for_shutdown(&mut self) -> Vec<i64> {
        self.wait_for_any("shutdown", true).0
    }

    fn wait_for_any(&mut self, name: &str, shutdown_expected: bool) -> (Vec<i64>, Vec<u8>) {
        for _ in 0..200 {
            while let Frame::Block { len, .. } | Frame::Bad(len) | Frame::Skip(len) = find_block(&self.rx) {
                let block: Vec<u8> = self.rx.drain(..len).collect();
                if !matches!(find_block(&block), Frame::Block { .. }) {
                    panic!("bad block from the MCU: {block:?}");
                }
                let mut p = block_payload(&block);
                let mut found = None;
                while !p.is_empty() {
                    let (id, used) = vlq::decode(p).unwrap();
                    let fmt = self.responses[&id].clone();
                    let mut vals = [Value::Int(0); 8];
                    let (cnt, used2) = decode_params(&fmt, &p[used..], &mut vals).unwrap();
                    let mut ints = Vec::new();
                    let mut bytes = Vec::new();
                    for v in &vals[..cnt] {
                        match v {
                            Value::Int(i) => ints.push(*i),
                            Value::Bytes(b) => bytes.extend_from_slice(b),
                        }
                    }
                    assert!(
                        shutdown_expected || self.shutdown_ok || message_name(&fmt) != "shutdown",
                        "MCU shut down: {ints:?}"
                    );
                    if message_name(&fmt) == name && found.is_none() {
                        found = Some((ints, bytes));
                    }
                    p = &p[used + used2..];
                }
                if let Some(f) = found {
                    return f;
                }
            }
            let mut fds = [PollFd::new(self.slave.as_fd(), PollFlags::POLLIN)];
            poll(&mut fds, PollTimeout::from(100u16)).unwrap();
            let mut buf = [0u8; 256];
            if fds[0].revents().is_some_and(|r| r.contains(PollFlags::POLLIN)) {
                let n = self.slave.read(&mut buf).unwrap();
                self.rx.extend_from_slice(&buf[..n]);
            }
        }
        panic!("no `{name}` response from the MCU");
    }

    pub fn identify(&mut self) {
        self.responses
            .insert(0, links::proto::FMT_IDENTIFY_RESPONSE.into());
        self.commands
            .insert("identify".into(), (1, links::proto::FMT_IDENTIFY.into()));
        let mut data = Vec::new();
        loop {
            self.send(&[("identify", &[data.len() as i64, 40])]);
            let (ints, bytes) = self.wait_for("identify_response");
            assert_eq!(ints[0], data.len() as i64);
            if bytes.is_empty() {
                break;
            }
            data.extend_from_slice(&bytes);
        }
        let mut text = String::new();
        flate2::read::ZlibDecoder::new(&data[..])
            .read_to_string(&mut text)
            .unwrap();
        let dict: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(dict["config"]["CLOCK_FREQ"], FREQ);
        for (fmt, id) in dict["commands"].as_object().unwrap() {
            let id = id.as_u64().unwrap() as u32;
            self.commands.insert(message_name(fmt).into(), (id, fmt.clone()));
        }
        for (fmt, id) in dict["responses"].as_object().unwrap() {
            self.responses.insert(id.as_u64().unwrap() as u32, fmt.clone());
        }
    }

    pub fn clock(&mut self) -> u64 {
        self.send(&[("get_clock", &[])]);
        self.wait_for("clock").0[0] as u64
    }
}

/// Starts `cadence-mcu --clock-freq FREQ` with `args` and opens its pty.
pub fn spawn_with(args: &[&std::ffi::OsStr]) -> Host {
    let mut child = Command::new(env!("CARGO_BIN_EXE_cadence-mcu"))
        .args(["--clock-freq", &FREQ.to_string()])
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let path = line
        .trim()
        .strip_prefix("cadence-mcu: pty ")
        .expect("pty line")
        .to_owned();
    let slave = OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags(libc::O_NOCTTY)
        .open(&path)
        .unwrap();
    Host {
        child,
        path,
        shutdown_ok: false,
        slave,
        seq: 0,
        rx: Vec::new(),
        commands: HashMap::new(),
        responses: HashMap::new(),
    }
}

impl Host {
    /// Closes the pty and waits for the MCU to exit; returns its stderr.
    pub fn close(self) -> String {
        let Host { mut child, slave, .. } = self;
        drop(slave);
        for _ in 0..200 {
            if child.try_wait().ok().flatten().is_some() {
                let mut stderr = String::new();
                if let Some(mut e) = child.stderr.take() {
                    let _ = e.read_to_string(&mut stderr);
                }
                return stderr;
            }
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        let _ = child.kill();
        panic!("cadence-mcu did not exit after the pty was closed");
    }
}
