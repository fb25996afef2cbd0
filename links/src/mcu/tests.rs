//! End-to-end tests of [`McuLink`] against the fake MCU. Timeouts are generous upper bounds so
//! a loaded machine cannot make them flake; nothing asserts how long anything took.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use super::fake::{Control, FakeMcu};
use super::*;
use crate::transport::{FaultConfig, FaultyTransport, MemoryPair, PtyTransport};

const NOMINAL: f64 = 50e6;
const LONG: Duration = Duration::from_secs(20);

fn opts() -> LinkOptions {
    LinkOptions {
        identify_timeout: Duration::from_secs(10),
        response_timeout: Duration::from_secs(10),
        queue_capacity: 256,
        ..LinkOptions::default()
    }
}

fn start(freq: f64) -> (McuLink, Arc<Control>, std::thread::JoinHandle<()>) {
    let (host, mcu) = MemoryPair::new();
    let (ctl, fake) = FakeMcu::spawn(Box::new(mcu), NOMINAL, freq, 123_456);
    let link = McuLink::connect(Box::new(host), opts()).expect("connect");
    (link, ctl, fake)
}

fn queue_step(link: &McuLink, oid: i64, interval: i64) -> Cmd {
    link.dictionary()
        .encode("queue_step", &[oid, interval, 10, 0])
        .unwrap()
}

#[test]
fn connects_queries_and_streams_in_order() {
    let (link, ctl, fake) = start(NOMINAL);
    let d = link.dictionary();
    assert_eq!(d.clock_freq().unwrap(), NOMINAL);
    assert_eq!(d.receive_window(), Some(192));
    let est = link.clock();
    assert!(est.is_valid());
    assert!((est.freq() / NOMINAL - 1.0).abs() < 0.1, "freq {}", est.freq());

    let cfg = link
        .query(d.encode("get_config", &[]).unwrap(), "config", None, LONG)
        .unwrap();
    assert_eq!(cfg.get("move_count"), Some(16));
    let pos = link
        .query(
            d.encode("stepper_get_position", &[4]).unwrap(),
            "stepper_position",
            Some(("oid", 4)),
            LONG,
        )
        .unwrap();
    assert_eq!(pos.to_string(), "stepper_position oid=4 pos=-5");

    let mut expected = Vec::new();
    let now_clock = link.clock().clock_at(McuLink::system_now()) as u64;
    for i in 0..300 {
        let cmd = queue_step(&link, 1, 1000 + i);
        expected.push(cmd.as_bytes().to_vec());
        if i % 3 == 0 {
            link.send(cmd).unwrap();
        } else {
            // Already due: ordered by req_clock, which grows with i.
            link.send_clocked(cmd, now_clock, now_clock + 1_000_000 + i as u64)
                .unwrap();
        }
    }
    link.wait_idle(LONG).unwrap();
    let got = ctl.received.lock().unwrap().clone();
    assert_eq!(got.len(), 300);
    // Plain messages keep their order, clocked ones keep theirs (each stream is in order).
    let plain: Vec<_> = expected.iter().step_by(3).cloned().collect();
    let got_plain: Vec<_> = got.iter().filter(|m| plain.contains(m)).cloned().collect();
    assert_eq!(got_plain, plain);
    let clocked: Vec<_> = expected
        .iter()
        .enumerate()
        .filter(|(i, _)| i % 3 != 0)
        .map(|(_, m)| m.clone())
        .collect();
    let got_clocked: Vec<_> = got.iter().filter(|m| !plain.contains(m)).cloned().collect();
    assert_eq!(got_clocked, clocked);

    let stats = link.close();
    assert_eq!(stats.clocked_msgs, 200);
    assert!(stats.min_lead_margin_ticks.is_some());
    assert!(stats.queue.bytes_write > 0);
    assert!(stats.clock_samples >= 8);
    fake.join().unwrap();
}

#[test]
fn min_clock_holds_a_message_until_its_time() {
    let (link, ctl, fake) = start(NOMINAL);
    let est = link.clock();
    let now = McuLink::system_now();
    let later = est.clock_at(now + 0.3) as u64;
    let cmd = queue_step(&link, 2, 777);
    link.send_clocked(cmd, later, later + 5_000_000).unwrap();
    link.wait_idle(LONG).unwrap();
    // It was written no earlier than the estimated clock reached min_clock.
    let margin = link.stats().min_lead_margin_ticks.unwrap();
    assert!(margin <= 5_000_000, "margin {margin}");
    assert_eq!(ctl.received.lock().unwrap().len(), 1);
    drop(link);
    fake.join().unwrap();
}

#[test]
fn time_scaled_clock_extends_across_wraps() {
    // 50× time scale: 2.5 G ticks per second wraps the 32-bit clock every 1.7 s.
    let freq = NOMINAL * 50.0;
    let (host, mcu) = MemoryPair::new();
    let c0 = 3 * (1u64 << 32) - 1_000_000_000;
    let t0 = McuLink::system_now();
    let (_ctl, fake) = FakeMcu::spawn(Box::new(mcu), NOMINAL, freq, c0);
    let tuning = LinkTuning {
        clock_interval: Duration::from_millis(300),
        ..LinkTuning::default()
    };
    let link = McuLink::connect_with(Box::new(host), opts(), tuning).unwrap();
    let get_clock = link.dictionary().encode("get_clock", &[]).unwrap();
    for _ in 0..8 {
        std::thread::sleep(Duration::from_millis(300));
        let before = FakeMcu::clock_at(freq, c0, t0, McuLink::system_now());
        let msg = link.query(get_clock, "clock", None, LONG).unwrap();
        let after = FakeMcu::clock_at(freq, c0, t0 - 0.01, McuLink::system_now());
        let wire = msg.get("clock").unwrap() as u32;
        let full = link.clock().extend(wire, McuLink::system_now());
        // The fake's t0 is a little later than ours, so the true clock lies in [.., after].
        assert!(
            full <= after && full + 2_500_000_000 / 2 >= before,
            "{before} {full} {after}"
        );
        assert_eq!(full as u32, wire);
    }
    let f = link.clock().freq();
    assert!((f / freq - 1.0).abs() < 0.05, "freq {f}");
    drop(link);
    fake.join().unwrap();
}

#[test]
fn identify_timeout_names_the_mcu() {
    let (host, mut mcu) = MemoryPair::new();
    let silent = std::thread::spawn(move || {
        let mut buf = [0u8; 256];
        while mcu.read(&mut buf, Duration::from_millis(5)).is_ok() {}
    });
    let o = LinkOptions {
        name: "toolboard".into(),
        identify_timeout: Duration::from_millis(300),
        ..opts()
    };
    let e = McuLink::connect(Box::new(host), o).unwrap_err();
    assert_eq!(
        e.to_string(),
        "mcu 'toolboard': no answer to identify within 0.3 s"
    );
    silent.join().unwrap();
}

#[test]
fn hang_up_is_reported_as_connection_lost() {
    let (link, ctl, fake) = start(NOMINAL);
    ctl.hang_up.store(true, Ordering::Release);
    fake.join().unwrap();
    let get_clock = link.dictionary().encode("get_clock", &[]).unwrap();
    let e = link.query(get_clock, "clock", None, LONG).unwrap_err();
    // The IO thread notices on its next read or write, whichever comes first.
    assert!(e.to_string().starts_with("mcu 'mcu': connection lost ("), "{e}");
    assert!(e.to_string().contains("memory a"), "{e}");
    assert!(link.send(get_clock).is_err());
    assert!(link.wait_idle(LONG).is_err());
}

#[test]
fn shutdown_is_recorded_with_its_reason() {
    let (link, _ctl, fake) = start(NOMINAL);
    link.send(queue_step(&link, 99, 10)).unwrap();
    let cfg_cmd = link.dictionary().encode("get_config", &[]).unwrap();
    for _ in 0..200 {
        if link.shutdown_reason().is_some() {
            break;
        }
        // The config reply comes after the shutdown message, so one query is usually enough.
        let cfg = link.query(cfg_cmd, "config", None, LONG).unwrap();
        if cfg.get("is_shutdown") == Some(1) {
            break;
        }
    }
    assert_eq!(link.shutdown_reason().as_deref(), Some("Timer too close"));
    let e = link.send_clocked(queue_step(&link, 1, 10), 0, 1).unwrap_err();
    assert_eq!(e.to_string(), "mcu 'mcu': shut down: Timer too close");
    // A query the MCU answers with is_shutdown fails at once with the reason.
    let pos = link.dictionary().encode("queue_step", &[1, 1, 1, 0]).unwrap();
    let e = link.query(pos, "stepper_position", None, LONG).unwrap_err();
    assert!(matches!(e, LinkError::Shutdown { .. }), "{e}");
    drop(link);
    fake.join().unwrap();
}

#[test]
fn silence_after_connect_ends_in_no_ack() {
    let (host, mcu) = MemoryPair::new();
    let (ctl, fake) = FakeMcu::spawn(Box::new(mcu), NOMINAL, NOMINAL, 0);
    let tuning = LinkTuning {
        no_ack_timeout: Duration::from_millis(500),
        ..LinkTuning::default()
    };
    let link = McuLink::connect_with(Box::new(host), opts(), tuning).unwrap();
    ctl.silent.store(true, Ordering::Release);
    link.send(queue_step(&link, 1, 5)).unwrap();
    let e = link.wait_idle(LONG).unwrap_err();
    assert_eq!(e.to_string(), "mcu 'mcu': no ack for 0.5 s");
    assert_eq!(link.error(), Some(e));
    let stats = link.close();
    assert!(stats.queue.retransmits > 0);
    ctl.hang_up.store(true, Ordering::Release);
    fake.join().unwrap();
}

#[test]
fn survives_a_lossy_link() {
    let (host, mcu) = MemoryPair::new();
    let (ctl, fake) = FakeMcu::spawn(Box::new(mcu), NOMINAL, NOMINAL, 0);
    let faults = FaultConfig {
        seed: 99,
        drop_rate: 0.05,
        corrupt_rate: 0.05,
        duplicate_rate: 0.02,
        on_read: true,
    };
    let link = McuLink::connect(Box::new(FaultyTransport::new(host, faults)), opts()).unwrap();
    let mut expected = Vec::new();
    for i in 0..400 {
        let cmd = queue_step(&link, 3, 5000 + i);
        expected.push(cmd.as_bytes().to_vec());
        link.send(cmd).unwrap();
    }
    link.wait_idle(LONG).unwrap();
    assert_eq!(*ctl.received.lock().unwrap(), expected);
    let stats = link.close();
    assert!(stats.queue.retransmits > 0);
    fake.join().unwrap();
}

#[test]
fn works_over_a_real_pty() {
    let (master, path) = crate::transport::pty::tests::pty_pair();
    let (ctl, fake) = FakeMcu::spawn(Box::new(master), NOMINAL, NOMINAL, 0);
    let host = PtyTransport::open(&path).unwrap();
    let link = McuLink::connect(Box::new(host), opts()).unwrap();
    let cmd = queue_step(&link, 1, 42);
    link.send(cmd).unwrap();
    link.wait_idle(LONG).unwrap();
    assert_eq!(*ctl.received.lock().unwrap(), vec![cmd.as_bytes().to_vec()]);
    let stats = link.close(); // closing the slave hangs up the fake
    assert!(stats.queue.srtt > 0.0);
    fake.join().unwrap();
}

#[test]
fn full_queue_blocks_then_drains() {
    let (host, mcu) = MemoryPair::new();
    let (ctl, fake) = FakeMcu::spawn(Box::new(mcu), NOMINAL, NOMINAL, 0);
    let o = LinkOptions {
        queue_capacity: 4,
        ..opts()
    };
    let link = McuLink::connect(Box::new(host), o).unwrap();
    for i in 0..100 {
        link.send(queue_step(&link, 5, 100 + i)).unwrap();
    }
    link.wait_idle(LONG).unwrap();
    assert_eq!(ctl.received.lock().unwrap().len(), 100);
    drop(link);
    fake.join().unwrap();
}

/// Polls `link` (with `get_clock` queries that also prompt traffic) until it died or `LONG`.
fn wait_dead(link: &McuLink) -> LinkError {
    let get_clock = link.dictionary().encode("get_clock", &[]).unwrap();
    let deadline = std::time::Instant::now() + LONG;
    while std::time::Instant::now() < deadline {
        if let Some(e) = link.error() {
            return e;
        }
        let _ = link.query(get_clock, "clock", None, Duration::from_millis(100));
    }
    panic!("link still alive: {:?}", link.stats());
}

#[test]
fn corrupt_dictionary_names_the_mcu() {
    let (host, mcu) = MemoryPair::new();
    let ctl = Arc::new(Control::default());
    ctl.corrupt_dict.store(true, Ordering::Release);
    let (_ctl, fake) = FakeMcu::spawn_with(Box::new(mcu), NOMINAL, NOMINAL, 0, ctl);
    let o = LinkOptions {
        name: "toolboard".into(),
        ..opts()
    };
    let e = McuLink::connect(Box::new(host), o).unwrap_err();
    assert!(matches!(e, LinkError::Dictionary { .. }), "{e}");
    let text = e.to_string();
    assert!(
        text.starts_with("mcu 'toolboard': bad data dictionary: "),
        "{text}"
    );
    assert!(text.contains("zlib"), "{text}");
    fake.join().unwrap();
}

#[test]
fn is_shutdown_alone_is_recorded_with_its_reason() {
    let (link, ctl, fake) = start(NOMINAL);
    // The MCU is shut down but its `shutdown` message was lost: only is_shutdown tells.
    ctl.shut_silently.store(true, Ordering::Release);
    let pos = link.dictionary().encode("stepper_get_position", &[1]).unwrap();
    for _ in 0..200 {
        if link.shutdown_reason().is_some() {
            break;
        }
        link.send(queue_step(&link, 1, 10)).unwrap();
        let _ = link.query(pos, "stepper_position", None, Duration::from_millis(50));
    }
    assert_eq!(link.shutdown_reason().as_deref(), Some("Timer too close"));
    let e = link.send_clocked(queue_step(&link, 1, 10), 0, 1).unwrap_err();
    assert_eq!(e.to_string(), "mcu 'mcu': shut down: Timer too close");
    drop(link);
    fake.join().unwrap();
}

/// Sends plain messages until the host's next sequence has non-zero low bits, so a reset MCU
/// (expecting 0) is out of step with it.
fn make_seq_nonzero(link: &McuLink) {
    for i in 0..16 {
        link.wait_idle(LONG).unwrap();
        if link.stats().queue.send_seq & 0x0F != 0 {
            return;
        }
        link.send(queue_step(link, 1, 100 + i)).unwrap();
    }
    panic!("sequence stuck at 0");
}

#[test]
fn reset_announced_by_starting_is_reported() {
    let (link, ctl, fake) = start(NOMINAL);
    make_seq_nonzero(&link);
    ctl.send_starting.store(true, Ordering::Release);
    ctl.reset.store(true, Ordering::Release);
    let e = wait_dead(&link);
    assert!(matches!(e, LinkError::Reset { .. }), "{e}");
    assert!(
        e.to_string().starts_with("mcu 'mcu': MCU reset during the print"),
        "{e}"
    );
    assert!(link.send(queue_step(&link, 1, 5)).is_err());
    drop(link);
    fake.join().unwrap();
}

#[test]
fn reset_seen_as_restarted_sequence_is_reported() {
    let (link, ctl, fake) = start(NOMINAL);
    make_seq_nonzero(&link);
    ctl.reset.store(true, Ordering::Release);
    link.send(queue_step(&link, 1, 5)).unwrap();
    let e = wait_dead(&link);
    assert!(matches!(e, LinkError::Reset { .. }), "{e}");
    assert!(e.to_string().contains("sequence restarted"), "{e}");
    drop(link);
    fake.join().unwrap();
}

#[test]
fn unconfigured_mcu_is_reported_as_reset() {
    // The fake always answers is_config=0: as if it lost the configuration the host sent.
    let (link, _ctl, fake) = start(NOMINAL);
    let e = link.expect_configured(LONG).unwrap_err();
    assert_eq!(
        e.to_string(),
        "mcu 'mcu': MCU reset during the print (get_config reports is_config=0)"
    );
    assert_eq!(link.error(), Some(e));
    drop(link);
    fake.join().unwrap();
}

/// A transport that starts failing every read and write with `EIO` once told to (a USB
/// adapter that was unplugged).
struct Unplugged {
    inner: crate::transport::MemoryEnd,
    gone: Arc<std::sync::atomic::AtomicBool>,
}

impl Transport for Unplugged {
    fn read(&mut self, buf: &mut [u8], timeout: Duration) -> std::io::Result<usize> {
        if self.gone.load(Ordering::Acquire) {
            return Err(std::io::Error::from_raw_os_error(libc::EIO));
        }
        self.inner.read(buf, timeout)
    }
    fn write_all(&mut self, data: &[u8]) -> std::io::Result<()> {
        if self.gone.load(Ordering::Acquire) {
            return Err(std::io::Error::from_raw_os_error(libc::EIO));
        }
        self.inner.write_all(data)
    }
    fn describe(&self) -> String {
        "serial /dev/ttyACM0".into()
    }
}

#[test]
fn eio_from_an_unplugged_device_is_connection_lost() {
    let (host, mcu) = MemoryPair::new();
    let (_ctl, fake) = FakeMcu::spawn(Box::new(mcu), NOMINAL, NOMINAL, 0);
    let gone = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let t = Unplugged {
        inner: host,
        gone: gone.clone(),
    };
    let link = McuLink::connect(Box::new(t), opts()).unwrap();
    gone.store(true, Ordering::Release);
    let e = wait_dead(&link);
    let text = e.to_string();
    assert!(
        text.starts_with("mcu 'mcu': connection lost (read from serial /dev/ttyACM0")
            || text.starts_with("mcu 'mcu': connection lost (write to serial /dev/ttyACM0"),
        "{text}"
    );
    assert!(text.contains("os error 5"), "{text}");
    drop(link);
    fake.join().unwrap();
}

#[test]
fn pty_hang_up_is_connection_lost() {
    let (master, path) = crate::transport::pty::tests::pty_pair();
    let (ctl, fake) = FakeMcu::spawn(Box::new(master), NOMINAL, NOMINAL, 0);
    let link = McuLink::connect(Box::new(PtyTransport::open(&path).unwrap()), opts()).unwrap();
    ctl.hang_up.store(true, Ordering::Release);
    fake.join().unwrap(); // the master is closed: the slave reads EIO or end of file
    let e = wait_dead(&link);
    assert!(
        e.to_string()
            .starts_with("mcu 'mcu': connection lost (read from pty "),
        "{e}"
    );
    assert!(e.to_string().contains("tty"), "{e}");
}

#[test]
fn stats_line_reads_like_klipper() {
    let (link, _ctl, fake) = start(NOMINAL);
    let s = link.stats();
    let line = s.to_string();
    for key in [
        "mcu_awake=",
        "mcu_task_avg=",
        "mcu_task_stddev=",
        "bytes_write=",
        "bytes_read=",
        "bytes_retransmit=",
        "bytes_invalid=",
        "send_seq=",
        "receive_seq=",
        "srtt=",
        "rttvar=",
        "rto=",
        "ready_bytes=",
        "upcoming_bytes=",
        "freq=",
        "clock_residual_us=",
    ] {
        assert!(line.contains(key), "{key} missing in {line}");
    }
    assert!(!line.contains('\n'));
    assert!(line.contains(&format!("send_seq={}", s.queue.send_seq)), "{line}");
    drop(link);
    fake.join().unwrap();
}

#[test]
fn urgent_track_reports_written_relays_in_order() {
    use super::io::UrgentTrack;
    use super::shared::RelayTag;
    let tag = |member| RelayTag { group: 1, member };
    let mut t = UrgentTrack::new();
    assert!(!t.sent(3), "nothing urgent queued");
    t.pushed(None);
    t.pushed(Some(tag(0)));
    t.pushed(None);
    t.pushed(Some(tag(1)));
    assert!(!t.sent(0));
    assert!(!t.sent(1), "only the untagged first one went out");
    assert_eq!(t.pop_written(), None);
    assert!(t.sent(1));
    assert_eq!(t.pop_written(), Some(tag(0)));
    assert_eq!(t.pop_written(), None);
    // More messages than urgent ones left: the rest were plain messages.
    assert!(t.sent(10));
    assert_eq!(t.pop_written(), Some(tag(1)));
    assert_eq!(t.pop_written(), None);
    t.pushed(Some(tag(2)));
    assert!(t.sent(1));
    assert_eq!(t.pop_written(), Some(tag(2)));
    // A full ring drops the newest tags, never miscounts the older ones.
    for i in 0..40 {
        t.pushed(Some(tag(i)));
    }
    assert!(t.sent(40));
    let mut got = Vec::new();
    while let Some(x) = t.pop_written() {
        got.push(x.member);
    }
    assert_eq!(got, (0..16).collect::<Vec<_>>());
    t.pushed(Some(tag(99)));
    assert!(t.sent(1));
    assert_eq!(t.pop_written(), Some(tag(99)));
}
