//! Installs the counting allocator and proves the RT-path pieces of rt-core allocate nothing
//! after warm-up: histogram recording, logger pushes, HandoffQueue hand-off.
#![cfg(feature = "std")]

use rt_core::alloc_count::{AllocCounter, CountingAlloc};
use rt_core::hist::LatencyHist;
use rt_core::logger::{Arg, Level, Logger, LoggerConfig};

#[global_allocator]
static ALLOC: CountingAlloc = CountingAlloc;

#[test]
fn counter_sees_allocations() {
    let before = AllocCounter::snapshot();
    let v: Vec<u64> = std::hint::black_box(Vec::with_capacity(16));
    drop(v);
    let d = AllocCounter::snapshot().since(before);
    assert_eq!(d.allocs, 1);
    assert_eq!(d.frees, 1);
}

#[test]
fn rt_loop_pieces_allocate_nothing() {
    let mut hist = LatencyHist::new();
    let (log, join) = Logger::start(LoggerConfig {
        stderr: false,
        capacity: 64,
        ..LoggerConfig::default()
    })
    .unwrap();
    let log = log.with_tag("test");
    let q = rt_core::handoff::HandoffQueue::<u64>::new(8);
    // Warm-up.
    hist.record(1);
    log.log(Level::Info, "warm", [Arg::U(0)]);
    let before = AllocCounter::snapshot();
    for i in 0..10_000u64 {
        hist.record(i * 37 % 1_000_000_000);
        hist.record_signed(-(i as i64));
        let _ = q.push(i);
        let _ = q.pop();
        log.log(Level::Info, "step", [Arg::U(i), Arg::F(0.5)]);
    }
    let d = AllocCounter::snapshot().since(before);
    assert_eq!(d.allocations(), 0, "{d:?}");
    log.shutdown();
    let _ = join.join();
}

/// Publishes and receives `n` step batches on `name` (publisher of service type `P`, subscriber
/// of `ipc::Service`, as the IO process uses) after 8 warm-up batches; returns the calling
/// thread's allocations during the `n`.
fn shm_round_trips<P: iceoryx2::service::Service>(tag: &str, n: u64) -> u64 {
    use iceoryx2::prelude::ipc;
    use rt_core::shm::{open_node, ChannelConfig, ShmPublisher, ShmSubscriber, StepBatch, WireMsg};
    let name = format!("test-{}-alloc-{tag}/steps", std::process::id());
    let cfg = ChannelConfig::steps();
    let (pub_node, _) = open_node::<P>(&format!("alloc-pub-{tag}")).unwrap();
    let (sub_node, _) = open_node::<ipc::Service>(&format!("alloc-sub-{tag}")).unwrap();
    let mut sub = ShmSubscriber::<ipc::Service, StepBatch>::open(&sub_node, &name, &cfg).unwrap();
    let mut p = ShmPublisher::<P, StepBatch>::open(&pub_node, &name, &cfg).unwrap();
    while p.connect().unwrap() < 1 {
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    let msg = WireMsg::new(1, 2, &[3, 4, 5]).unwrap();
    let mut round_trip = |i: u64| {
        p.send_with(|b| {
            b.count = 0;
            b.push(msg);
            b.mcu = i as u32;
        })
        .unwrap();
        let got = sub.try_recv_with(|b| (b.seq, b.mcu)).unwrap();
        assert_eq!(got, Some((i, i as u32)));
    };
    for i in 0..8 {
        round_trip(i);
    }
    let before = AllocCounter::snapshot();
    for i in 8..8 + n {
        round_trip(i);
    }
    AllocCounter::snapshot().since(before).allocations()
}

#[test]
fn shm_loans_allocate_nothing_with_the_pooled_service() {
    assert_eq!(shm_round_trips::<rt_core::shm::pooled::Ipc>("pooled", 1000), 0);
}

/// Why `shm::pooled` exists: with plain `ipc::Service`, iceoryx2 0.10 allocates the sample's
/// reference-counted state on every loan. If this starts failing, iceoryx2 stopped doing that
/// and the pooled variant can go.
#[test]
fn shm_loans_allocate_with_plain_ipc() {
    assert!(shm_round_trips::<iceoryx2::prelude::ipc::Service>("plain", 100) >= 100);
}
