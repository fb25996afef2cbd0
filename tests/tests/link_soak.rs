//! Soak test of the reliable transport (issue 4 item 7): a stream of real dictionary commands
//! (`queue_step`, the global sequence number in `interval`, the per-stream sequence in `count`)
//! goes from the host's [`SerialQueue`] through a [`FaultyTransport`] (1% of writes dropped,
//! 1% corrupted, in both directions) into the firmware's own protocol layer
//! ([`firmware::core::link::Link`]: framing, sequence check, ack/nak) running in a peer thread
//! on a [`MemoryPair`].
//!
//! The peer proves, for every command: it arrived exactly once (a bitmap over the global
//! sequence), in order within its stream (per-stream sequence consecutive, which also means
//! `req_clock` order since `req_clock` grows along a stream), and never before its `min_clock`
//! (host and peer read the same MCU clock, `(t − t0)·FREQ` of `CLOCK_MONOTONIC`, and the host
//! releases a message only once that clock reached its `min_clock`). Stream 0 is plain
//! (`min_clock = req_clock = 0`, submission order); streams 1..=3 are clocked, a quarter of
//! their messages due a little in the future so the upcoming queue is always in use.
//!
//! Throughput and retransmit counts are printed; nothing asserts a duration.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use firmware::core::board::Board;
use firmware::core::link::Link;
use links::clocksync::ClockEstimate;
use links::dict::Dictionary;
use links::mcu::McuLink;
use links::proto::format::{decode_params, Value};
use links::proto::{vlq, MESSAGE_PAYLOAD_MAX};
use links::serialqueue::{QueueConfig, QueueStats, SerialQueue};
use links::transport::{
    FaultConfig, FaultStats, FaultyTransport, MemoryEnd, MemoryPair, Transport, XorShift64,
};
use rt_core::WireClock;

/// Ticks per second of the shared MCU clock.
const FREQ: f64 = 1e6;
/// Streams (oids); 0 is plain, the others clocked.
const STREAMS: usize = 4;
/// Guard against a hang (not a timing assertion): the run fails if it makes no progress this long.
const STALL: Duration = Duration::from_secs(60);

/// The peer's board: writes blocks through its own faulty transport.
struct PeerBoard {
    t: FaultyTransport<MemoryEnd>,
}

impl Board for PeerBoard {
    fn step(&mut self, _oid: u8, _dir: bool, _clock: WireClock) {}
    fn write(&mut self, bytes: &[u8]) {
        // A closed pipe ends the run: the next read reports it.
        let _ = self.t.write_all(bytes);
    }
}

/// What the peer saw.
#[derive(Debug, Default)]
struct PeerReport {
    received: u64,
    faults: FaultStats,
    errors: Vec<String>,
}

/// The peer thread: firmware framing plus the checks of every received command.
fn peer(
    t: FaultyTransport<MemoryEnd>,
    total: usize,
    qs_id: u32,
    qs_fmt: String,
    min_clocks: Arc<Vec<AtomicU64>>,
    t0: f64,
) -> PeerReport {
    let mut board = PeerBoard { t };
    let mut link = Link::new();
    let mut seen = vec![false; total];
    let mut next_in_stream = [0u16; STREAMS];
    let mut last_k = [None::<u32>; STREAMS];
    let mut report = PeerReport::default();
    let mut buf = [0u8; 4096];
    let mut out = [0u8; MESSAGE_PAYLOAD_MAX];
    let fail = |report: &mut PeerReport, e: String| {
        if report.errors.len() < 20 {
            report.errors.push(e);
        }
    };
    while let Ok(n) = board.t.read(&mut buf, Duration::from_millis(20)) {
        let mut data = &buf[..n];
        loop {
            let taken = link.push_rx(data);
            data = &data[taken..];
            while let Some(len) = link.next_block(&mut out, &mut board) {
                let clock = (McuLink::system_now() - t0) * FREQ;
                let mut p = &out[..len];
                while !p.is_empty() {
                    let Some((id, used)) = vlq::decode(p) else {
                        fail(&mut report, "undecodable id".into());
                        break;
                    };
                    let mut vals = [Value::Int(0); 4];
                    let parsed = (id == qs_id)
                        .then(|| decode_params(&qs_fmt, &p[used..], &mut vals).ok())
                        .flatten();
                    let Some((_, n)) = parsed else {
                        fail(&mut report, format!("unexpected message id {id}"));
                        break;
                    };
                    p = &p[used + n..];
                    let (oid, k, seq) = (vals[0].int() as usize, vals[1].int() as u32, vals[2].int() as u16);
                    report.received += 1;
                    if oid >= STREAMS || k as usize >= total {
                        fail(&mut report, format!("bad oid {oid} / sequence {k}"));
                        continue;
                    }
                    if std::mem::replace(&mut seen[k as usize], true) {
                        fail(&mut report, format!("command {k} arrived twice"));
                    }
                    if seq != next_in_stream[oid] || last_k[oid].is_some_and(|l| l >= k) {
                        fail(
                            &mut report,
                            format!(
                                "stream {oid}: command {k} (#{seq}) after {:?} (expected #{})",
                                last_k[oid], next_in_stream[oid]
                            ),
                        );
                    }
                    next_in_stream[oid] = seq.wrapping_add(1);
                    last_k[oid] = Some(k);
                    let min_clock = min_clocks[k as usize].load(Ordering::Relaxed);
                    if min_clock as f64 > clock {
                        fail(
                            &mut report,
                            format!(
                                "command {k} arrived at clock {clock:.0} before its min_clock {min_clock}"
                            ),
                        );
                    }
                }
                link.ack(&mut board);
            }
            if data.is_empty() {
                break;
            }
        }
    }
    let missing = seen.iter().filter(|s| !**s).count();
    if missing > 0 {
        fail(&mut report, format!("{missing} commands never arrived"));
    }
    report.faults = board.t.stats();
    report
}

/// Figures of one run.
#[derive(Debug)]
struct Soak {
    secs: f64,
    host: QueueStats,
    host_faults: FaultStats,
    peer: PeerReport,
}

/// Pushes `total` commands through the faulty link and checks them at the peer.
fn soak(total: usize, seed: u64) -> Soak {
    let dict = Dictionary::from_json(&firmware::dict::dictionary_json(FREQ as u32).to_string())
        .expect("firmware dictionary");
    let qs = dict.encoder("queue_step").expect("queue_step");
    let def = dict.command("queue_step").expect("queue_step");
    let (qs_id, qs_fmt) = (def.id, def.format.clone());
    let window = dict.receive_window();

    let faults = |seed| FaultConfig {
        seed,
        drop_rate: 0.01,
        corrupt_rate: 0.01,
        duplicate_rate: 0.0,
        on_read: false,
    };
    let (host_end, mcu_end) = MemoryPair::new();
    let mut host = FaultyTransport::new(host_end, faults(seed));
    let min_clocks: Arc<Vec<AtomicU64>> = Arc::new((0..total).map(|_| AtomicU64::new(0)).collect());
    let t0 = McuLink::system_now();
    let peer_thread = {
        let (min_clocks, fmt, t) = (
            min_clocks.clone(),
            qs_fmt.clone(),
            FaultyTransport::new(mcu_end, faults(seed ^ 0x5555)),
        );
        std::thread::spawn(move || peer(t, total, qs_id, fmt, min_clocks, t0))
    };

    let est = ClockEstimate::new(t0, 0.0, FREQ);
    let mut sq = SerialQueue::new(QueueConfig {
        capacity: 2048,
        receive_window: window,
    });
    sq.set_clock_est(est);
    let mut rng = XorShift64::new(seed);
    let mut stream_seq = [0u16; STREAMS];
    let mut stream_min = [0u64; STREAMS];
    let mut stream_req = [0u64; STREAMS];
    let mut next = 0usize;
    let mut buf = [0u8; 4096];
    let mut last_progress = (Instant::now(), 0u64);
    let start = McuLink::system_now();
    loop {
        let now = McuLink::system_now();
        while next < total && sq.space() > 0 {
            let oid = rng.below(STREAMS);
            let clock = est.clock_at(now) as u64;
            let (min_clock, req_clock) = if oid == 0 {
                (0, 0)
            } else {
                // A quarter due up to 2 ms ahead (held as upcoming), the rest already due.
                let ahead = if rng.below(4) == 0 {
                    rng.below(2000) as u64
                } else {
                    0
                };
                let min = stream_min[oid].max(clock + ahead).max(1);
                let req = stream_req[oid].max(min + 100_000 + rng.below(1000) as u64);
                (min, req)
            };
            stream_min[oid] = min_clock;
            stream_req[oid] = req_clock;
            min_clocks[next].store(min_clock, Ordering::Relaxed);
            let cmd = qs
                .encode(&[oid as i64, next as i64, stream_seq[oid] as i64, 0])
                .expect("encode");
            stream_seq[oid] = stream_seq[oid].wrapping_add(1);
            if sq.push(cmd, min_clock, req_clock).is_err() {
                unreachable!("space was checked");
            }
            next += 1;
        }
        let out = sq.poll(now);
        if !out.is_empty() {
            host.write_all(out).expect("host write");
        }
        if next == total && sq.is_idle() {
            break;
        }
        let wait = sq.poll_at().map_or(0.005, |at| (at - now).clamp(0.0, 0.005));
        let n = host
            .read(&mut buf, Duration::from_secs_f64(wait))
            .expect("host read");
        if n > 0 {
            sq.receive(McuLink::system_now(), &buf[..n], &mut |_| {});
        }
        let acked = sq.stats().msgs_acked;
        if acked != last_progress.1 {
            last_progress = (Instant::now(), acked);
        }
        assert!(
            last_progress.0.elapsed() < STALL,
            "no progress: {acked} of {total} acked, {:?}",
            sq.stats()
        );
    }
    let secs = McuLink::system_now() - start;
    let host_stats = sq.stats();
    let host_faults = host.stats();
    drop(host);
    let peer = peer_thread.join().expect("peer thread");
    Soak {
        secs,
        host: host_stats,
        host_faults,
        peer,
    }
}

fn check_and_print(total: usize, r: &Soak) {
    let q = &r.host;
    println!(
        "soak {total} commands: {:.2} s, {:.0} messages/s; retransmits {} ({} bytes of {} written); \
         invalid bytes from MCU {}; srtt {:.3} ms rto {:.1} ms; faults host→mcu {:?}, mcu→host {:?}",
        r.secs,
        total as f64 / r.secs,
        q.retransmits,
        q.bytes_retransmit,
        q.bytes_write,
        q.bytes_invalid,
        q.srtt * 1e3,
        q.rto * 1e3,
        r.host_faults,
        r.peer.faults,
    );
    assert!(r.peer.errors.is_empty(), "{:#?}", r.peer.errors);
    assert_eq!(r.peer.received, total as u64);
    assert_eq!(q.msgs_acked, total as u64);
    assert!(
        r.host_faults.dropped > 0 && r.host_faults.corrupted > 0,
        "{:?}",
        r.host_faults
    );
    assert!(
        r.peer.faults.dropped > 0 && r.peer.faults.corrupted > 0,
        "{:?}",
        r.peer.faults
    );
    assert!(q.retransmits > 0);
}

/// The full 10^6 commands (about 20 s in a debug build on a 2-core VM).
#[test]
fn soak_1m_commands_through_a_faulty_link() {
    let total = 1_000_000;
    let r = soak(total, 0xBADC_0FFE);
    check_and_print(total, &r);
}
