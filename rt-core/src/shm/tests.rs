//! Tests of the shared-memory channels: layouts, no-loss round trip under back-pressure,
//! gap detection, the back-pressure bound, and a round trip between two processes.

use super::*;
use std::mem::{align_of, offset_of, size_of};
use std::time::Instant;

/// A per-test instance name so parallel tests and repeated runs never share a service.
fn instance(test: &str) -> String {
    format!("test-{}-{test}", std::process::id())
}

fn wait_for_subscribers<S: Service, T: Sequenced>(p: &ShmPublisher<S, T>, n: usize) {
    let start = Instant::now();
    while p.connect().unwrap() < n {
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "subscriber never connected"
        );
        std::thread::sleep(Duration::from_millis(1));
    }
}

#[test]
fn payload_layouts() {
    assert_eq!((size_of::<WireMsg>(), align_of::<WireMsg>()), (80, 8));
    assert_eq!(offset_of!(WireMsg, len), 16);
    assert_eq!(offset_of!(WireMsg, data), 17);
    assert_eq!(
        (size_of::<StepBatch>(), align_of::<StepBatch>()),
        (24 + 80 * BATCH_MSGS, 8)
    );
    assert_eq!(offset_of!(StepBatch, t_ns), 16);
    assert_eq!(offset_of!(StepBatch, msgs), 24);
    assert_eq!((size_of::<Telemetry>(), align_of::<Telemetry>()), (160, 8));
    assert_eq!(offset_of!(Telemetry, count), 24);
    assert_eq!(offset_of!(Telemetry, values), 32);
}

#[test]
fn wire_msg_and_batch_bounds() {
    assert!(WireMsg::new(0, 0, &[0; WIRE_MSG_DATA + 1]).is_none());
    let m = WireMsg::new(1, 2, &[7, 8, 9]).unwrap();
    assert_eq!(m.bytes(), &[7, 8, 9]);
    let mut b = StepBatch::default();
    for _ in 0..BATCH_MSGS {
        assert!(b.push(m));
    }
    assert!(!b.push(m));
    assert_eq!(b.messages().len(), BATCH_MSGS);
    b.count = u32::MAX; // corrupt: still no panic
    assert_eq!(b.messages().len(), BATCH_MSGS);
}

#[test]
fn service_names() {
    assert_eq!(steps_service_name("p1", "mcu"), "cadence/p1/mcu/mcu/steps");
    assert_eq!(telemetry_service_name("p1"), "cadence/p1/telemetry");
}

/// Sends `n` batches whose first message encodes the batch number.
fn publish<S: Service>(node: &Node<S>, name: &str, n: u64, cfg: &ChannelConfig) {
    let mut p = ShmPublisher::<S, StepBatch>::open(node, name, cfg).unwrap();
    wait_for_subscribers(&p, 1);
    for i in 0..n {
        let got = p
            .send_with(|b| {
                b.mcu = 1;
                b.push(WireMsg::new(i, i + 1, &i.to_le_bytes()).unwrap_or_default());
            })
            .unwrap();
        assert_eq!(got, 1);
    }
}

/// Receives `n` batches (slowly: a pause every 8), checking order and content.
fn consume<S: Service>(node: &Node<S>, name: &str, n: u64, cfg: &ChannelConfig) {
    let mut sub = ShmSubscriber::<S, StepBatch>::open(node, name, cfg).unwrap();
    let mut next = 0u64;
    let start = Instant::now();
    while next < n {
        assert!(start.elapsed() < Duration::from_secs(60), "stalled at {next}");
        let got = sub
            .recv_timeout_with(Duration::from_millis(100), |b| {
                (b.seq, b.count, b.messages().first().map(|m| m.req_clock))
            })
            .unwrap();
        if let Some((seq, count, req)) = got {
            assert_eq!((seq, count, req), (next, 1, Some(next + 1)));
            next += 1;
            if next.is_multiple_of(8) {
                std::thread::sleep(Duration::from_millis(2));
            }
        }
    }
}

#[test]
fn slow_subscriber_loses_nothing() {
    let name = steps_service_name(&instance("slow"), "mcu");
    let cfg = ChannelConfig {
        buffer: 4,
        ..ChannelConfig::steps()
    };
    let n = 300;
    let name2 = name.clone();
    let reader = std::thread::spawn(move || {
        let (node, _) = open_node::<ipc::Service>("reader").unwrap();
        consume(&node, &name2, n, &cfg);
    });
    let (node, _) = open_node::<ipc::Service>("writer").unwrap();
    publish(&node, &name, n, &cfg);
    reader.join().unwrap();
}

#[test]
fn backpressure_is_bounded() {
    let name = steps_service_name(&instance("bound"), "mcu");
    let cfg = ChannelConfig {
        buffer: 2,
        backpressure_timeout: Duration::from_millis(20),
        ..ChannelConfig::steps()
    };
    let (node, _) = open_node::<ipc::Service>("bound").unwrap();
    let sub = ShmSubscriber::<ipc::Service, StepBatch>::open(&node, &name, &cfg).unwrap();
    let mut p = ShmPublisher::<ipc::Service, StepBatch>::open(&node, &name, &cfg).unwrap();
    wait_for_subscribers(&p, 1);
    sub.connect().unwrap();
    let mut result = Ok(0);
    for _ in 0..4 {
        result = p.send_with(|_| {});
        if result.is_err() {
            break;
        }
    }
    match result {
        Err(ShmError::Backpressure { seq, .. }) => assert_eq!(seq, 2),
        other => panic!("expected back-pressure, got {other:?}"),
    }
}

#[test]
fn unconnected_full_subscriber_is_an_error_not_a_loss() {
    let name = steps_service_name(&instance("unconnected"), "mcu");
    let cfg = ChannelConfig {
        buffer: 2,
        ..ChannelConfig::steps()
    };
    let (node, _) = open_node::<ipc::Service>("unconnected").unwrap();
    let _sub = ShmSubscriber::<ipc::Service, StepBatch>::open(&node, &name, &cfg).unwrap();
    let mut p = ShmPublisher::<ipc::Service, StepBatch>::open(&node, &name, &cfg).unwrap();
    wait_for_subscribers(&p, 1);
    let mut result = Ok(0);
    for _ in 0..4 {
        result = p.send_with(|_| {});
        if result.is_err() {
            break;
        }
    }
    assert!(
        matches!(result, Err(ShmError::Undelivered { seq: 2, got: 0, .. })),
        "{result:?}"
    );
}

#[test]
fn overflowing_channel_reports_a_gap() {
    let name = telemetry_service_name(&instance("gap"));
    let cfg = ChannelConfig {
        buffer: 4,
        ..ChannelConfig::telemetry()
    };
    let (node, _) = open_node::<ipc::Service>("gap").unwrap();
    let mut sub = ShmSubscriber::<ipc::Service, Telemetry>::open(&node, &name, &cfg).unwrap();
    let mut p = ShmPublisher::<ipc::Service, Telemetry>::open(&node, &name, &cfg).unwrap();
    wait_for_subscribers(&p, 1);
    for _ in 0..10 {
        p.send_with(|t| t.kind = telemetry_kind::STATS).unwrap();
    }
    match sub.try_recv_with(|t| t.seq) {
        Err(ShmError::Gap { expected, got, .. }) => assert_eq!((expected, got), (0, 6)),
        other => panic!("expected a gap, got {other:?}"),
    }
    assert_eq!(sub.try_recv_with(|t| t.seq).unwrap(), Some(7));
}

const CHILD_ENV: &str = "CADENCE_SHM_TEST_CHILD";
const CROSS_PROCESS_BATCHES: u64 = 200;

/// The child half of `two_processes_lose_nothing`; does nothing unless spawned by it.
#[test]
fn two_process_child() {
    let Ok(name) = std::env::var(CHILD_ENV) else {
        return;
    };
    let (node, _) = open_node::<ipc::Service>("child").unwrap();
    consume(&node, &name, CROSS_PROCESS_BATCHES, &ChannelConfig::steps());
}

#[test]
fn two_processes_lose_nothing() {
    let name = steps_service_name(&instance("xproc"), "mcu");
    let exe = std::env::current_exe().unwrap();
    let mut child = std::process::Command::new(exe)
        .args([
            "--exact",
            "shm::tests::two_process_child",
            "--test-threads=1",
            "--quiet",
        ])
        .env(CHILD_ENV, &name)
        .stdout(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let (node, _) = open_node::<ipc::Service>("parent").unwrap();
    publish(&node, &name, CROSS_PROCESS_BATCHES, &ChannelConfig::steps());
    let status = child.wait().unwrap();
    assert!(status.success(), "child failed: {status}");
}

#[test]
fn access_hint_names_a_directory_this_user_cannot_write() {
    let root = std::env::temp_dir().join(format!("cadence-iox-hint-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    // Missing, then writable: no hint (iceoryx2 creates or uses them).
    assert_eq!(access_hint(&root), None);
    std::fs::create_dir_all(root.join("nodes")).unwrap();
    assert_eq!(access_hint(&root), None);
    assert!(
        std::fs::read_dir(root.join("nodes")).unwrap().next().is_none(),
        "probe file left behind"
    );
    // Read-only: root may write anyway (then no hint); any other user gets one.
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(root.join("nodes"), std::fs::Permissions::from_mode(0o500)).unwrap();
    let hint = access_hint(&root);
    let is_root = std::fs::metadata("/proc/self").map(|m| std::os::unix::fs::MetadataExt::uid(&m) == 0);
    if is_root.unwrap_or(false) {
        assert_eq!(hint, None);
    } else {
        let hint = hint.expect("a hint for a read-only nodes directory");
        assert!(hint.contains("nodes") && hint.contains("mode 500"), "{hint}");
    }
    std::fs::set_permissions(root.join("nodes"), std::fs::Permissions::from_mode(0o700)).unwrap();
    let _ = std::fs::remove_dir_all(&root);
}
