//! Wake-up latency, measured as cyclictest does: one thread per chosen CPU, pinned, under
//! SCHED_FIFO when allowed, sleeps until an absolute CLOCK_MONOTONIC deadline
//! (`clock_nanosleep(TIMER_ABSTIME)`) every `interval`, reads the clock on waking and records
//! `now − deadline` in a histogram. The next deadline is the previous one plus `interval`
//! (skipping deadlines already past, counted as overruns), so lateness never accumulates.
//! In busy-wait mode the thread spins on the clock instead of sleeping: what remains is the
//! latency of being preempted or stalled (SMIs, a VM's pauses), without the timer path.
//!
//! Threads record into a fixed-bound histogram (no allocation after start) and, every
//! `log_interval`, hand the filled one to the caller over a lock-free queue in exchange for an
//! empty one; the caller writes it to the interval log and merges it into the totals. If the
//! caller falls behind, a thread keeps recording into the same histogram (a longer interval),
//! never blocks and never drops a sample.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use crossbeam_queue::ArrayQueue;
use hdrhistogram::Histogram;
use nix::errno::Errno;
use nix::sys::time::TimeSpec;
use nix::time::{clock_gettime, clock_nanosleep, ClockId, ClockNanosleepFlags};
use rt_core::os::{apply_rt, RtApplied, RtSpec, RT_STACK_SIZE};

use crate::error::BenchError;
use crate::stats::{merge, new_hist};

/// When a run ends.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stop {
    /// After this long (each thread checks after each wake-up).
    Duration(Duration),
    /// After this many wake-ups per thread.
    Loops(u64),
}

/// How each thread waits for its deadline.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Wait {
    /// `clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME)`.
    Sleep,
    /// Spin reading CLOCK_MONOTONIC.
    Busy,
}

/// What to measure.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WakeupOptions {
    /// One thread per CPU, pinned to it.
    pub cpus: Vec<usize>,
    /// SCHED_FIFO priority (`None`: normal scheduling).
    pub priority: Option<i32>,
    pub interval: Duration,
    pub stop: Stop,
    pub wait: Wait,
    /// How often threads hand their histogram over (the interval log's resolution).
    pub log_interval: Duration,
}

impl Default for WakeupOptions {
    fn default() -> Self {
        WakeupOptions {
            cpus: vec![0],
            priority: Some(80),
            interval: Duration::from_micros(1000),
            stop: Stop::Duration(Duration::from_secs(10)),
            wait: Wait::Sleep,
            log_interval: Duration::from_secs(1),
        }
    }
}

/// One thread's histogram over `[start_ns, end_ns]` (CLOCK_MONOTONIC).
#[derive(Debug)]
pub struct Interval {
    pub start_ns: u64,
    pub end_ns: u64,
    pub hist: Histogram<u64>,
}

/// One thread's results.
#[derive(Debug)]
pub struct ThreadResult {
    pub cpu: usize,
    /// Every wake-up's lateness (ns).
    pub hist: Histogram<u64>,
    /// What the OS granted (pinning, SCHED_FIFO, stack prefault).
    pub applied: RtApplied,
    /// Deadlines skipped because the thread woke after the next one had passed.
    pub overruns: u64,
}

/// CLOCK_MONOTONIC in ns.
pub fn mono_ns() -> Result<u64, BenchError> {
    let ts = clock_gettime(ClockId::CLOCK_MONOTONIC)
        .map_err(|e| BenchError::Thread(format!("clock_gettime: {e}")))?;
    Ok(ts.tv_sec() as u64 * 1_000_000_000 + ts.tv_nsec() as u64)
}

fn timespec(ns: u64) -> TimeSpec {
    TimeSpec::new((ns / 1_000_000_000) as _, (ns % 1_000_000_000) as _)
}

/// Waits until CLOCK_MONOTONIC reaches `deadline_ns`.
fn wait_until(deadline_ns: u64, wait: Wait) -> Result<(), BenchError> {
    match wait {
        Wait::Sleep => {
            let ts = timespec(deadline_ns);
            loop {
                match clock_nanosleep(ClockId::CLOCK_MONOTONIC, ClockNanosleepFlags::TIMER_ABSTIME, &ts) {
                    Ok(_) => return Ok(()),
                    Err(Errno::EINTR) => continue,
                    Err(e) => return Err(BenchError::Thread(format!("clock_nanosleep: {e}"))),
                }
            }
        }
        Wait::Busy => {
            while mono_ns()? < deadline_ns {
                std::hint::spin_loop();
            }
            Ok(())
        }
    }
}

/// The queues between one measurement thread and the caller.
#[derive(Debug)]
struct Chan {
    /// Filled intervals, thread → caller.
    full: ArrayQueue<Interval>,
    /// Empty histograms, caller → thread.
    free: ArrayQueue<Histogram<u64>>,
    /// Wake-ups so far (for progress in loop mode).
    samples: AtomicU64,
}

const QUEUE: usize = 8;

struct ThreadEnd {
    last: Interval,
    applied: RtApplied,
    overruns: u64,
}

/// The measurement loop of one thread. Allocation-free after its first histogram is taken.
fn measure(opts: &WakeupOptions, cpu: usize, chan: &Chan) -> Result<ThreadEnd, BenchError> {
    let applied = apply_rt(&RtSpec {
        core: Some(cpu),
        fifo_priority: opts.priority,
        prefault_stack: 256 * 1024,
        ..RtSpec::new(format!("bench-wake{cpu}"))
    });
    let mut cur = match chan.free.pop() {
        Some(h) => h,
        None => new_hist()?,
    };
    let interval = u64::try_from(opts.interval.as_nanos()).unwrap_or(u64::MAX).max(1);
    let log_every = u64::try_from(opts.log_interval.as_nanos()).unwrap_or(u64::MAX);
    let start = mono_ns()?;
    let end = match opts.stop {
        Stop::Duration(d) => start.saturating_add(u64::try_from(d.as_nanos()).unwrap_or(u64::MAX)),
        Stop::Loops(_) => u64::MAX,
    };
    let loops = match opts.stop {
        Stop::Loops(n) => n.max(1),
        Stop::Duration(_) => u64::MAX,
    };
    let (mut next, mut interval_start, mut flush_at) =
        (start + interval, start, start.saturating_add(log_every));
    let (mut samples, mut overruns, mut now) = (0u64, 0u64, start);
    while samples < loops && now < end {
        wait_until(next, opts.wait)?;
        now = mono_ns()?;
        cur.saturating_record(now.saturating_sub(next));
        samples += 1;
        // Relaxed: a progress counter, read for display only.
        chan.samples.store(samples, Ordering::Relaxed);
        next = next.saturating_add(interval);
        while next <= now {
            next = next.saturating_add(interval);
            overruns += 1;
        }
        // Only this thread pushes to `full`, so a non-full queue takes the push.
        if now >= flush_at && !chan.full.is_full() {
            if let Some(fresh) = chan.free.pop() {
                let hist = std::mem::replace(&mut cur, fresh);
                let _ = chan.full.push(Interval {
                    start_ns: interval_start,
                    end_ns: now,
                    hist,
                });
                interval_start = now;
            }
            flush_at = now.saturating_add(log_every);
        }
    }
    Ok(ThreadEnd {
        last: Interval {
            start_ns: interval_start,
            end_ns: now,
            hist: cur,
        },
        applied,
        overruns,
    })
}

/// Runs one measurement: a thread per CPU until `opts.stop`. `on_interval(thread, interval)` is
/// called on this thread for every filled interval (then merged into that thread's total);
/// `on_tick(samples)` about every 100 ms with the wake-ups so far, summed over threads.
pub fn run(
    opts: &WakeupOptions,
    on_interval: &mut dyn FnMut(usize, &Interval) -> Result<(), BenchError>,
    on_tick: &mut dyn FnMut(u64),
) -> Result<Vec<ThreadResult>, BenchError> {
    if opts.cpus.is_empty() {
        return Err(BenchError::Options("no CPU to measure on".into()));
    }
    let mut chans = Vec::new();
    let mut handles: Vec<JoinHandle<Result<ThreadEnd, BenchError>>> = Vec::new();
    for &cpu in &opts.cpus {
        let chan = Arc::new(Chan {
            full: ArrayQueue::new(QUEUE),
            free: ArrayQueue::new(QUEUE),
            samples: AtomicU64::new(0),
        });
        for _ in 0..3 {
            let _ = chan.free.push(new_hist()?);
        }
        let (c, o) = (chan.clone(), opts.clone());
        let handle = std::thread::Builder::new()
            .name(format!("bench-wake{cpu}"))
            .stack_size(RT_STACK_SIZE)
            .spawn(move || measure(&o, cpu, &c))
            .map_err(|e| BenchError::Thread(format!("spawning the thread for CPU {cpu}: {e}")))?;
        chans.push(chan);
        handles.push(handle);
    }
    let mut totals = Vec::new();
    for _ in &opts.cpus {
        totals.push(new_hist()?);
    }
    let drain = |totals: &mut Vec<Histogram<u64>>,
                 on_interval: &mut dyn FnMut(usize, &Interval) -> Result<(), BenchError>| {
        for (i, chan) in chans.iter().enumerate() {
            while let Some(mut iv) = chan.full.pop() {
                on_interval(i, &iv)?;
                merge(&mut totals[i], &iv.hist)?;
                iv.hist.reset();
                let _ = chan.free.push(iv.hist);
            }
        }
        Ok::<_, BenchError>(())
    };
    while !handles.iter().all(|h| h.is_finished()) {
        std::thread::sleep(Duration::from_millis(100));
        drain(&mut totals, on_interval)?;
        on_tick(chans.iter().map(|c| c.samples.load(Ordering::Relaxed)).sum());
    }
    drain(&mut totals, on_interval)?;
    let mut out = Vec::new();
    for ((handle, mut total), &cpu) in handles.into_iter().zip(totals).zip(&opts.cpus) {
        let end = handle
            .join()
            .map_err(|_| BenchError::Thread(format!("the thread on CPU {cpu} panicked")))??;
        on_interval(out.len(), &end.last)?;
        merge(&mut total, &end.last.hist)?;
        out.push(ThreadResult {
            cpu,
            hist: total,
            applied: end.applied,
            overruns: end.overruns,
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn short(wait: Wait, stop: Stop) -> WakeupOptions {
        WakeupOptions {
            cpus: vec![0],
            priority: None,
            interval: Duration::from_micros(500),
            stop,
            wait,
            log_interval: Duration::from_millis(20),
        }
    }

    #[test]
    fn loops_give_exactly_that_many_samples_in_intervals() {
        let mut seen = 0;
        let mut intervals = 0;
        let r = run(
            &short(Wait::Sleep, Stop::Loops(200)),
            &mut |i, iv| {
                assert_eq!(i, 0);
                assert!(iv.end_ns >= iv.start_ns);
                seen += iv.hist.len();
                intervals += 1;
                Ok(())
            },
            &mut |_| {},
        )
        .unwrap();
        assert_eq!(r.len(), 1);
        assert_eq!(r[0].hist.len(), 200);
        // The intervals add up to the total: nothing dropped between thread and caller.
        assert_eq!(seen, 200);
        assert!(intervals >= 1);
        assert!(r[0].applied.pinned);
    }

    #[test]
    fn busy_wait_and_duration_stop() {
        let r = run(
            &short(Wait::Busy, Stop::Duration(Duration::from_millis(30))),
            &mut |_, _| Ok(()),
            &mut |_| {},
        )
        .unwrap();
        assert!(!r[0].hist.is_empty());
    }

    #[test]
    fn no_cpu_is_an_error() {
        let o = WakeupOptions {
            cpus: vec![],
            ..WakeupOptions::default()
        };
        assert!(run(&o, &mut |_, _| Ok(()), &mut |_| {}).is_err());
    }
}
