//! Waking a link's IO thread out of its read wait.
//!
//! The IO thread spends most of its life blocked in [`Transport::read_wake`](super::Transport)
//! (a `ppoll` on the tty). Another thread that hands it work — a homing trigger relayed from
//! another MCU, an urgent `trsync_set_timeout`, a step command — calls [`Wake::wake`], which
//! writes to an `eventfd` the same `ppoll` watches, so the IO thread sends within microseconds
//! instead of at the end of its read slice.
//!
//! Cost: the IO thread marks itself [`Wake::sleeping`] just before it blocks; `wake` only makes
//! the system call when that flag is set, so a burst of hand-offs costs one write. Ordering:
//! the IO thread sets the flag (SeqCst), then re-checks its queues before blocking; a waker
//! pushes to a queue, then swaps the flag (SeqCst). Either the IO thread sees the pushed item,
//! or the waker sees the flag and writes the eventfd, which ends the `ppoll`.

use std::io;
use std::os::fd::{AsFd, BorrowedFd};
use std::sync::atomic::{AtomicBool, Ordering};

use nix::sys::eventfd::{EfdFlags, EventFd};

/// An eventfd-backed wake-up for one IO thread.
#[derive(Debug)]
pub struct Wake {
    fd: EventFd,
    sleeping: AtomicBool,
}

impl Wake {
    /// A non-blocking, close-on-exec eventfd.
    pub fn new() -> io::Result<Wake> {
        let fd = EventFd::from_value_and_flags(0, EfdFlags::EFD_NONBLOCK | EfdFlags::EFD_CLOEXEC)?;
        Ok(Wake {
            fd,
            sleeping: AtomicBool::new(false),
        })
    }

    /// Ends the owner's current or next wait if it is (about to be) blocked.
    pub fn wake(&self) {
        if self.sleeping.swap(false, Ordering::SeqCst) {
            // EAGAIN (counter saturated) still leaves the fd readable: nothing to do.
            let _ = self.fd.write(1);
        }
    }

    /// Called by the owner just before it blocks; it must re-check its queues afterwards.
    pub fn sleeping(&self) {
        self.sleeping.store(true, Ordering::SeqCst);
    }

    /// Called by the owner after its wait, whatever ended it.
    pub fn awake(&self) {
        self.sleeping.store(false, Ordering::SeqCst);
    }

    /// Empties the eventfd after `ppoll` reported it readable.
    pub fn drain(&self) {
        let _ = self.fd.read();
    }

    /// The descriptor to poll for readability.
    pub fn fd(&self) -> BorrowedFd<'_> {
        self.fd.as_fd()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nix::poll::{poll, PollFd, PollFlags, PollTimeout};

    fn readable(w: &Wake) -> bool {
        let mut fds = [PollFd::new(w.fd(), PollFlags::POLLIN)];
        poll(&mut fds, PollTimeout::ZERO).unwrap() > 0
    }

    #[test]
    fn wakes_only_a_sleeper_and_drains() {
        let w = Wake::new().unwrap();
        w.wake();
        assert!(!readable(&w), "not sleeping: no system call, nothing to read");
        w.sleeping();
        w.wake();
        assert!(readable(&w));
        w.wake();
        w.drain();
        assert!(!readable(&w));
        w.awake();
    }

    #[test]
    fn wake_from_another_thread_ends_a_poll() {
        let w = std::sync::Arc::new(Wake::new().unwrap());
        w.sleeping();
        let w2 = w.clone();
        let t = std::thread::spawn(move || w2.wake());
        let mut fds = [PollFd::new(w.fd(), PollFlags::POLLIN)];
        // Bounded so that a broken wake fails instead of hanging; no timing asserted.
        let n = poll(&mut fds, PollTimeout::from(10_000u16)).unwrap();
        t.join().unwrap();
        assert_eq!(n, 1);
    }
}
