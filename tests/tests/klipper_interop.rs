//! Interoperability with Klipper that the normal suite can prove without Klipper: stream and
//! dictionary forms Klipper's host and build produce (the live exchanges with klippy are in
//! scripts/klipper-interop; the MCU-side regressions are the firmware's scripted exchanges).

use std::time::Duration;

use cadence_tests::{cadence, scratch, workspace};
use links::dict::{Dictionary, FieldValue, Message};
use links::proto::block::encode_block;

const TIMEOUT: Duration = Duration::from_secs(120);

/// Rewrites a Cadence batch stream the way Klipper's host writes one: each stepper's first
/// `queue_step` comes before any `reset_step_clock`, its interval counted from clock 0 (the
/// MCU's step clock after `config_stepper`). Returns the stream and how many steppers changed.
fn klipper_style(dict: &Dictionary, stream: &[u8]) -> (Vec<u8>, usize) {
    let mut pending_reset: std::collections::HashMap<i64, i64> = Default::default();
    let mut seen: std::collections::HashSet<i64> = Default::default();
    let mut changed = 0;
    let mut out = Vec::new();
    let mut seq = 0u8;
    for item in dict.decode_stream(stream, true) {
        let links::dict::StreamItem::Block { messages, .. } = item else {
            continue;
        };
        let mut payload = Vec::new();
        for m in messages {
            let oid = m.get("oid").unwrap_or(-1);
            let mut m: Message = m;
            match m.name.as_str() {
                "reset_step_clock" if !seen.contains(&oid) => {
                    pending_reset.insert(oid, m.get("clock").unwrap());
                    continue;
                }
                "queue_step" if !seen.contains(&oid) => {
                    seen.insert(oid);
                    if let Some(clock) = pending_reset.remove(&oid) {
                        for (name, v) in &mut m.fields {
                            if name == "interval" {
                                if let FieldValue::Int(i) = v {
                                    *i += clock;
                                }
                            }
                        }
                        changed += 1;
                    }
                }
                _ => {}
            }
            let args: Vec<i64> = m
                .fields
                .iter()
                .map(|(_, v)| match v {
                    FieldValue::Int(i) => *i,
                    FieldValue::Bytes(_) => panic!("no byte fields in a batch stream"),
                })
                .collect();
            let cmd = dict.encode(&m.name, &args).unwrap();
            if payload.len() + cmd.len() > links::proto::MESSAGE_PAYLOAD_MAX {
                push_block(&mut out, &mut seq, &payload);
                payload.clear();
            }
            payload.extend_from_slice(cmd.as_bytes());
        }
        if !payload.is_empty() {
            push_block(&mut out, &mut seq, &payload);
        }
    }
    (out, changed)
}

fn push_block(out: &mut Vec<u8>, seq: &mut u8, payload: &[u8]) {
    let mut block = [0u8; 64];
    let n = encode_block(*seq, payload, &mut block).unwrap();
    out.extend_from_slice(&block[..n]);
    *seq = (*seq + 1) & 0x0F;
}

/// `decode --check` refused a Klipper stream ("queue_step before any reset_step_clock"):
/// Klipper's host sends each stepper's first interval counted from 0. The same steps written
/// that way must prove as the Cadence form does; and `--dictionary` takes the plain JSON
/// Klipper's build writes (`out/klipper.dict`) as well as zlib.
#[test]
fn decode_check_proves_a_klipper_style_stream_with_a_plain_json_dictionary() {
    let dir = scratch("klipper-style");
    let g = workspace().join("examples/square.gcode");
    let out = dir.join("square.bin");
    let (g_s, out_s) = (g.to_str().unwrap(), out.to_str().unwrap());
    let run = cadence(&["print", g_s, "--batch", out_s], TIMEOUT);
    assert_eq!(run.code, Some(0), "{}", run.stderr);

    let dict = Dictionary::from_compressed(&firmware::dictionary_bytes(50_000_000)).unwrap();
    let (stream, changed) = klipper_style(&dict, &std::fs::read(&out).unwrap());
    assert_eq!(
        changed, 4,
        "every stepper's first reset folded into its first interval"
    );
    let kstream = dir.join("square-klipper-style.bin");
    std::fs::write(&kstream, &stream).unwrap();
    let json = dir.join("cadence.dict");
    std::fs::write(&json, firmware::dict::dictionary_json(50_000_000).to_string()).unwrap();

    let run = cadence(
        &[
            "decode",
            kstream.to_str().unwrap(),
            "--check",
            g_s,
            "--dictionary",
            json.to_str().unwrap(),
        ],
        TIMEOUT,
    );
    assert_eq!(run.code, Some(0), "{}\n{}", run.stdout, run.stderr);
    for name in ["stepper_x", "stepper_y", "stepper_z", "extruder"] {
        assert!(
            run.stdout
                .lines()
                .any(|l| l.contains(name) && l.ends_with(": ok")),
            "{name}:\n{}",
            run.stdout
        );
    }
    // The plain decode with the JSON dictionary: the absolute first intervals are there.
    let run = cadence(
        &[
            "decode",
            kstream.to_str().unwrap(),
            "--dictionary",
            json.to_str().unwrap(),
        ],
        TIMEOUT,
    );
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    let first_qs = run.stdout.lines().find(|l| l.starts_with("queue_step")).unwrap();
    let interval: i64 = first_qs
        .split_whitespace()
        .find_map(|f| f.strip_prefix("interval="))
        .unwrap()
        .parse()
        .unwrap();
    assert!(interval > 1_000_000, "an absolute first interval: {first_qs}");
    // A dictionary file that is neither form is refused by name.
    let bad = dir.join("bad.dict");
    std::fs::write(&bad, "not a dictionary").unwrap();
    let run = cadence(&["decode", out_s, "--dictionary", bad.to_str().unwrap()], TIMEOUT);
    assert_eq!(run.code, Some(1), "{}", run.stdout);
    assert!(
        run.stderr.contains("bad.dict") && run.stderr.contains("neither JSON"),
        "{}",
        run.stderr
    );
}

/// The configuration Cadence sends names endstops before steppers, as Klipper's host does:
/// Klipper's Linux-process MCU without GPIO crashed (SIGSEGV) on a first `config_stepper` it
/// could not set up, where a first `config_endstop` gives a clean shutdown with its reason.
#[test]
fn configuration_sends_endstops_before_steppers() {
    let dir = scratch("config-order");
    let out = dir.join("square.bin");
    let g = workspace().join("examples/square.gcode");
    let run = cadence(
        &["print", g.to_str().unwrap(), "--batch", out.to_str().unwrap()],
        TIMEOUT,
    );
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    let run = cadence(&["decode", out.to_str().unwrap()], TIMEOUT);
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    let names: Vec<&str> = run
        .stdout
        .lines()
        .map(|l| l.split_whitespace().next().unwrap_or(""))
        .take_while(|n| *n != "finalize_config")
        .collect();
    let first = |n: &str| {
        names
            .iter()
            .position(|x| *x == n)
            .unwrap_or_else(|| panic!("no {n}: {names:?}"))
    };
    assert_eq!(names[0], "allocate_oids");
    assert!(first("config_endstop") < first("config_stepper"), "{names:?}");
    assert!(first("config_trsync") < first("config_stepper"), "{names:?}");
    let last_endstop = names.iter().rposition(|x| *x == "config_endstop").unwrap();
    assert!(last_endstop < first("config_stepper"), "{names:?}");
}

/// A board keeps its state between host runs: an MCU left shut down, or configured, by an
/// earlier host is restarted the way Klipper's FIRMWARE_RESTART does it (`emergency_stop`,
/// `config_reset`), saying why (with the MCU's shutdown reason when it was heard), then
/// configured afresh (Cadence used to refuse both: "restart the MCU"). A `cadence-mcu
/// --keep-open` on a pty is shut down by a first host's `emergency_stop`; then two `cadence
/// print` runs connect to it as to a board: the first finds it shut down, the second
/// configured by the first.
#[test]
fn an_mcu_left_shut_down_or_configured_by_an_earlier_run_is_restarted() {
    use std::io::{BufRead, BufReader, Write};
    use std::os::unix::fs::OpenOptionsExt;
    let dir = scratch("earlier-run-mcu");
    let pty = dir.join("mcu.pty");
    let mut mcu = std::process::Command::new(cadence_tests::bin("cadence-mcu"))
        .args(["--keep-open", "--pty-link", pty.to_str().unwrap()])
        .args(["--heater", "PE0=PF0,hotend", "--heater", "PE1=PF1,bed"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(mcu.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    {
        let mut slave = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags(libc_o_noctty())
            .open(&pty)
            .unwrap();
        let dict = Dictionary::from_compressed(&firmware::dictionary_bytes(50_000_000)).unwrap();
        let stop = dict.encode("emergency_stop", &[]).unwrap();
        let mut block = [0u8; 64];
        let n = encode_block(0, stop.as_bytes(), &mut block).unwrap();
        slave.write_all(&block[..n]).unwrap();
        // Let the MCU read it before the hang-up.
        std::thread::sleep(Duration::from_millis(300));
    }
    let cfg = dir.join("printer.cfg");
    let text = std::fs::read_to_string(workspace().join("examples/simulated-cartesian.cfg"))
        .unwrap()
        .replace("serial: simulator", &format!("serial: {}", pty.display()));
    std::fs::write(&cfg, text).unwrap();
    let gcode = dir.join("wait.gcode");
    std::fs::write(&gcode, "G4 P50\nM400\n").unwrap();
    let print = || {
        cadence(
            &[
                "print",
                gcode.to_str().unwrap(),
                "--config",
                cfg.to_str().unwrap(),
                "--no-realtime",
                "--no-progress",
            ],
            TIMEOUT,
        )
    };
    let first = print();
    let second = print();
    let _ = mcu.kill();
    let _ = mcu.wait();
    assert_eq!(first.code, Some(0), "{}\n{}", first.stdout, first.stderr);
    assert!(
        first.stderr.contains(
            "cadence: mcu 'mcu' was shut down by an earlier run: restarting it (emergency_stop, \
             config_reset)"
        ),
        "{}",
        first.stderr
    );
    assert_eq!(second.code, Some(0), "{}\n{}", second.stdout, second.stderr);
    assert!(
        second.stderr.contains(
            "cadence: mcu 'mcu' was configured by an earlier run (with this printer.cfg's configuration"
        ),
        "{}",
        second.stderr
    );
}

fn libc_o_noctty() -> i32 {
    nix::fcntl::OFlag::O_NOCTTY.bits()
}

/// Opt-in: the conformance harness against a real Klipper tree named by
/// `CADENCE_KLIPPER_SRC` (`CADENCE_KLIPPER_ONLY` picks scenarios, as its `--only`;
/// `CADENCE_SIMULAVR`, a simulavr tree with its Python module, for the AVR one). Skipped,
/// saying so, when the variable is unset: the normal suite never needs Klipper. Every row of
/// the harness's table must be PASS or BLOCKED.
#[test]
fn harness_against_real_klipper() {
    let Ok(src) = std::env::var("CADENCE_KLIPPER_SRC") else {
        eprintln!("skipped: set CADENCE_KLIPPER_SRC to a Klipper source tree to run the harness");
        return;
    };
    let bins = cadence_tests::bin("cadence-mcu").parent().unwrap().to_path_buf();
    let work = scratch("klipper-harness");
    let mut cmd = std::process::Command::new("python3");
    cmd.arg(workspace().join("scripts/klipper-interop/interop.py"))
        .args(["--klipper", &src, "--bin-dir", bins.to_str().unwrap()])
        .args(["--work", work.to_str().unwrap()]);
    if let Ok(only) = std::env::var("CADENCE_KLIPPER_ONLY") {
        cmd.args(["--only", &only]);
    }
    let run = cadence_tests::run(&mut cmd, Duration::from_secs(3 * 3600));
    println!("{}", run.stdout);
    let rows: Vec<&str> = run
        .stdout
        .lines()
        .filter(|l| l.starts_with("| "))
        .skip(1)
        .collect();
    assert!(!rows.is_empty(), "no table:\n{}\n{}", run.stdout, run.stderr);
    let failed: Vec<&&str> = rows.iter().filter(|r| r.contains("| FAIL ")).collect();
    assert!(failed.is_empty(), "{failed:#?}\n{}", run.stderr);
    assert_eq!(run.code, Some(0), "{}", run.stderr);
}
