//! Idle polling: one SCHED_IDLE thread per CPU spins while a latency-critical phase runs
//! (a homing or probing move), so no CPU of the machine enters its idle state meanwhile.
//!
//! Why: a CPU with nothing to run halts (`hlt`, or a C-state on bare metal); waking a thread on
//! it then first pays the exit from that state, which on a virtual machine is a VM exit and a
//! wait for the hypervisor to run the vCPU again (this kind of machine: a 1 ms sleeper wakes
//! p50 29 µs / p99.9 121 µs late with idle CPUs, 6 µs / 42 µs with them polling). Holding
//! `/dev/cpu_dma_latency` at 0 asks the kernel's cpuidle governor for the same thing, but a
//! kernel without a cpuidle driver (many VMs) ignores it; `idle=poll` on the kernel command
//! line does it for the whole uptime. Polling only for the seconds a homing move lasts costs
//! those seconds of CPU power and nothing else:
//!
//! - a SCHED_IDLE thread runs only when its CPU has nothing else of any other policy to run,
//!   and is preempted at once by any waking thread (SCHED_OTHER or real-time): the kernel's
//!   pty and serial work, the MCU IO threads and the simulators all run as before;
//! - it spins on a relaxed atomic load with the CPU's pause hint, touching no shared cache
//!   line but the stop flag.
//!
//! Measured trade-off (why `[realtime] idle_poll_homing` is off by default): on the 2-vCPU VM
//! this was built on, the VM itself pauses for up to ~25 ms now and then; with the CPUs polling
//! while other work ran, those pauses came more often (11 homing timeouts in 12 runs of 20
//! cycles, none in 6 without polling), and on a quiet machine the tail was no better. On bare
//! metal, where a halted core costs only its C-state exit, the trade-off is the usual one of
//! `idle=poll`.
//!
//! Threads are started by [`IdlePoll::start`] and told to end when the guard drops.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use super::report::{refused, Guarantee};
use super::sys;

/// Stack of a polling thread (it only spins; small so that `mlockall(MCL_FUTURE)` locks little).
const POLL_STACK: usize = 64 * 1024;

/// Spinning SCHED_IDLE threads, one per online CPU, until dropped.
///
/// Neither starting nor stopping waits for the threads: under a full CPU load a SCHED_IDLE
/// thread may wait long for its first slice, and the caller (a real-time planner thread)
/// must not wait with it. A thread whose SCHED_IDLE is refused reports it once
/// ([`super::rt_report`]) and ends without spinning.
#[derive(Debug)]
pub struct IdlePoll {
    stop: Arc<AtomicBool>,
    tids: Arc<Mutex<Vec<i32>>>,
    threads: usize,
}

impl IdlePoll {
    /// Starts one polling thread per online CPU; each switches itself to SCHED_IDLE before it
    /// does anything else (it inherits its creator's policy, maybe SCHED_FIFO), then pins
    /// itself to its CPU (where a cpuset refuses the pin it still keeps some CPU busy). The
    /// caller's own affinity does not matter (a pinned planner thread may start it). Errs
    /// only when no thread could be spawned.
    pub fn start() -> std::io::Result<IdlePoll> {
        let stop = Arc::new(AtomicBool::new(false));
        let tids = Arc::new(Mutex::new(Vec::new()));
        let mut threads = 0;
        let mut last_err = None;
        for core in 0..sys::online_cpus() {
            let (stop, tids) = (stop.clone(), tids.clone());
            let spawned = std::thread::Builder::new()
                .name(format!("idle-poll-{core}"))
                .stack_size(POLL_STACK)
                .spawn(move || {
                    if let Err(e) = sys::set_idle_policy() {
                        let error = format!("SCHED_IDLE refused ({e})");
                        refused(
                            Guarantee::IdlePoll,
                            "idle-poll",
                            &error,
                            "idle CPUs may halt during homing",
                        );
                        return;
                    }
                    if core < sys::CPU_SETSIZE {
                        let _ = sys::set_affinity(core);
                    }
                    tids.lock().unwrap_or_else(|p| p.into_inner()).push(sys::gettid());
                    while !stop.load(Ordering::Relaxed) {
                        std::hint::spin_loop();
                    }
                });
            match spawned {
                Ok(_) => threads += 1,
                Err(e) => last_err = Some(e),
            }
        }
        match (threads, last_err) {
            (0, Some(e)) => Err(e),
            _ => Ok(IdlePoll { stop, tids, threads }),
        }
    }

    /// Polling threads started.
    pub fn threads(&self) -> usize {
        self.threads
    }

    /// The kernel thread ids (`/proc/self/task/TID`) of the threads spinning so far.
    pub fn thread_ids(&self) -> Vec<i32> {
        self.tids.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }
}

impl Drop for IdlePoll {
    /// Tells the threads to end (each does at its next slice).
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::{Duration, Instant};

    /// Waits up to 10 s for `cond`.
    fn eventually(mut cond: impl FnMut() -> bool) -> bool {
        let deadline = Instant::now() + Duration::from_secs(10);
        while Instant::now() < deadline {
            if cond() {
                return true;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        cond()
    }

    #[test]
    fn one_sched_idle_thread_per_cpu_until_dropped() {
        let poll = IdlePoll::start().unwrap();
        let cpus = sys::online_cpus();
        assert_eq!(poll.threads(), cpus);
        assert!(
            eventually(|| poll.thread_ids().len() == cpus),
            "every thread spins"
        );
        // Each thread's policy as the kernel shows it (field 41 of /proc/.../stat: 5 = SCHED_IDLE).
        let tids = poll.thread_ids();
        for tid in &tids {
            let stat = std::fs::read_to_string(format!("/proc/self/task/{tid}/stat")).unwrap();
            // The fields after the ")" closing the name start at field 3 (state).
            let rest = &stat[stat.rfind(')').unwrap() + 2..];
            let policy: i32 = rest.split(' ').nth(41 - 3).unwrap().parse().unwrap();
            assert_eq!(policy, libc::SCHED_IDLE, "thread {tid}: {stat}");
        }
        drop(poll);
        for tid in &tids {
            let dir = format!("/proc/self/task/{tid}");
            assert!(
                eventually(|| !std::path::Path::new(&dir).exists()),
                "thread {tid} ends once the guard drops"
            );
        }
    }

    #[test]
    fn started_from_a_fifo_thread_the_pollers_still_run_as_sched_idle() {
        // Without the privilege the creator stays SCHED_OTHER: the test then covers that case.
        let t = std::thread::spawn(|| {
            let _ = super::super::set_current_thread_fifo(10);
            let _ = super::super::pin_current_thread(0);
            let poll = IdlePoll::start().unwrap();
            // The creator blocks, so the pollers (inheriting its SCHED_FIFO and core) get to
            // drop to SCHED_IDLE; they then never keep it from running.
            let spinning = eventually(|| poll.thread_ids().len() == poll.threads());
            let busy_until = Instant::now() + Duration::from_millis(20);
            while Instant::now() < busy_until {
                std::hint::spin_loop();
            }
            spinning
        });
        assert!(t.join().unwrap());
    }
}
