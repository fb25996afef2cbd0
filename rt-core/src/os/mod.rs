//! The thread runtime's OS layer (std only): pin a thread to a core, raise it to SCHED_FIFO,
//! lock memory, prefault the stack, hold `/dev/cpu_dma_latency` at 0 and keep idle CPUs polling
//! ([`IdlePoll`]).
//!
//! Every call returns a [`RtError`] naming what was refused and why (EPERM without privilege,
//! EINVAL for a core that does not exist ...). [`spawn_rt`] applies an [`RtSpec`] inside the new
//! thread, never fails because the OS refused a guarantee, and records each refusal in the
//! process-wide report ([`rt_report`]), printing the first refusal of each kind once to stderr,
//! e.g. `realtime: SCHED_FIFO priority 50 refused (EPERM: ...): running with normal priority`.
//!
//! `unsafe` lives only in the private `sys` module (libc calls) and in [`crate::alloc_count`].

mod idle_poll;
mod report;
mod sys;

use std::fmt;
use std::fs::File;
use std::io::{self, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;

pub use idle_poll::IdlePoll;
pub use report::{clear_rt_report_for_tests, ok_or_report, report_refusal, rt_report, Guarantee};

/// An OS error number with its symbolic name in `Display` ("EPERM: Operation not permitted").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Errno(pub i32);

impl Errno {
    /// The symbolic name of the common errors the runtime meets, else "errno N".
    pub fn name(self) -> &'static str {
        match self.0 {
            libc::EPERM => "EPERM",
            libc::EINVAL => "EINVAL",
            libc::ENOMEM => "ENOMEM",
            libc::ESRCH => "ESRCH",
            libc::EAGAIN => "EAGAIN",
            libc::EACCES => "EACCES",
            libc::ENOENT => "ENOENT",
            _ => "errno",
        }
    }
}

impl fmt::Display for Errno {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.name(), io::Error::from_raw_os_error(self.0))
    }
}

/// Why a real-time guarantee could not be applied.
#[derive(Debug, thiserror::Error)]
pub enum RtError {
    /// `pin_current_thread` got a core index a CPU set cannot even hold.
    #[error("core {core} does not exist (at most {max} cores)")]
    NoSuchCore { core: usize, max: usize },
    /// The kernel refused the affinity (EINVAL: core offline or absent; EPERM: cgroup/cpuset).
    #[error("pinning to core {core} refused ({errno})")]
    Affinity { core: usize, errno: Errno },
    /// The SCHED_FIFO priority is outside what the kernel accepts.
    #[error("SCHED_FIFO priority {priority} is outside {min}..={max}")]
    PriorityRange { priority: i32, min: i32, max: i32 },
    /// `pthread_setschedparam` refused (EPERM: no CAP_SYS_NICE / RLIMIT_RTPRIO).
    #[error("SCHED_FIFO priority {priority} refused ({errno})")]
    Fifo { priority: i32, errno: Errno },
    /// `mlockall` refused (EPERM: no CAP_IPC_LOCK; ENOMEM: RLIMIT_MEMLOCK too small).
    #[error("mlockall(MCL_CURRENT|MCL_FUTURE) refused ({errno})")]
    LockMemory { errno: Errno },
    /// The stack cannot be prefaulted by that much (it would overflow the thread's stack).
    #[error("prefaulting {bytes} bytes of stack: the thread's stack is only {stack} bytes")]
    StackTooSmall { bytes: usize, stack: usize },
    /// The thread's stack size could not be read.
    #[error("reading the thread's stack size failed ({errno})")]
    StackQuery { errno: Errno },
    /// `/dev/cpu_dma_latency` could not be opened or written.
    #[error("/dev/cpu_dma_latency: {0}")]
    DmaLatency(io::Error),
}

/// Pins the calling thread to CPU `core`.
pub fn pin_current_thread(core: usize) -> Result<(), RtError> {
    if core >= sys::CPU_SETSIZE {
        return Err(RtError::NoSuchCore {
            core,
            max: sys::CPU_SETSIZE,
        });
    }
    sys::set_affinity(core).map_err(|errno| RtError::Affinity { core, errno })
}

/// Switches the calling thread to SCHED_FIFO at `priority` (1..=99 on Linux).
pub fn set_current_thread_fifo(priority: i32) -> Result<(), RtError> {
    let (min, max) = sys::fifo_priority_range();
    if priority < min || priority > max {
        return Err(RtError::PriorityRange { priority, min, max });
    }
    sys::set_fifo(priority).map_err(|errno| RtError::Fifo { priority, errno })
}

/// True when the calling thread runs under SCHED_FIFO.
pub fn current_thread_is_fifo() -> bool {
    sys::current_policy() == Ok(libc::SCHED_FIFO)
}

/// Locks all current and future pages of the process in RAM (`mlockall(MCL_CURRENT|MCL_FUTURE)`).
pub fn lock_memory() -> Result<(), RtError> {
    sys::mlockall().map_err(|errno| RtError::LockMemory { errno })
}

/// Headroom left below a prefaulted stack region for the frames around the call.
const STACK_HEADROOM: usize = 64 * 1024;
/// Bytes touched per recursion level of [`prefault_stack`].
const PREFAULT_CHUNK: usize = 4096;

/// Touches `bytes` of the calling thread's stack so later deep calls take no page fault (after
/// [`lock_memory`] the pages then stay resident). Refuses sizes that would not leave 64 KiB of
/// headroom in the thread's stack.
pub fn prefault_stack(bytes: usize) -> Result<(), RtError> {
    let stack = sys::current_stack_size().map_err(|errno| RtError::StackQuery { errno })?;
    if bytes.saturating_add(STACK_HEADROOM) > stack {
        return Err(RtError::StackTooSmall { bytes, stack });
    }
    touch_stack(bytes.div_ceil(PREFAULT_CHUNK));
    Ok(())
}

#[inline(never)]
fn touch_stack(chunks: usize) {
    let mut page = [0u8; PREFAULT_CHUNK];
    std::hint::black_box(&mut page);
    if chunks > 1 {
        touch_stack(chunks - 1);
    }
    std::hint::black_box(&page);
}

/// Keeps `/dev/cpu_dma_latency` open at 0 µs while alive, so idle CPUs stay in shallow
/// C-states (halves idle wake-up latency on this kind of machine). Dropping it restores the
/// kernel default.
#[derive(Debug)]
pub struct DmaLatencyHold {
    _file: File,
}

/// Opens `/dev/cpu_dma_latency` and writes 0 (best effort: callers usually only report the
/// error).
pub fn hold_cpu_dma_latency_zero() -> Result<DmaLatencyHold, RtError> {
    let mut file = std::fs::OpenOptions::new()
        .write(true)
        .open("/dev/cpu_dma_latency")
        .map_err(RtError::DmaLatency)?;
    file.write_all(&0i32.to_ne_bytes()).map_err(RtError::DmaLatency)?;
    Ok(DmaLatencyHold { _file: file })
}

/// What a real-time thread asks of the OS.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RtSpec {
    /// Thread name (shown by `ps -L`, `top -H`; Linux keeps the first 15 bytes).
    pub name: String,
    /// Pin to this core.
    pub core: Option<usize>,
    /// SCHED_FIFO at this priority.
    pub fifo_priority: Option<i32>,
    /// `mlockall` (process-wide; done once by the first thread that asks).
    pub lock_memory: bool,
    /// Bytes of stack to prefault (0 = none).
    pub prefault_stack: usize,
}

impl RtSpec {
    /// A spec that asks for nothing but a name.
    pub fn new(name: impl Into<String>) -> RtSpec {
        RtSpec {
            name: name.into(),
            core: None,
            fifo_priority: None,
            lock_memory: false,
            prefault_stack: 0,
        }
    }
}

/// What [`apply_rt`] obtained for the calling thread.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct RtApplied {
    pub pinned: bool,
    pub fifo: bool,
    pub memory_locked: bool,
    pub stack_prefaulted: bool,
}

/// Stack size of threads made by [`spawn_rt`]; prefault requests must leave headroom in it.
pub const RT_STACK_SIZE: usize = 2 * 1024 * 1024;

static MEMORY_LOCKED: AtomicBool = AtomicBool::new(false);

/// Applies `spec` to the calling thread. Never fails: each refusal is recorded in the
/// process-wide report and the thread runs on without that guarantee.
pub fn apply_rt(spec: &RtSpec) -> RtApplied {
    let mut got = RtApplied::default();
    if let Some(core) = spec.core {
        match pin_current_thread(core) {
            Ok(()) => got.pinned = true,
            Err(e) => report::refused(Guarantee::Affinity, &spec.name, &e, "running unpinned"),
        }
    }
    if let Some(priority) = spec.fifo_priority {
        match set_current_thread_fifo(priority) {
            Ok(()) => got.fifo = true,
            Err(e) => report::refused(Guarantee::Fifo, &spec.name, &e, "running with normal priority"),
        }
    }
    if spec.lock_memory {
        // Acquire pairs with the Release store below: a thread that sees `true` knows the lock
        // succeeded and need not call mlockall again.
        if MEMORY_LOCKED.load(Ordering::Acquire) {
            got.memory_locked = true;
        } else {
            match lock_memory() {
                Ok(()) => {
                    MEMORY_LOCKED.store(true, Ordering::Release);
                    got.memory_locked = true;
                }
                Err(e) => report::refused(Guarantee::LockMemory, &spec.name, &e, "pages may be swapped"),
            }
        }
    }
    if spec.prefault_stack > 0 {
        match prefault_stack(spec.prefault_stack) {
            Ok(()) => got.stack_prefaulted = true,
            Err(e) => report::refused(Guarantee::Stack, &spec.name, &e, "first deep calls may fault"),
        }
    }
    got
}

/// Spawns a named thread that applies `spec` to itself (see [`apply_rt`]) and then runs `f`.
/// Fails only when the thread cannot be created at all.
pub fn spawn_rt<F, T>(spec: RtSpec, f: F) -> io::Result<JoinHandle<T>>
where
    F: FnOnce() -> T + Send + 'static,
    T: Send + 'static,
{
    std::thread::Builder::new()
        .name(spec.name.clone())
        .stack_size(RT_STACK_SIZE)
        .spawn(move || {
            apply_rt(&spec);
            f()
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn invalid_core_and_priority_are_errors() {
        assert!(matches!(
            pin_current_thread(1 << 20),
            Err(RtError::NoSuchCore { .. })
        ));
        // A core below CPU_SETSIZE that this machine does not have: the kernel says EINVAL.
        let e = pin_current_thread(sys::CPU_SETSIZE - 1).unwrap_err();
        assert!(e.to_string().contains("EINVAL"), "{e}");
        assert!(matches!(
            set_current_thread_fifo(1000),
            Err(RtError::PriorityRange { .. })
        ));
    }

    #[test]
    fn prefault_refuses_more_than_the_stack() {
        let e = prefault_stack(1 << 40).unwrap_err();
        assert!(matches!(e, RtError::StackTooSmall { .. }), "{e}");
    }

    #[test]
    fn spawn_rt_falls_back_and_reports_once() {
        let spec = RtSpec {
            core: Some(sys::CPU_SETSIZE - 1),
            fifo_priority: Some(1000),
            prefault_stack: 64 * 1024,
            ..RtSpec::new("rt-test-refused")
        };
        let a = spawn_rt(spec.clone(), || 1 + 1).unwrap().join().unwrap();
        let b = spawn_rt(spec, || 3).unwrap().join().unwrap();
        assert_eq!((a, b), (2, 3));
        let report = rt_report();
        let affinity: Vec<_> = report.iter().filter(|l| l.contains("pinning")).collect();
        let fifo: Vec<_> = report.iter().filter(|l| l.contains("SCHED_FIFO")).collect();
        assert_eq!(affinity.len(), 1, "{report:?}");
        assert_eq!(fifo.len(), 1, "{report:?}");
        assert!(fifo[0].starts_with("realtime: SCHED_FIFO"), "{}", fifo[0]);
        assert!(fifo[0].ends_with("running with normal priority"), "{}", fifo[0]);
    }

    #[test]
    fn spawn_rt_applies_what_the_os_allows() {
        // Core 0 always exists; FIFO may or may not be allowed (root here, maybe not in CI).
        let spec = RtSpec {
            core: Some(0),
            fifo_priority: Some(1),
            prefault_stack: 256 * 1024,
            ..RtSpec::new("rt-test-ok")
        };
        let fifo_now = spawn_rt(spec, current_thread_is_fifo).unwrap().join().unwrap();
        // Whatever happened, the report and the thread agree.
        if !fifo_now {
            assert!(rt_report().iter().any(|l| l.contains("SCHED_FIFO")));
        }
    }

    #[test]
    fn errno_display_names_the_error() {
        assert!(Errno(libc::EPERM).to_string().starts_with("EPERM: "));
    }
}
