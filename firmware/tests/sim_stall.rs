//! A stalled `cadence-mcu` takes the input its host sent meanwhile before the timers that fell
//! due: the process is stopped (SIGSTOP) with a trsync armed to expire 1 s later, the host
//! renews the expiry while the MCU is stopped (well before the old expiry), and the MCU is let
//! go after the old expiry has passed. A board's UART would have received the renewal in time,
//! so the trsync must not have expired. Before the fix the loop ran its late timers first when
//! it came back from a stall in its spin phase, and under Klipper's host a cadence-mcu stalled
//! by a busy machine expired trsyncs (“Communication timeout during homing”) and refused a
//! queue_step as “Timer too close”. Timeouts only guard against hangs: the one timing premise
//! (the renewal written before the old expiry) is checked, and the exchange retried if this
//! machine was too busy to meet it.

mod common;

use common::{spawn_with, FREQ};
use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;
use std::time::{Duration, Instant};

const OID: i64 = 0;
const STEPPER: i64 = 1;
const REASON_HOST_REQUEST: i64 = 2;
const REASON_COMMS_TIMEOUT: i64 = 4;

#[test]
fn a_renewal_sent_while_the_mcu_was_stalled_is_taken_before_the_old_expiry() {
    // Busy-waiting allowed for up to 100 ms in a row, and a stepper stepping every 20 µs
    // throughout: the loop spends its time in its spin phase, where the stop lands.
    let mut host = spawn_with(&["--spin-us".as_ref(), "100000".as_ref()]);
    host.identify();
    host.send(&[("allocate_oids", &[2])]);
    host.send(&[("config_trsync", &[OID])]);
    host.send(&[("config_stepper", &[STEPPER, 0, 1, 0, 2])]);
    host.send(&[("finalize_config", &[7])]);
    let pid = Pid::from_raw(host.child.id() as i32);
    let mut premise_met = false;
    for _attempt in 0..5 {
        let t0 = Instant::now();
        let now = host.clock();
        host.send(&[("reset_step_clock", &[STEPPER, (now + FREQ / 10) as u32 as i64])]);
        for _ in 0..4 {
            host.send(&[("queue_step", &[STEPPER, 20, 60_000, 0])]); // 1.2 s each
        }
        // Armed, no periodic reports, expiring 1 s after `now` unless renewed.
        host.send(&[
            ("trsync_start", &[OID, now as u32 as i64, 0, REASON_COMMS_TIMEOUT]),
            ("trsync_set_timeout", &[OID, (now + FREQ) as u32 as i64]),
        ]);
        host.clock(); // both commands are in effect
        kill(pid, Signal::SIGSTOP).unwrap();
        host.send(&[("trsync_set_timeout", &[OID, (now + 60 * FREQ) as u32 as i64])]);
        let renewed_in_time = t0.elapsed() < Duration::from_millis(600);
        std::thread::sleep(Duration::from_millis(1500)); // past the old expiry
        kill(pid, Signal::SIGCONT).unwrap();
        host.send(&[("trsync_trigger", &[OID, REASON_HOST_REQUEST])]);
        let (state, _) = host.wait_for("trsync_state");
        if !renewed_in_time {
            // Too busy to write the renewal before the old expiry: no verdict, try again.
            host.clock(); // the stale reports are read and dropped
            continue;
        }
        premise_met = true;
        assert_eq!(
            state[..3],
            [OID, 0, REASON_HOST_REQUEST],
            "the first trsync_state after the stall must answer the host's trsync_trigger (can_trigger=0, reason 2); \
             reason {REASON_COMMS_TIMEOUT} means the trsync expired although its renewal was waiting"
        );
        break;
    }
    assert!(
        premise_met,
        "this machine never wrote the renewal within 600 ms of arming"
    );
    let stderr = host.close();
    assert!(!stderr.contains("shutdown"), "{stderr}");
}
