//! The byte pipe between the host and one MCU, and its implementations.
//!
//! [`Transport`] is all the IO thread needs: a read that waits at most a given time, a write of
//! a whole buffer, and a name for messages. Contract (checked for every implementation by one
//! conformance test below):
//! - `read` returns `Ok(n > 0)` with data, `Ok(0)` when the timeout passed with no data, and
//!   `Err` of kind `UnexpectedEof` or `BrokenPipe` once the peer is gone;
//! - `write_all` writes every byte or fails; it never blocks for longer than about a second;
//! - bytes are passed through unchanged (raw mode: no line discipline, no flow control chars).

mod faulty;
mod memory;
pub(crate) mod pty;
mod serial;
mod wake;

pub use faulty::{FaultConfig, FaultStats, FaultyTransport, XorShift64};
pub use memory::{MemoryEnd, MemoryPair};
pub use pty::PtyTransport;
pub use serial::SerialTransport;
pub use wake::Wake;

use std::io;
use std::time::Duration;

/// A byte pipe to an MCU.
pub trait Transport: Send {
    /// Reads what is available, waiting at most `timeout` for the first byte.
    /// `Ok(0)` = timed out with no data; `Err(UnexpectedEof | BrokenPipe)` = peer gone.
    fn read(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize>;
    /// Writes all of `data`.
    fn write_all(&mut self, data: &[u8]) -> io::Result<()>;
    /// A short description for messages, e.g. `pty /dev/pts/3`.
    fn describe(&self) -> String;
    /// Like [`read`](Transport::read), but also returns `Ok(0)` as soon as `wake` is woken
    /// (see [`Wake`]). Transports without a pollable descriptor ignore `wake` (the default):
    /// callers that need prompt wake-ups then read in short slices ([`supports_wake`]).
    ///
    /// [`supports_wake`]: Transport::supports_wake
    fn read_wake(&mut self, buf: &mut [u8], timeout: Duration, wake: &Wake) -> io::Result<usize> {
        let _ = wake;
        self.read(buf, timeout)
    }
    /// True when [`read_wake`](Transport::read_wake) really watches the wake descriptor.
    fn supports_wake(&self) -> bool {
        false
    }
}

impl<T: Transport + ?Sized> Transport for Box<T> {
    fn read(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        (**self).read(buf, timeout)
    }
    fn write_all(&mut self, data: &[u8]) -> io::Result<()> {
        (**self).write_all(data)
    }
    fn describe(&self) -> String {
        (**self).describe()
    }
    fn read_wake(&mut self, buf: &mut [u8], timeout: Duration, wake: &Wake) -> io::Result<usize> {
        (**self).read_wake(buf, timeout, wake)
    }
    fn supports_wake(&self) -> bool {
        (**self).supports_wake()
    }
}

/// True for the error kinds that mean the peer has gone away.
pub fn is_peer_gone(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::UnexpectedEof | io::ErrorKind::BrokenPipe | io::ErrorKind::ConnectionReset
    )
}

#[cfg(test)]
pub(crate) mod conformance {
    //! The one test suite every transport must pass.
    use super::*;

    /// Upper bound on read attempts while waiting for data (each waits at most 10 ms), so a
    /// broken transport fails the test instead of hanging it; no timing is asserted.
    const MAX_TRIES: usize = 3000;

    fn read_exact(t: &mut dyn Transport, n: usize) -> Vec<u8> {
        let mut out = Vec::new();
        let mut buf = [0u8; 512];
        for _ in 0..MAX_TRIES {
            if out.len() >= n {
                break;
            }
            let got = t.read(&mut buf, Duration::from_millis(10)).expect("read failed");
            out.extend_from_slice(&buf[..got]);
        }
        assert_eq!(out.len(), n, "{}: short read", t.describe());
        out
    }

    /// Runs the suite on a connected pair `a` ↔ `b`; consumes both (it tests hang-up).
    pub(crate) fn run(mut a: Box<dyn Transport>, mut b: Box<dyn Transport>) {
        assert!(!a.describe().is_empty());
        let mut buf = [0u8; 64];
        // Nothing sent: a timed-out read returns Ok(0).
        assert_eq!(b.read(&mut buf, Duration::from_millis(5)).unwrap(), 0);
        assert_eq!(b.read(&mut buf, Duration::ZERO).unwrap(), 0);
        // Small message, both directions.
        a.write_all(b"hello").unwrap();
        assert_eq!(read_exact(&mut *b, 5), b"hello");
        // Every byte value passes through unchanged (raw mode), the other way.
        let all: Vec<u8> = (0..=255u8).collect();
        b.write_all(&all).unwrap();
        assert_eq!(read_exact(&mut *a, 256), all);
        // A write larger than a pty's buffer while the peer reads concurrently.
        let big: Vec<u8> = (0..20_000u32).map(|i| (i * 7 + i / 256) as u8).collect();
        let sent = big.clone();
        let writer = std::thread::spawn(move || {
            a.write_all(&sent).unwrap();
            a
        });
        assert_eq!(read_exact(&mut *b, big.len()), big);
        let a = writer.join().unwrap();
        // Hang-up: once one end is dropped, the other reports the peer gone.
        drop(a);
        let mut gone = None;
        for _ in 0..MAX_TRIES {
            match b.read(&mut buf, Duration::from_millis(10)) {
                Ok(_) => continue,
                Err(e) => {
                    gone = Some(e);
                    break;
                }
            }
        }
        let e = gone.expect("no hang-up reported");
        assert!(is_peer_gone(&e), "{}: hang-up reported as {e:?}", b.describe());
    }
}
