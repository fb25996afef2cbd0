//! Trigger dispatch between two fake MCUs on in-memory links. Bounds are generous upper
//! limits (a loaded machine cannot make them flake); nothing asserts how long anything took.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::*;
use crate::mcu::fake::{Control, FakeMcu};
use crate::mcu::{LinkOptions, McuLink};
use crate::transport::MemoryPair;

const NOMINAL: f64 = 50e6;
const LONG: Duration = Duration::from_secs(20);
const ID_SET_TIMEOUT: u32 = 30;
const ID_TRIGGER: u32 = 31;

fn start(name: &str) -> (McuLink, Arc<Control>, std::thread::JoinHandle<()>) {
    let (host, mcu) = MemoryPair::new();
    let (ctl, fake) = FakeMcu::spawn(Box::new(mcu), NOMINAL, NOMINAL, 1_000);
    let opts = LinkOptions {
        name: name.into(),
        identify_timeout: Duration::from_secs(10),
        response_timeout: Duration::from_secs(10),
        queue_capacity: 64,
    };
    (
        McuLink::connect(Box::new(host), opts).expect("connect"),
        ctl,
        fake,
    )
}

/// Waits (bounded) until the fake logged a trsync command matching `want`.
fn wait_logged(ctl: &Control, want: impl Fn(&(u32, i64, i64)) -> bool) -> (u32, i64, i64) {
    let deadline = Instant::now() + LONG;
    loop {
        if let Some(x) = ctl.trsync_log.lock().unwrap().iter().find(|x| want(x)) {
            return *x;
        }
        assert!(Instant::now() < deadline, "{:?}", ctl.trsync_log.lock().unwrap());
        std::thread::sleep(Duration::from_millis(1));
    }
}

fn report(ctl: &Control, oid: i64, can_trigger: bool, reason: i64, clock: i64) {
    ctl.send_states
        .lock()
        .unwrap()
        .push([oid, can_trigger as i64, reason, clock]);
}

#[test]
fn a_trigger_on_one_mcu_reaches_the_other() {
    let (a, ctl_a, fake_a) = start("endstop_mcu");
    let (b, ctl_b, fake_b) = start("stepper_mcu");
    // A long timeout: this test is about the relay, not about silence.
    let group = TriggerGroup::new(&[(&a, 3), (&b, 5)], 5.0).unwrap();
    let wire = 0xFFFF_FF00u32 as i64;
    report(&ctl_a, 3, false, REASON_ENDSTOP_HIT as i64, wire);
    let got = wait_logged(&ctl_b, |x| x.0 == ID_TRIGGER);
    assert_eq!(got, (ID_TRIGGER, 5, REASON_ENDSTOP_HIT as i64));
    let outcome = group.wait(Instant::now() + LONG).unwrap();
    assert_eq!(outcome.mcu, "endstop_mcu");
    assert_eq!(outcome.reason, REASON_ENDSTOP_HIT);
    assert_eq!(outcome.trigger_clock as u32, wire as u32);
    // The triggering MCU itself is not told (it already stopped).
    assert!(ctl_a.trsync_log.lock().unwrap().iter().all(|x| x.0 != ID_TRIGGER));
    // A later trigger from the other MCU does not replace the first.
    report(&ctl_b, 5, false, REASON_HOST_REQUEST as i64, 7);
    std::thread::sleep(Duration::from_millis(50));
    assert_eq!(group.outcome(), Some(outcome));
    group.close();
    assert_eq!(a.shared().armed.load(Ordering::Acquire), 0);
    assert!(a.shared().trsyncs.read().unwrap().is_empty());
    drop((a, b));
    fake_a.join().unwrap();
    fake_b.join().unwrap();
}

#[test]
fn reports_extend_the_timeout() {
    let (a, ctl_a, fake_a) = start("a");
    let (b, _ctl_b, fake_b) = start("b");
    let timeout = 5.0;
    let group = TriggerGroup::new(&[(&a, 1), (&b, 2)], timeout).unwrap();
    report(&ctl_a, 1, true, 0, 123_456);
    let (_, oid, clock) = wait_logged(&ctl_a, |x| x.0 == ID_SET_TIMEOUT);
    assert_eq!(oid, 1);
    let ticks = (clock as u32).wrapping_sub(123_456) as f64;
    let expect = timeout * NOMINAL;
    assert!(
        (ticks / expect - 1.0).abs() < 0.1,
        "ticks {ticks} expected ≈ {expect}"
    );
    assert!(group.outcome().is_none());
    drop(group); // unregisters too
    assert_eq!(b.shared().armed.load(Ordering::Acquire), 0);
    drop((a, b));
    fake_a.join().unwrap();
    fake_b.join().unwrap();
}

#[test]
fn silence_is_a_communication_timeout() {
    let (a, ctl_a, fake_a) = start("a");
    let (b, ctl_b, fake_b) = start("b");
    let group = TriggerGroup::new(&[(&a, 1), (&b, 2)], TriggerGroup::default_timeout(2)).unwrap();
    // Nobody reports.
    let e = group.wait(Instant::now() + LONG).unwrap_err();
    assert_eq!(e.to_string(), "Communication timeout during homing");
    assert!(
        matches!(&e, TrsyncError::CommTimeout { detail, .. } if detail.contains("no report from") && detail.contains("members silent")),
        "{e:?}"
    );
    // Every member is stopped with the comms-timeout reason.
    let reason = REASON_COMMS_TIMEOUT as i64;
    assert_eq!(
        wait_logged(&ctl_a, |x| x.0 == ID_TRIGGER),
        (ID_TRIGGER, 1, reason)
    );
    assert_eq!(
        wait_logged(&ctl_b, |x| x.0 == ID_TRIGGER),
        (ID_TRIGGER, 2, reason)
    );
    group.close();
    drop((a, b));
    fake_a.join().unwrap();
    fake_b.join().unwrap();
}

#[test]
fn an_expired_trsync_is_a_communication_timeout() {
    let (a, ctl_a, fake_a) = start("a");
    let (b, ctl_b, fake_b) = start("b");
    let group = TriggerGroup::new(&[(&a, 1), (&b, 2)], 5.0).unwrap();
    report(&ctl_b, 2, false, REASON_COMMS_TIMEOUT as i64, 99);
    let e = group.wait(Instant::now() + LONG).unwrap_err();
    assert!(
        matches!(&e, TrsyncError::CommTimeout { mcu, detail } if mcu == "b" && detail.contains("reason 4")),
        "{e:?}"
    );
    assert_eq!(
        wait_logged(&ctl_a, |x| x.0 == ID_TRIGGER),
        (ID_TRIGGER, 1, REASON_COMMS_TIMEOUT as i64)
    );
    assert!(ctl_b.trsync_log.lock().unwrap().iter().all(|x| x.0 != ID_TRIGGER));
    group.close();
    drop((a, b));
    fake_a.join().unwrap();
    fake_b.join().unwrap();
}

#[test]
fn host_request_stops_every_member() {
    let (a, ctl_a, fake_a) = start("a");
    let group = TriggerGroup::new(&[(&a, 7)], 5.0).unwrap();
    group.trigger_all(REASON_HOST_REQUEST);
    assert_eq!(
        wait_logged(&ctl_a, |x| x.0 == ID_TRIGGER),
        (ID_TRIGGER, 7, REASON_HOST_REQUEST as i64)
    );
    let o = group.wait(Instant::now() + LONG).unwrap();
    assert_eq!(o.reason, REASON_HOST_REQUEST);
    assert!(TriggerGroup::new(&[], 1.0).is_err());
    assert!(TriggerGroup::new(&[(&a, 7), (&a, 7)], 1.0).is_err());
    group.close();
    drop(a);
    fake_a.join().unwrap();
}

/// Polls (bounded) until member `i` of `group` has a trigger write time.
fn wait_written(group: &TriggerGroup, i: usize) -> f64 {
    let deadline = Instant::now() + LONG;
    loop {
        if let Some(t) = group.trigger_written_at(i) {
            return t;
        }
        assert!(Instant::now() < deadline, "member {i}: no trigger write time");
        std::thread::sleep(Duration::from_millis(1));
    }
}

#[test]
fn a_relayed_trigger_is_timestamped() {
    let (a, ctl_a, fake_a) = start("endstop_mcu");
    let (b, ctl_b, fake_b) = start("stepper_mcu");
    let group = TriggerGroup::new(&[(&a, 3), (&b, 5)], 5.0).unwrap();
    // Reports that only extend the timeout write urgent messages too: never a trigger time.
    report(&ctl_b, 5, true, 0, 1_000);
    wait_logged(&ctl_b, |x| x.0 == ID_SET_TIMEOUT);
    assert_eq!(group.trigger_written_at(1), None);
    let before = McuLink::system_now();
    report(&ctl_a, 3, false, REASON_ENDSTOP_HIT as i64, 2_000);
    let outcome = group.wait(Instant::now() + LONG).unwrap();
    wait_logged(&ctl_b, |x| x.0 == ID_TRIGGER);
    let written = wait_written(&group, 1);
    // Ordering only: report read, then the relay written, all after the report was sent.
    assert!(
        before <= outcome.received_at,
        "{before} > {}",
        outcome.received_at
    );
    assert!(
        outcome.received_at <= written,
        "{} > {written}",
        outcome.received_at
    );
    assert!(written <= McuLink::system_now());
    // The triggering MCU was told nothing; no such member.
    assert_eq!(group.trigger_written_at(0), None);
    assert_eq!(group.trigger_written_at(2), None);
    // A host stop afterwards reaches both; the relayed trigger's time stays the first write.
    group.trigger_all(REASON_HOST_REQUEST);
    let written_a = wait_written(&group, 0);
    assert!(written <= written_a);
    assert_eq!(group.trigger_written_at(1), Some(written));
    // The outcome (and its read time) is still the endstop's.
    assert_eq!(group.outcome(), Some(outcome));
    group.close();
    drop((a, b));
    fake_a.join().unwrap();
    fake_b.join().unwrap();
}
