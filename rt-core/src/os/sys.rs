//! The only place that calls libc for the thread runtime: CPU affinity, SCHED_FIFO, mlockall and
//! the stack size query. Every function is a thin, checked wrapper that turns the C return
//! convention (-1 + errno, or an error number) into an [`Errno`].
#![allow(unsafe_code)]

use super::Errno;

/// Largest CPU index a `cpu_set_t` can hold (glibc's CPU_SETSIZE).
pub(crate) const CPU_SETSIZE: usize = libc::CPU_SETSIZE as usize;

fn last_errno() -> Errno {
    Errno(std::io::Error::last_os_error().raw_os_error().unwrap_or(0))
}

/// `sched_setaffinity(0, {core})` for the calling thread. `core < CPU_SETSIZE` is checked by
/// the caller.
pub(crate) fn set_affinity(core: usize) -> Result<(), Errno> {
    debug_assert!(core < CPU_SETSIZE);
    // SAFETY: cpu_set_t is a plain bit array; all-zero is the valid empty set.
    let mut set: libc::cpu_set_t = unsafe { std::mem::zeroed() };
    // SAFETY: `core < CPU_SETSIZE` (checked by the caller), so the bit is inside `set`.
    unsafe { libc::CPU_SET(core, &mut set) };
    // SAFETY: pid 0 is the calling thread; the pointer and size describe `set`, alive for the call.
    let rc = unsafe { libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set) };
    if rc == 0 {
        Ok(())
    } else {
        Err(last_errno())
    }
}

/// Valid SCHED_FIFO priorities (1..=99 on Linux).
pub(crate) fn fifo_priority_range() -> (i32, i32) {
    // SAFETY: pure queries without pointers.
    unsafe {
        (
            libc::sched_get_priority_min(libc::SCHED_FIFO),
            libc::sched_get_priority_max(libc::SCHED_FIFO),
        )
    }
}

/// `pthread_setschedparam(self, SCHED_FIFO, priority)`.
pub(crate) fn set_fifo(priority: i32) -> Result<(), Errno> {
    let param = libc::sched_param {
        sched_priority: priority,
    };
    // SAFETY: pthread_self() is always valid for the calling thread; `param` lives for the call.
    let rc = unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_FIFO, &param) };
    if rc == 0 {
        Ok(())
    } else {
        Err(Errno(rc))
    }
}

/// `pthread_setschedparam(self, SCHED_IDLE, 0)`: the thread runs only when nothing else of
/// any other policy wants the CPU (lowering a policy needs no privilege).
pub(crate) fn set_idle_policy() -> Result<(), Errno> {
    let param = libc::sched_param { sched_priority: 0 };
    // SAFETY: pthread_self() is always valid for the calling thread; `param` lives for the call.
    let rc = unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_IDLE, &param) };
    if rc == 0 {
        Ok(())
    } else {
        Err(Errno(rc))
    }
}

/// CPUs online (`sysconf(_SC_NPROCESSORS_ONLN)`, at least 1): unlike the affinity mask it
/// does not shrink when the calling thread is pinned.
pub(crate) fn online_cpus() -> usize {
    // SAFETY: a pure query without pointers.
    let n = unsafe { libc::sysconf(libc::_SC_NPROCESSORS_ONLN) };
    usize::try_from(n).unwrap_or(1).max(1)
}

/// The calling thread's kernel thread id.
pub(crate) fn gettid() -> i32 {
    // SAFETY: no arguments; always succeeds.
    unsafe { libc::gettid() }
}

/// The calling thread's scheduling policy (SCHED_OTHER = 0, SCHED_FIFO = 1, ...).
pub(crate) fn current_policy() -> Result<i32, Errno> {
    let mut policy = 0;
    let mut param = libc::sched_param { sched_priority: 0 };
    // SAFETY: both out-pointers refer to live locals.
    let rc = unsafe { libc::pthread_getschedparam(libc::pthread_self(), &mut policy, &mut param) };
    if rc == 0 {
        Ok(policy)
    } else {
        Err(Errno(rc))
    }
}

/// `mlockall(MCL_CURRENT | MCL_FUTURE)`.
pub(crate) fn mlockall() -> Result<(), Errno> {
    // SAFETY: no pointers; affects only this process's paging.
    let rc = unsafe { libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE) };
    if rc == 0 {
        Ok(())
    } else {
        Err(last_errno())
    }
}

/// Stack size of the calling thread in bytes (`pthread_getattr_np`).
pub(crate) fn current_stack_size() -> Result<usize, Errno> {
    // SAFETY: pthread_attr_t is initialised by pthread_getattr_np before any read; zeroed is a
    // valid starting state for the out-parameter.
    let mut attr: libc::pthread_attr_t = unsafe { std::mem::zeroed() };
    // SAFETY: `attr` is a live out-parameter for the calling thread's attributes.
    let rc = unsafe { libc::pthread_getattr_np(libc::pthread_self(), &mut attr) };
    if rc != 0 {
        return Err(Errno(rc));
    }
    let mut size = 0usize;
    // SAFETY: `attr` was initialised above; `size` is a live out-parameter.
    let rc = unsafe { libc::pthread_attr_getstacksize(&attr, &mut size) };
    // SAFETY: `attr` was initialised by pthread_getattr_np and is destroyed exactly once.
    unsafe { libc::pthread_attr_destroy(&mut attr) };
    if rc == 0 {
        Ok(size)
    } else {
        Err(Errno(rc))
    }
}
