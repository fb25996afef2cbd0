//! End to end: spawn `cadence-mcu`, talk to it over its pty like a host (identify, config,
//! queue_step with a comfortable lead), close the pty, and check the step trace it wrote.
//! Timeouts here only guard against hangs; nothing asserts on wall-clock durations.

use firmware::trace::{read_trace, TraceRecord};
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
use std::time::Duration;

const FREQ: u64 = 1_000_000;

struct Host {
    child: Child,
    slave: File,
    seq: u8,
    rx: Vec<u8>,
    commands: HashMap<String, (u32, String)>,
    responses: HashMap<u32, String>,
}

impl Host {
    fn send(&mut self, msgs: &[(&str, &[i64])]) {
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

    /// Reads until a response named `name` arrives; returns its ints and bytes.
    fn wait_for(&mut self, name: &str) -> (Vec<i64>, Vec<u8>) {
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
                    assert_ne!(message_name(&fmt), "shutdown", "MCU shut down: {ints:?}");
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

    fn identify(&mut self) {
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

    fn clock(&mut self) -> u64 {
        self.send(&[("get_clock", &[])]);
        self.wait_for("clock").0[0] as u64
    }
}

fn spawn(trace: &std::path::Path) -> Host {
    let mut child = Command::new(env!("CARGO_BIN_EXE_cadence-mcu"))
        .args([
            "--clock-freq",
            &FREQ.to_string(),
            "--move-count",
            "100",
            "--trace",
        ])
        .arg(trace)
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
        slave,
        seq: 0,
        rx: Vec::new(),
        commands: HashMap::new(),
        responses: HashMap::new(),
    }
}

#[test]
fn identify_config_steps_and_trace() {
    let trace = std::env::temp_dir().join(format!("cadence-mcu-it-{}.bin", std::process::id()));
    let mut host = spawn(&trace);
    host.identify();
    host.send(&[("get_config", &[])]);
    assert_eq!(host.wait_for("config").0, [0, 0, 0, 100]);
    host.send(&[("allocate_oids", &[1])]);
    host.send(&[("config_stepper", &[0, 0, 1, 0, 2])]);
    host.send(&[("finalize_config", &[1234]), ("get_config", &[])]);
    assert_eq!(host.wait_for("config").0, [1, 1234, 0, 100]);

    // 1.5 s of lead: far more than a loaded machine needs to deliver three blocks.
    let base = host.clock() + 3 * FREQ / 2;
    let moves: [(u32, u16, i16, bool); 3] = [(1000, 10, 0, true), (2000, 5, 10, true), (500, 3, 0, false)];
    host.send(&[("reset_step_clock", &[0, base as u32 as i64])]);
    for &(interval, count, add, dir) in &moves {
        host.send(&[
            ("set_next_step_dir", &[0, dir as i64]),
            ("queue_step", &[0, interval as i64, count as i64, add as i64]),
        ]);
    }
    let mut expect = Vec::new();
    let mut last = base;
    for &(interval, count, add, dir) in &moves {
        let mut i = interval as i64;
        for _ in 0..count {
            last = (last as i64 + i) as u64;
            expect.push((last, dir as u8));
            i += add as i64;
        }
    }
    for _ in 0..100 {
        if host.clock() > last {
            break;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    host.send(&[("stepper_get_position", &[0])]);
    assert_eq!(host.wait_for("stepper_position").0, [0, 12]);

    // Closing the pty ends the MCU, which flushes its trace.
    let Host { mut child, slave, .. } = host;
    drop(slave);
    let mut status = None;
    for _ in 0..200 {
        status = child.try_wait().unwrap();
        if status.is_some() {
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let Some(status) = status else {
        let _ = child.kill();
        panic!("cadence-mcu did not exit after the pty was closed");
    };
    let mut stderr = String::new();
    child.stderr.take().unwrap().read_to_string(&mut stderr).unwrap();
    assert!(status.success(), "exit {status:?}: {stderr}");
    assert!(
        stderr.contains("host closed the pty") && stderr.contains("p99.9="),
        "{stderr}"
    );

    let t = read_trace(&trace).unwrap();
    let _ = std::fs::remove_file(&trace);
    assert_eq!((t.clock_freq, t.time_scale), (FREQ, 1.0));
    let mut steps = Vec::new();
    let mut queued = Vec::new();
    for r in &t.records {
        match *r {
            TraceRecord::Step { clock, dir, .. } => steps.push((clock, dir as u8)),
            TraceRecord::QueueStep {
                received_clock,
                first_step_clock,
                ..
            } => queued.push((received_clock, first_step_clock)),
            TraceRecord::Shutdown { .. } => panic!("the MCU shut down: {r:?}"),
        }
    }
    assert_eq!(steps, expect);
    assert_eq!(queued.len(), 3);
    assert!(
        queued.iter().all(|(recv, first)| first > recv),
        "every queue_step arrived ahead of its first step: {queued:?}"
    );
    // The first step of each move, as the firmware computed it on receipt (µs resolution).
    let firsts = [expect[0].0, expect[10].0, expect[15].0];
    for ((_, first), want) in queued.iter().zip(firsts) {
        assert_eq!(*first, want);
    }
}
