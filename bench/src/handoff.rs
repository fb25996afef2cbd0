//! Hand-off latency between two pinned threads (and two processes): the time from just before
//! a producer publishes a timestamped message to the moment the consumer holds it, recorded in
//! a fixed-bound ns histogram (`rt_core::hist`). Transports:
//!
//! - `queue-poll`: `crossbeam_queue::ArrayQueue`, consumer polls with `spin_loop`.
//! - `handoff-poll`: `rt_core::handoff::HandoffQueue` (the link's and the logger's queue: never
//!   waits on the other thread), consumer polls.
//! - `queue-park`: same queue as `queue-poll`, consumer spins for `spin` then parks; the producer unparks it
//!   when it saw the consumer's "parked" flag (the flag is set before parking and re-checked
//!   after, so no wake-up is lost).
//! - `ipc-poll` / `ipc-event`: iceoryx2 publish-subscribe of a 5 KiB `StepBatch` (zero-copy
//!   loan), consumer polls `receive()` or sleeps on the event service.
//! - `proc-poll` / `proc-event`: the same with the consumer in a child process
//!   (`cadence bench handoff-child ...`), which prints its histogram on stdout.
//!
//! The producer paces messages `gap` apart (spinning for short gaps, so the consumer sees a
//! steady stream rather than a burst). Timestamps are CLOCK_MONOTONIC ns (shared by processes).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crossbeam_queue::ArrayQueue;
use hdrhistogram::serialization::{Deserializer, Serializer, V2DeflateSerializer};
use hdrhistogram::Histogram;
use iceoryx2::prelude::*;
use rt_core::handoff::HandoffQueue;
use rt_core::hist::LatencyHist;
use rt_core::os::{spawn_rt, RtSpec};
use rt_core::shm::{open_node, ChannelConfig, ShmPublisher, ShmSubscriber, StepBatch};

/// Benchmark settings.
#[derive(Debug, Clone)]
pub struct HandoffOpts {
    /// Messages per transport.
    pub samples: u64,
    /// Producer core, consumer core.
    pub cores: (usize, usize),
    /// SCHED_FIFO priority for both threads (None = normal).
    pub fifo: Option<i32>,
    /// Time between messages.
    pub gap: Duration,
    /// Spin budget of `queue-park` before parking.
    pub spin: Duration,
}

impl Default for HandoffOpts {
    fn default() -> Self {
        HandoffOpts {
            samples: 50_000,
            cores: (0, 1),
            fifo: None,
            gap: Duration::from_micros(20),
            spin: Duration::from_micros(50),
        }
    }
}

/// CLOCK_MONOTONIC in ns (comparable across processes).
pub fn mono_ns() -> u64 {
    match nix::time::clock_gettime(nix::time::ClockId::CLOCK_MONOTONIC) {
        Ok(ts) => ts.tv_sec() as u64 * 1_000_000_000 + ts.tv_nsec() as u64,
        Err(_) => 0,
    }
}

fn pace(gap: Duration) {
    if gap >= Duration::from_micros(200) {
        std::thread::sleep(gap);
    } else {
        let until = Instant::now() + gap;
        while Instant::now() < until {
            std::hint::spin_loop();
        }
    }
}

fn spec(name: &str, core: usize, fifo: Option<i32>) -> RtSpec {
    RtSpec {
        core: Some(core),
        fifo_priority: fifo,
        ..RtSpec::new(name)
    }
}

fn join<T>(h: std::io::Result<std::thread::JoinHandle<T>>) -> Result<T, String> {
    h.map_err(|e| format!("spawn: {e}"))?
        .join()
        .map_err(|_| "benchmark thread panicked".to_string())
}

/// A bounded queue of timestamps between two threads.
trait BenchQueue: Send + Sync + 'static {
    fn put(&self, v: u64) -> Result<(), u64>;
    fn take(&self) -> Option<u64>;
}

impl BenchQueue for ArrayQueue<u64> {
    fn put(&self, v: u64) -> Result<(), u64> {
        self.push(v)
    }
    fn take(&self) -> Option<u64> {
        self.pop()
    }
}

impl BenchQueue for HandoffQueue<u64> {
    fn put(&self, v: u64) -> Result<(), u64> {
        self.push(v)
    }
    fn take(&self) -> Option<u64> {
        self.pop()
    }
}

/// ArrayQueue, polling consumer.
pub fn queue_poll(o: &HandoffOpts) -> Result<LatencyHist, String> {
    poll_with(ArrayQueue::<u64>::new(1024), o)
}

/// rt_core::handoff::HandoffQueue (the link's and the logger's queue), polling consumer.
pub fn handoff_poll(o: &HandoffOpts) -> Result<LatencyHist, String> {
    poll_with(HandoffQueue::<u64>::new(1024), o)
}

fn poll_with<Q: BenchQueue>(q: Q, o: &HandoffOpts) -> Result<LatencyHist, String> {
    let q = Arc::new(q);
    let n = o.samples;
    let qc = q.clone();
    let consumer = spawn_rt(spec("bench-cons", o.cores.1, o.fifo), move || {
        let mut h = LatencyHist::new();
        let mut got = 0;
        while got < n {
            match qc.take() {
                Some(t) => {
                    h.record(mono_ns().saturating_sub(t));
                    got += 1;
                }
                None => std::hint::spin_loop(),
            }
        }
        h
    });
    let gap = o.gap;
    join(spawn_rt(spec("bench-prod", o.cores.0, o.fifo), move || {
        for _ in 0..n {
            let mut t = mono_ns();
            while let Err(back) = q.put(t) {
                t = back;
                std::hint::spin_loop();
            }
            pace(gap);
        }
    }))?;
    join(consumer)
}

/// ArrayQueue, consumer spins for `spin` then parks.
pub fn queue_park(o: &HandoffOpts) -> Result<LatencyHist, String> {
    let q = Arc::new(ArrayQueue::<u64>::new(1024));
    let parked = Arc::new(AtomicBool::new(false));
    let n = o.samples;
    let (qc, pc, spin) = (q.clone(), parked.clone(), o.spin);
    let consumer = spawn_rt(spec("bench-cons", o.cores.1, o.fifo), move || {
        let mut h = LatencyHist::new();
        let mut got = 0;
        while got < n {
            let started = Instant::now();
            let t = loop {
                if let Some(t) = qc.pop() {
                    break Some(t);
                }
                if started.elapsed() > spin {
                    // SeqCst pairs with the producer's SeqCst load after its push: either the
                    // producer sees `parked` and unparks, or we see its item on the re-check.
                    pc.store(true, Ordering::SeqCst);
                    if let Some(t) = qc.pop() {
                        pc.store(false, Ordering::SeqCst);
                        break Some(t);
                    }
                    std::thread::park_timeout(Duration::from_millis(100));
                    pc.store(false, Ordering::SeqCst);
                    break None;
                }
                std::hint::spin_loop();
            };
            if let Some(t) = t {
                h.record(mono_ns().saturating_sub(t));
                got += 1;
            }
        }
        h
    })
    .map_err(|e| format!("spawn: {e}"))?;
    let cons_thread = consumer.thread().clone();
    let gap = o.gap;
    join(spawn_rt(spec("bench-prod", o.cores.0, o.fifo), move || {
        for _ in 0..n {
            let mut t = mono_ns();
            while let Err(back) = q.push(t) {
                t = back;
                std::hint::spin_loop();
            }
            if parked.load(Ordering::SeqCst) {
                cons_thread.unpark();
            }
            pace(gap);
        }
    }))?;
    consumer.join().map_err(|_| "consumer panicked".to_string())
}

fn instance() -> String {
    format!("bench-{}", std::process::id())
}

/// The consumer half over iceoryx2: polling (`poll`) or sleeping on the event service.
pub fn ipc_consume(service: &str, n: u64, poll: bool) -> Result<LatencyHist, String> {
    let (node, _) = open_node::<ipc::Service>("bench-sub").map_err(|e| e.to_string())?;
    let mut sub = ShmSubscriber::<ipc::Service, StepBatch>::open(&node, service, &ChannelConfig::steps())
        .map_err(|e| e.to_string())?;
    let mut h = LatencyHist::new();
    let mut got = 0;
    let started = Instant::now();
    while got < n {
        if started.elapsed() > Duration::from_secs(120) {
            return Err(format!("consumer stalled after {got} of {n}"));
        }
        let stamp = if poll {
            let r = sub
                .try_recv_with(|b| b.msgs[0].min_clock)
                .map_err(|e| e.to_string())?;
            if r.is_none() {
                std::hint::spin_loop();
            }
            r
        } else {
            sub.recv_timeout_with(Duration::from_millis(100), |b| b.msgs[0].min_clock)
                .map_err(|e| e.to_string())?
        };
        if let Some(t) = stamp {
            h.record(mono_ns().saturating_sub(t));
            got += 1;
        }
    }
    Ok(h)
}

/// The producer half over iceoryx2: waits for `subscribers`, then sends `n` stamped batches.
pub fn ipc_produce(service: &str, n: u64, gap: Duration, subscribers: usize) -> Result<(), String> {
    let (node, _) = open_node::<ipc::Service>("bench-pub").map_err(|e| e.to_string())?;
    let mut p = ShmPublisher::<ipc::Service, StepBatch>::open(&node, service, &ChannelConfig::steps())
        .map_err(|e| e.to_string())?;
    let started = Instant::now();
    while p.connect().map_err(|e| e.to_string())? < subscribers {
        if started.elapsed() > Duration::from_secs(30) {
            return Err("subscriber never connected".into());
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    // Let the subscriber connect its side (it does on its next receive).
    std::thread::sleep(Duration::from_millis(200));
    for _ in 0..n {
        p.send_with(|b| {
            b.count = 1;
            b.msgs[0].min_clock = mono_ns();
        })
        .map_err(|e| e.to_string())?;
        pace(gap);
    }
    Ok(())
}

/// iceoryx2 between two pinned threads of this process.
pub fn ipc_threads(o: &HandoffOpts, poll: bool) -> Result<LatencyHist, String> {
    let service = rt_core::shm::steps_service_name(&instance(), if poll { "poll" } else { "event" });
    let (n, s2) = (o.samples, service.clone());
    let consumer = spawn_rt(spec("bench-cons", o.cores.1, o.fifo), move || {
        ipc_consume(&s2, n, poll)
    });
    let gap = o.gap;
    join(spawn_rt(spec("bench-prod", o.cores.0, o.fifo), move || {
        ipc_produce(&service, n, gap, 1)
    }))??;
    join(consumer)?
}

/// How to start the consumer process: `exe args... SERVICE SAMPLES poll|event CORE` (the CLI's
/// hidden `cadence bench handoff-child`), which prints [`encode_hist`] of its histogram.
#[derive(Debug, Clone)]
pub struct ChildCommand {
    pub exe: std::path::PathBuf,
    pub args: Vec<String>,
}

/// iceoryx2 with the consumer in a child process (see [`ChildCommand`]).
pub fn ipc_process(o: &HandoffOpts, child_cmd: &ChildCommand, poll: bool) -> Result<Histogram<u64>, String> {
    let service = rt_core::shm::steps_service_name(&instance(), "xproc");
    let child = std::process::Command::new(&child_cmd.exe)
        .args(&child_cmd.args)
        .args([
            service.as_str(),
            &o.samples.to_string(),
            if poll { "poll" } else { "event" },
            &o.cores.1.to_string(),
        ])
        .stdout(std::process::Stdio::piped())
        .spawn()
        .map_err(|e| format!("{}: {e}", child_cmd.exe.display()))?;
    let (n, gap) = (o.samples, o.gap);
    join(spawn_rt(spec("bench-prod", o.cores.0, o.fifo), move || {
        ipc_produce(&service, n, gap, 1)
    }))??;
    let out = child.wait_with_output().map_err(|e| e.to_string())?;
    if !out.status.success() {
        return Err(format!("child failed: {}", out.status));
    }
    decode_hist(String::from_utf8_lossy(&out.stdout).trim())
}

/// The consumer process's work: pinned to `core`, receives `n` samples on `service` and
/// returns the line to print (its histogram, [`encode_hist`]).
pub fn child_main(service: &str, n: u64, poll: bool, core: usize) -> Result<String, String> {
    rt_core::os::apply_rt(&RtSpec {
        core: Some(core),
        ..RtSpec::new("bench-child")
    });
    let h = ipc_consume(service, n, poll)?;
    encode_hist(h.histogram())
}

/// A histogram as one line: base64 of its V2 deflate serialization (as in interval logs).
pub fn encode_hist(h: &Histogram<u64>) -> Result<String, String> {
    use base64::Engine as _;
    let mut buf = Vec::new();
    V2DeflateSerializer::new()
        .serialize(h, &mut buf)
        .map_err(|e| format!("serializing the histogram: {e:?}"))?;
    Ok(base64::engine::general_purpose::STANDARD.encode(buf))
}

/// The inverse of [`encode_hist`].
pub fn decode_hist(line: &str) -> Result<Histogram<u64>, String> {
    use base64::Engine as _;
    let raw = base64::engine::general_purpose::STANDARD
        .decode(line)
        .map_err(|e| format!("the child's histogram line: {e}"))?;
    Deserializer::new()
        .deserialize(&mut raw.as_slice())
        .map_err(|e| format!("the child's histogram: {e:?}"))
}

/// The transports [`run_one`] measures, in order (the `proc-` ones need a child command).
pub const TRANSPORTS: [&str; 7] = [
    "queue-poll",
    "handoff-poll",
    "queue-park",
    "ipc-poll",
    "ipc-event",
    "proc-poll",
    "proc-event",
];

/// Measures one transport of [`TRANSPORTS`].
pub fn run_one(name: &str, o: &HandoffOpts, child: Option<&ChildCommand>) -> Result<Histogram<u64>, String> {
    let hist = |r: Result<LatencyHist, String>| r.map(|h| h.histogram().clone());
    match (name, child) {
        ("queue-poll", _) => hist(queue_poll(o)),
        ("handoff-poll", _) => hist(handoff_poll(o)),
        ("queue-park", _) => hist(queue_park(o)),
        ("ipc-poll", _) => hist(ipc_threads(o, true)),
        ("ipc-event", _) => hist(ipc_threads(o, false)),
        ("proc-poll", Some(c)) => ipc_process(o, c, true),
        ("proc-event", Some(c)) => ipc_process(o, c, false),
        (other, _) => Err(format!("transport {other} is not available here")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn queue_transports_deliver_every_sample() {
        let o = HandoffOpts {
            samples: 200,
            gap: Duration::from_micros(5),
            ..HandoffOpts::default()
        };
        assert_eq!(queue_poll(&o).unwrap().count(), 200);
        assert_eq!(queue_park(&o).unwrap().count(), 200);
    }

    #[test]
    fn ipc_threads_deliver_every_sample() {
        let o = HandoffOpts {
            samples: 100,
            ..HandoffOpts::default()
        };
        // A hang (iceoryx2 waiting on a dead process's storage) fails here instead of stalling
        // the whole run.
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let _ = tx.send(ipc_threads(&o, false).map(|h| h.count()));
        });
        let got = rx
            .recv_timeout(Duration::from_secs(240))
            .expect("the iceoryx2 hand-off did not finish within 240 s");
        assert_eq!(got.unwrap(), 100);
    }

    #[test]
    fn histograms_cross_the_process_boundary_as_one_line() {
        let mut h = crate::stats::new_hist().unwrap();
        h.record(1234).unwrap();
        h.record(5_000_000).unwrap();
        let line = encode_hist(&h).unwrap();
        assert!(!line.contains('\n'));
        let back = decode_hist(&line).unwrap();
        assert_eq!((back.len(), back.max()), (2, h.max()));
        assert!(decode_hist("not base64!").is_err());
    }
}
