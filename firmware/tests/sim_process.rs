//! End to end: spawn `cadence-mcu`, talk to it over its pty like a host (identify, config,
//! queue_step with a comfortable lead), close the pty, and check the step trace it wrote.
//! Timeouts here only guard against hangs; nothing asserts on wall-clock durations.

mod common;

use common::{spawn_with, Host, FREQ};
use firmware::trace::{read_trace, TraceRecord};
use std::io::Read;
use std::time::Duration;

fn spawn(trace: &std::path::Path) -> Host {
    spawn_with(&[
        "--move-count".as_ref(),
        "100".as_ref(),
        "--trace".as_ref(),
        trace.as_os_str(),
    ])
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
    let _ = std::fs::remove_file(firmware::sim::epoch_path(&trace));
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

/// A real-time request the OS refuses (a core that does not exist) is reported once on stderr
/// and the simulator still serves the host.
#[test]
fn refused_real_time_falls_back_and_says_so_once() {
    let mut host = spawn_with(&[
        "--cpu".as_ref(),
        "1000".as_ref(),
        "--spin-us".as_ref(),
        "0".as_ref(),
    ]);
    host.identify();
    host.send(&[("get_config", &[])]);
    assert_eq!(host.wait_for("config").0[0], 0);
    let stderr = host.close();
    let refusals: Vec<&str> = stderr.lines().filter(|l| l.contains("realtime:")).collect();
    assert_eq!(refusals.len(), 1, "{stderr}");
    assert!(refusals[0].contains("core 1000"), "{stderr}");
    assert!(refusals[0].ends_with("running unpinned"), "{stderr}");
    assert!(stderr.contains("host closed the pty"), "{stderr}");
}

/// `--keep-open`: the host closing the pty does not end the MCU, whose state is kept for the
/// next host (Klipper's host reopens the port for RESTART and FIRMWARE_RESTART); the next host
/// can `config_reset` it after a shutdown and configure it again.
#[test]
fn keep_open_serves_the_next_host() {
    let mut host = spawn_with(&["--keep-open".as_ref(), "--move-count".as_ref(), "100".as_ref()]);
    host.identify();
    host.send(&[("allocate_oids", &[1])]);
    host.send(&[("config_stepper", &[0, 0, 1, 0, 2])]);
    host.send(&[("finalize_config", &[77]), ("get_config", &[])]);
    assert_eq!(host.wait_for("config").0, [1, 77, 0, 100]);
    // Hang up, wait a little (the MCU must notice), open the pty again.
    let reopen = |host: &mut Host| {
        use std::os::unix::fs::OpenOptionsExt;
        let slave = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags(libc::O_NOCTTY)
            .open(&host.path)
            .unwrap();
        host.slave = slave;
        host.rx.clear();
    };
    let dummy = std::fs::File::open("/dev/null").unwrap();
    drop(std::mem::replace(&mut host.slave, dummy));
    std::thread::sleep(Duration::from_millis(300));
    assert!(
        host.child.try_wait().unwrap().is_none(),
        "the MCU exited on the hang-up"
    );
    reopen(&mut host);
    host.send(&[("get_config", &[])]);
    assert_eq!(
        host.wait_for("config").0,
        [1, 77, 0, 100],
        "state kept across hosts"
    );
    host.shutdown_ok = true;
    host.send(&[
        ("emergency_stop", &[]),
        ("config_reset", &[]),
        ("get_config", &[]),
    ]);
    assert_eq!(host.wait_for("config").0, [0, 0, 0, 100]);
    let _ = host.child.kill();
    let _ = host.child.wait();
}
