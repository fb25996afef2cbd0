//! Tests of the serial queue against a scripted MCU peer in virtual time.

use super::*;
use crate::transport::XorShift64;
use proptest::prelude::*;

/// The MCU side of the protocol, as the firmware does it: accept the expected sequence, ack
/// every good block, NAK out-of-order and corrupt ones.
struct Peer {
    expected: u8,
    rx: Vec<u8>,
    payloads: Vec<Vec<u8>>,
    out: Vec<u8>,
    naks: usize,
}

impl Peer {
    fn new(expected: u8) -> Peer {
        Peer {
            expected,
            rx: Vec::new(),
            payloads: Vec::new(),
            out: Vec::new(),
            naks: 0,
        }
    }

    fn feed(&mut self, data: &[u8]) {
        self.rx.extend_from_slice(data);
        loop {
            match find_block(&self.rx) {
                Frame::Incomplete => break,
                Frame::Skip(n) => drop(self.rx.drain(..n)),
                Frame::Bad(n) => {
                    self.rx.drain(..n);
                    self.naks += 1;
                    self.send(&[]);
                }
                Frame::Block { len, seq } => {
                    if seq == self.expected {
                        self.expected = (self.expected + 1) & 0x0F;
                        self.payloads.push(block_payload(&self.rx[..len]).to_vec());
                    } else {
                        self.naks += 1;
                    }
                    self.rx.drain(..len);
                    self.send(&[]);
                }
            }
        }
    }

    fn send(&mut self, payload: &[u8]) {
        let mut buf = [0u8; MESSAGE_MAX];
        let n = encode_block(self.expected, payload, &mut buf).unwrap();
        self.out.extend_from_slice(&buf[..n]);
    }

    fn take(&mut self) -> Vec<u8> {
        std::mem::take(&mut self.out)
    }
}

fn cmd(bytes: &[u8]) -> Cmd {
    Cmd::from_bytes(bytes).unwrap()
}

fn queue(window: Option<usize>) -> SerialQueue {
    SerialQueue::new(QueueConfig {
        capacity: 64,
        receive_window: window,
    })
}

/// Blocks in a written buffer: (seq, payload).
fn blocks(mut data: &[u8]) -> Vec<(u8, Vec<u8>)> {
    let mut out = Vec::new();
    while !data.is_empty() {
        match find_block(data) {
            Frame::Block { len, seq } => {
                out.push((seq, block_payload(&data[..len]).to_vec()));
                data = &data[len..];
            }
            Frame::Skip(n) | Frame::Bad(n) => data = &data[n..],
            Frame::Incomplete => panic!("partial block written"),
        }
    }
    out
}

fn feed(sq: &mut SerialQueue, now: f64, data: &[u8]) -> Vec<Vec<u8>> {
    let mut got = Vec::new();
    sq.receive(now, data, &mut |p| got.push(p.to_vec()));
    got
}

/// Makes the queue synced with a fresh MCU (first exchange).
fn synced(window: Option<usize>) -> (SerialQueue, Peer) {
    let mut sq = queue(window);
    let mut peer = Peer::new(0);
    sq.push(cmd(&[1]), 0, 0).unwrap();
    let out = sq.poll(0.0).to_vec();
    peer.feed(&out);
    feed(&mut sq, 0.001, &peer.take());
    assert!(sq.is_idle());
    peer.payloads.clear();
    (sq, peer)
}

#[test]
fn ack_advances_and_packs_messages() {
    let (mut sq, mut peer) = synced(None);
    for i in 0..10u8 {
        sq.push(cmd(&[i; 10]), 0, 0).unwrap();
    }
    let out = sq.poll(1.0).to_vec();
    let bl = blocks(&out);
    assert_eq!(bl.len(), 2, "5 messages of 10 bytes per 59-byte block");
    assert_eq!(bl[0].1.len(), 50);
    assert_eq!(sq.stats().inflight_blocks, 2);
    peer.feed(&out);
    feed(&mut sq, 1.002, &peer.take());
    let st = sq.stats();
    assert_eq!(st.inflight_blocks, 0);
    assert_eq!(st.receive_seq, st.send_seq);
    assert_eq!(st.msgs_acked, 11);
    assert_eq!(st.bytes_write, 5 + 1 + 2 * 55);
    assert!(sq.is_idle());
    assert_eq!(sq.poll_at(), None);
    let all: Vec<u8> = peer.payloads.concat();
    assert_eq!(all, (0..10u8).flat_map(|i| [i; 10]).collect::<Vec<_>>());
}

#[test]
fn responses_are_handed_out_and_ack() {
    let (mut sq, mut peer) = synced(None);
    sq.push(cmd(&[7]), 0, 0).unwrap();
    let out = sq.poll(1.0).to_vec();
    peer.feed(&out);
    peer.out.clear();
    peer.send(&[81, 5]); // a response carrying the ack
    let got = feed(&mut sq, 1.001, &peer.take());
    assert_eq!(got, vec![vec![81, 5]]);
    assert!(sq.is_idle());
}

#[test]
fn nak_retransmits_everything_unacked_once() {
    let (mut sq, mut peer) = synced(None);
    sq.push(cmd(&[1; 50]), 0, 0).unwrap();
    sq.push(cmd(&[2; 50]), 0, 0).unwrap();
    sq.push(cmd(&[3; 50]), 0, 0).unwrap();
    let out = sq.poll(1.0).to_vec();
    let bl = blocks(&out);
    assert_eq!(bl.len(), 3);
    // Block 2 is lost: the peer gets 1 and 3; it acks 1 and NAKs 3 (same sequence twice).
    let mut lossy = Vec::new();
    let mut buf = [0u8; 64];
    for (i, (seq, p)) in bl.iter().enumerate() {
        if i != 1 {
            let n = encode_block(*seq, p, &mut buf).unwrap();
            lossy.extend_from_slice(&buf[..n]);
        }
    }
    peer.feed(&lossy);
    assert_eq!(peer.naks, 1);
    feed(&mut sq, 1.001, &peer.take());
    assert_eq!(sq.stats().inflight_blocks, 2);
    assert_eq!(sq.poll_at(), Some(1.001), "a NAK asks for an immediate poll");
    let re = sq.poll(1.001).to_vec();
    assert_eq!(re[0], MESSAGE_SYNC, "retransmit starts with a sync byte");
    assert_eq!(blocks(&re).len(), 2);
    assert_eq!(sq.stats().retransmits, 1);
    assert_eq!(sq.stats().rto, MIN_RTO, "a NAK does not back off");
    // A second NAK at the same ack level is ignored.
    peer.send(&[]);
    feed(&mut sq, 1.0015, &peer.take());
    assert!(sq.poll(1.0015).is_empty());
    peer.feed(&re);
    feed(&mut sq, 1.002, &peer.take());
    assert!(sq.is_idle());
    assert_eq!(peer.payloads.concat(), [[1u8; 50], [2; 50], [3; 50]].concat());
}

#[test]
fn timeout_backs_off_and_caps() {
    let (mut sq, _peer) = synced(None);
    let rto0 = sq.stats().rto;
    assert!((MIN_RTO..=MAX_RTO).contains(&rto0));
    sq.push(cmd(&[9]), 0, 0).unwrap();
    assert_eq!(blocks(sq.poll(10.0)).len(), 1);
    let mut now = 10.0;
    let mut expected_rto = rto0;
    for _ in 0..12 {
        let at = sq.poll_at().unwrap();
        assert!(
            (at - (now + expected_rto)).abs() < 1e-9,
            "deadline {at} vs {}",
            now + expected_rto
        );
        assert!(sq.poll(at - 1e-6).is_empty(), "no retransmit before the deadline");
        now = at;
        let re = sq.poll(now).to_vec();
        assert_eq!(blocks(&re).len(), 1);
        expected_rto = (expected_rto * 2.0).min(MAX_RTO);
        assert_eq!(sq.stats().rto, expected_rto);
    }
    assert_eq!(sq.stats().rto, MAX_RTO);
    assert_eq!(sq.ack_wait_since(), Some(10.0));
}

#[test]
fn rtt_sets_rto_per_rfc6298() {
    let (mut sq, mut peer) = synced(None);
    // The sync exchange measured 1 ms: srtt 1 ms, rttvar 0.5 ms, rto clamped to 25 ms.
    assert!((sq.stats().srtt - 0.001).abs() < 1e-12);
    assert_eq!(sq.stats().rto, MIN_RTO);
    sq.push(cmd(&[1]), 0, 0).unwrap();
    let out = sq.poll(2.0).to_vec();
    peer.feed(&out);
    feed(&mut sq, 2.201, &peer.take());
    let st = sq.stats();
    // r = 0.201: rttvar = 0.75·0.0005 + 0.25·0.2 = 0.050375; srtt = 0.875·0.001 + 0.125·0.201.
    assert!((st.rttvar - 0.050375).abs() < 1e-9);
    assert!((st.srtt - 0.026).abs() < 1e-9);
    assert!((st.rto - (0.026 + 4.0 * 0.050375)).abs() < 1e-9);
}

#[test]
fn window_limits_unacked_bytes() {
    let (mut sq, mut peer) = synced(Some(192));
    for i in 0..8u8 {
        sq.push(cmd(&[i; 59]), 0, 0).unwrap();
    }
    let out = sq.poll(1.0).to_vec();
    assert_eq!(blocks(&out).len(), 3, "3 × 64 bytes fill a 192-byte window");
    assert!(sq.poll(1.0).is_empty());
    // Ack the first block only.
    let first = &out[..64];
    peer.feed(first);
    feed(&mut sq, 1.001, &peer.take());
    assert_eq!(blocks(sq.poll(1.001)).len(), 1);
    // Without a window: 12 blocks at most.
    let (mut sq, _) = synced(None);
    for i in 0..20u8 {
        sq.push(cmd(&[i; 59]), 0, 0).unwrap();
    }
    assert_eq!(blocks(sq.poll(1.0)).len(), MAX_PENDING_BLOCKS);
}

#[test]
fn min_clock_holds_messages() {
    let (mut sq, mut peer) = synced(None);
    sq.set_clock_est(ClockEstimate::new(0.0, 0.0, 1000.0)); // 1000 ticks per second
    sq.push(cmd(&[5]), 500, 600).unwrap();
    sq.push(cmd(&[6]), 0, 0).unwrap();
    assert_eq!(sq.stats().upcoming_bytes, 1);
    let out = sq.poll(0.4).to_vec();
    assert_eq!(blocks(&out)[0].1, vec![6], "plain goes, clocked waits");
    peer.feed(&out);
    feed(&mut sq, 0.401, &peer.take());
    assert!(sq.has_upcoming());
    let at = sq.poll_at().unwrap();
    assert!((at - 0.5).abs() < 1e-9, "wake-up at min_clock: {at}");
    assert!(sq.poll(0.499).is_empty());
    let out = sq.poll(0.5).to_vec();
    assert_eq!(blocks(&out)[0].1, vec![5]);
    let st = sq.stats();
    assert_eq!(st.upcoming_bytes, 0);
    assert_eq!(st.min_lead_margin, Some(100));
    assert_eq!(st.clocked_sent, 1);
}

#[test]
fn ready_messages_go_by_req_clock_then_submission() {
    let (mut sq, _) = synced(None);
    sq.set_clock_est(ClockEstimate::new(0.0, 0.0, 1000.0));
    sq.push(cmd(&[30]), 1, 300).unwrap();
    sq.push(cmd(&[10]), 1, 100).unwrap();
    sq.push(cmd(&[20]), 1, 200).unwrap();
    sq.push(cmd(&[11]), 1, 100).unwrap();
    sq.push(cmd(&[0]), 0, 0).unwrap();
    sq.push(cmd(&[1]), 0, 0).unwrap();
    let out = sq.poll(1.0).to_vec();
    assert_eq!(blocks(&out)[0].1, vec![0, 1, 10, 11, 20, 30]);
}

#[test]
fn lead_margins_reach_the_hook() {
    let (mut sq, _) = synced(None);
    sq.set_clock_est(ClockEstimate::new(0.0, 0.0, 1000.0));
    let seen = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
    let s2 = seen.clone();
    sq.set_margin_hook(Some(Box::new(move |req, margin| {
        s2.lock().unwrap().push((req, margin))
    })));
    sq.push(cmd(&[1]), 0, 1500).unwrap();
    sq.push(cmd(&[2]), 0, 900).unwrap();
    sq.poll(1.0);
    assert_eq!(*seen.lock().unwrap(), vec![(900, -100), (1500, 500)]);
    assert_eq!(sq.stats().min_lead_margin, Some(-100));
}

#[test]
fn garbage_is_counted_and_skipped() {
    let (mut sq, mut peer) = synced(None);
    sq.push(cmd(&[1]), 0, 0).unwrap();
    let out = sq.poll(1.0).to_vec();
    peer.feed(&out);
    let mut data = vec![0x7E, 0x7E, 0x03, 0x11, 0x22, 0x7E];
    data.extend(peer.take());
    feed(&mut sq, 1.001, &data);
    assert!(sq.is_idle());
    assert_eq!(sq.stats().bytes_invalid, 4, "stray syncs are skipped silently");
    // An ack for a block never sent is invalid.
    let mut buf = [0u8; 8];
    let n = encode_block((sq.stats().send_seq as u8 + 3) & 0xF, &[], &mut buf).unwrap();
    feed(&mut sq, 1.002, &buf[..n]);
    assert_eq!(sq.stats().bytes_invalid, 9);
}

#[test]
fn adopts_the_sequence_a_running_mcu_expects() {
    let mut sq = queue(None);
    let mut peer = Peer::new(5);
    sq.push(cmd(&[1]), 0, 0).unwrap();
    sq.push(cmd(&[2; 59]), 0, 0).unwrap();
    let out = sq.poll(0.0).to_vec();
    assert_eq!(
        blocks(&out).len(),
        1,
        "one block in flight until the first answer"
    );
    peer.feed(&out);
    assert_eq!(peer.naks, 1);
    feed(&mut sq, 0.001, &peer.take());
    let out = sq.poll(0.001).to_vec();
    let bl = blocks(&out);
    assert_eq!(bl[0].0, 5, "renumbered to what the MCU expects");
    assert_eq!(bl.len(), 2);
    peer.feed(&out);
    feed(&mut sq, 0.002, &peer.take());
    assert!(sq.is_idle());
    assert_eq!(peer.payloads, vec![vec![1], vec![2; 59]]);
}

#[test]
fn capacity_is_bounded() {
    let mut sq = SerialQueue::new(QueueConfig {
        capacity: 3,
        receive_window: None,
    });
    for _ in 0..3 {
        sq.push(cmd(&[1]), 0, 0).unwrap();
    }
    assert!(sq.push(cmd(&[2]), 0, 0).is_err());
    assert_eq!(sq.space(), 0);
}

#[test]
fn marked_message_records_its_write_time() {
    let (mut sq, _) = synced(None);
    sq.push_marked(cmd(&[6])).unwrap();
    assert_eq!(sq.take_marked_sent(), None);
    sq.poll(3.5);
    assert_eq!(sq.take_marked_sent(), Some(3.5));
    assert_eq!(sq.take_marked_sent(), None);
}

/// A one-way channel with latency and faults, in virtual time.
struct Wire {
    rng: XorShift64,
    drop: f64,
    corrupt: f64,
    dup: f64,
    in_flight: VecDeque<(f64, Vec<u8>)>,
}

impl Wire {
    fn send(&mut self, now: f64, data: &[u8]) {
        if data.is_empty() || self.rng.next_f64() < self.drop {
            return;
        }
        let mut data = data.to_vec();
        if self.rng.next_f64() < self.corrupt {
            let i = self.rng.below(data.len());
            data[i] ^= 1 << self.rng.below(8);
        }
        let at = now + 0.0001 + 0.0004 * self.rng.next_f64();
        let at = self.in_flight.back().map_or(at, |(t, _)| at.max(*t)); // a wire keeps order
        if self.rng.next_f64() < self.dup {
            self.in_flight.push_back((at, data.clone()));
        }
        self.in_flight.push_back((at, data));
    }

    fn due(&mut self, now: f64) -> Vec<u8> {
        let mut out = Vec::new();
        while self.in_flight.front().is_some_and(|(t, _)| *t <= now) {
            if let Some((_, d)) = self.in_flight.pop_front() {
                out.extend(d);
            }
        }
        out
    }

    fn next(&self) -> Option<f64> {
        self.in_flight.front().map(|(t, _)| *t)
    }
}

/// Streams `msgs` through lossy wires both ways; returns what the peer received, in order.
fn run_lossy(
    msgs: &[Vec<u8>],
    seed: u64,
    drop: f64,
    corrupt: f64,
    dup: f64,
    window: Option<usize>,
) -> Vec<u8> {
    let mut sq = SerialQueue::new(QueueConfig {
        capacity: 16,
        receive_window: window,
    });
    let mut peer = Peer::new(0);
    let wire = |s| Wire {
        rng: XorShift64::new(s),
        drop,
        corrupt,
        dup,
        in_flight: VecDeque::new(),
    };
    let (mut to_mcu, mut to_host) = (wire(seed), wire(seed ^ 0xABCD));
    let mut next = 0;
    let mut now = 0.0;
    for _ in 0..2_000_000 {
        while next < msgs.len() && sq.push(cmd(&msgs[next]), 0, 0).is_ok() {
            next += 1;
        }
        let out = sq.poll(now).to_vec();
        to_mcu.send(now, &out);
        peer.feed(&to_mcu.due(now));
        let back = peer.take();
        to_host.send(now, &back);
        let data = to_host.due(now);
        if !data.is_empty() {
            feed(&mut sq, now, &data);
        }
        if next == msgs.len() && sq.is_idle() {
            return peer.payloads.concat();
        }
        let wake = [sq.poll_at(), to_mcu.next(), to_host.next()]
            .into_iter()
            .flatten()
            .fold(now + 0.001, f64::min);
        now = wake.max(now + 1e-6);
    }
    panic!("did not finish: {:?}", sq.stats());
}

#[test]
fn lossy_link_delivers_everything_once() {
    let msgs: Vec<Vec<u8>> = (0..500u32)
        .map(|i| vec![(i % 251) as u8; 1 + (i % 23) as usize])
        .collect();
    let got = run_lossy(&msgs, 42, 0.1, 0.1, 0.05, Some(192));
    assert_eq!(got, msgs.concat());
}

#[test]
fn steady_state_does_not_grow_buffers() {
    // Every queue is preallocated in `new`; streaming must never make one reallocate.
    let (mut sq, mut peer) = synced(Some(192));
    sq.set_clock_est(ClockEstimate::new(0.0, 0.0, 1000.0));
    let caps = |sq: &SerialQueue| {
        (
            sq.upcoming.capacity(),
            sq.ready.capacity(),
            sq.inflight.capacity(),
        )
    };
    let before = caps(&sq);
    let mut now = 1.0;
    for round in 0..200u64 {
        while sq.space() > 0 {
            let clock = round * 10;
            if sq.push(cmd(&[(round % 200) as u8; 9]), clock, clock + 5).is_err() {
                break;
            }
        }
        now += 0.01;
        let out = sq.poll(now).to_vec();
        peer.feed(&out);
        feed(&mut sq, now + 0.0001, &peer.take());
        assert_eq!(caps(&sq), before, "round {round}");
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn every_message_exactly_once_in_order(
        seed in 1u64..u64::MAX,
        lens in proptest::collection::vec(1usize..=MESSAGE_PAYLOAD_MAX, 1..120),
        drop in 0.0f64..0.3,
        corrupt in 0.0f64..0.3,
        dup in 0.0f64..0.2,
        window in proptest::option::of(64usize..400),
    ) {
        // Distinct contents so a duplicate or a loss changes the concatenation.
        let msgs: Vec<Vec<u8>> = lens
            .iter()
            .enumerate()
            .map(|(i, &n)| (0..n).map(|j| (i * 31 + j) as u8).collect())
            .collect();
        let got = run_lossy(&msgs, seed, drop, corrupt, dup, window);
        prop_assert_eq!(got, msgs.concat());
    }

    #[test]
    fn receive_never_panics(data in proptest::collection::vec(any::<u8>(), 0..300)) {
        let (mut sq, _) = synced(Some(192));
        sq.push(cmd(&[1]), 0, 0).unwrap();
        sq.poll(1.0);
        feed(&mut sq, 1.0, &data);
        sq.poll(2.0);
    }
}
