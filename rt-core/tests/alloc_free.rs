//! Installs the counting allocator and proves the RT-path pieces of rt-core allocate nothing
//! after warm-up: histogram recording, logger pushes, ArrayQueue hand-off.
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
    let q = crossbeam_queue::ArrayQueue::<u64>::new(8);
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
