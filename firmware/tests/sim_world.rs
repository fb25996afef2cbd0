//! Two `cadence-mcu` processes in one simulated world: a stepper on one MCU drives axis `z`, an
//! endstop on the other MCU watches it. The test plays the host: it homes `z` across both MCUs
//! (trsync on each, the endstop's trigger relayed to the stepper MCU) and checks that the
//! endstop saw the other process's stepper, that the stepper stopped, and the trigger records.
//! Margins are generous (the move is 1 s long, the trigger comes after 50 ms of it); nothing
//! asserts on wall-clock durations.

mod common;

use common::{spawn_with, FREQ};
use firmware::trace::read_trace;
use std::ffi::OsStr;

#[test]
fn a_stepper_on_one_mcu_trips_an_endstop_on_another() {
    let id = format!("it-{}", std::process::id());
    let trace = std::env::temp_dir().join(format!("cadence-world-{id}.bin"));
    let a: &[&OsStr] = &[
        "--world".as_ref(),
        id.as_ref(),
        "--axis".as_ref(),
        "z=PA2,100,10".as_ref(),
    ];
    let b: &[&OsStr] = &[
        "--world".as_ref(),
        id.as_ref(),
        "--endstop".as_ref(),
        "PA5=z,10.5,max".as_ref(),
        "--trace".as_ref(),
        trace.as_os_str(),
    ];
    let mut stepper = spawn_with(a);
    let mut endstop = spawn_with(b);
    stepper.identify();
    endstop.identify();
    stepper.send(&[("allocate_oids", &[2])]);
    stepper.send(&[("config_stepper", &[0, 2, 3, 0, 2]), ("config_trsync", &[1])]);
    stepper.send(&[("finalize_config", &[1]), ("get_config", &[])]);
    assert_eq!(stepper.wait_for("config").0[0], 1);
    endstop.send(&[("allocate_oids", &[2])]);
    endstop.send(&[("config_trsync", &[0]), ("config_endstop", &[1, 5, 0])]);
    endstop.send(&[("finalize_config", &[1]), ("get_config", &[])]);
    assert_eq!(endstop.wait_for("config").0[0], 1);

    endstop.send(&[("endstop_query_state", &[1])]);
    assert_eq!(
        endstop.wait_for("endstop_state").0,
        [1, 0, 0, 0],
        "z at 10 mm: open"
    );

    // 1000 steps of 10 µm, 1 ms apart, from 10 mm up: the endstop (10.5 mm) trips at step 50.
    let start_b = endstop.clock() + FREQ / 5;
    endstop.send(&[("trsync_start", &[0, 0, 0, 4])]);
    endstop.send(&[("endstop_home", &[1, start_b as u32 as i64, 15, 4, 100, 1, 0, 1])]);
    let start_a = stepper.clock() + FREQ / 2;
    stepper.send(&[
        ("trsync_start", &[1, 0, 0, 4]),
        ("stepper_stop_on_trigger", &[0, 1]),
        ("reset_step_clock", &[0, start_a as u32 as i64]),
        ("set_next_step_dir", &[0, 1]),
        ("queue_step", &[0, 1000, 1000, 0]),
    ]);
    let (state, _) = endstop.wait_for("trsync_state");
    assert_eq!(
        state[..3],
        [0, 0, 1],
        "endstop MCU's trsync triggered by the endstop"
    );
    stepper.send(&[("trsync_trigger", &[1, 1])]);
    let (state, _) = stepper.wait_for("trsync_state");
    assert_eq!(
        state[..3],
        [1, 0, 1],
        "stepper MCU's trsync triggered by the relay"
    );
    stepper.send(&[("stepper_get_position", &[0])]);
    let pos = stepper.wait_for("stepper_position").0[1];
    assert!(
        (50..1000).contains(&pos),
        "stopped after the trigger, before the end: {pos}"
    );
    endstop.send(&[("endstop_query_state", &[1])]);
    let (es, _) = endstop.wait_for("endstop_state");
    assert_eq!((es[1], es[3]), (0, 1), "homing over, pin reads triggered");
    // The stepper stays stopped.
    std::thread::sleep(std::time::Duration::from_millis(200));
    stepper.send(&[("stepper_get_position", &[0])]);
    assert_eq!(stepper.wait_for("stepper_position").0[1], pos);

    let stderr = stepper.close();
    assert!(stderr.contains("host closed the pty"), "{stderr}");
    endstop.close();
    let t = read_trace(&trace).unwrap();
    let _ = std::fs::remove_file(&trace);
    let _ = std::fs::remove_file(trace.with_extension("bin.epoch"));
    assert_eq!(t.triggers.len(), 2, "{:?}", t.triggers);
    assert!(t.triggers[0].endstop && t.triggers[0].oid == 1 && t.triggers[0].reason == 1);
    assert!(!t.triggers[1].endstop && t.triggers[1].oid == 0);
    assert_eq!(t.triggers[0].clock, t.triggers[1].clock);
    // Klipper's meaning: next_clock = first matching read + rest_ticks (100); the trigger
    // (the 4th matching read, 15 ticks apart) came 3 × 15 ticks after that first read.
    let first_match = (t.triggers[0].clock as u32).wrapping_sub(3 * 15);
    assert_eq!(
        es[2] as u32,
        first_match.wrapping_add(100),
        "next_clock − rest_ticks is the first matching read"
    );
}
