//! An in-memory transport pair for tests: two byte pipes under mutexes, with condition
//! variables for the bounded read wait. Dropping one end closes both directions: the other end
//! reads what is left, then gets `UnexpectedEof`; its writes fail with `BrokenPipe`.

use std::collections::VecDeque;
use std::io;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use super::Transport;

#[derive(Debug, Default)]
struct PipeState {
    data: VecDeque<u8>,
    closed: bool,
}

#[derive(Debug, Default)]
struct Pipe {
    state: Mutex<PipeState>,
    ready: Condvar,
}

impl Pipe {
    fn lock(&self) -> MutexGuard<'_, PipeState> {
        // A panicking peer thread must not take this end down with it.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn close(&self) {
        self.lock().closed = true;
        self.ready.notify_all();
    }
}

/// Constructor of connected [`MemoryEnd`] pairs.
#[derive(Debug)]
pub struct MemoryPair;

impl MemoryPair {
    /// Two connected ends: bytes written to one are read from the other.
    #[allow(clippy::new_ret_no_self)]
    pub fn new() -> (MemoryEnd, MemoryEnd) {
        let (ab, ba) = (Arc::new(Pipe::default()), Arc::new(Pipe::default()));
        (
            MemoryEnd {
                rx: ba.clone(),
                tx: ab.clone(),
                name: "memory a",
            },
            MemoryEnd {
                rx: ab,
                tx: ba,
                name: "memory b",
            },
        )
    }
}

/// One end of a [`MemoryPair`].
#[derive(Debug)]
pub struct MemoryEnd {
    rx: Arc<Pipe>,
    tx: Arc<Pipe>,
    name: &'static str,
}

impl Drop for MemoryEnd {
    fn drop(&mut self) {
        self.rx.close();
        self.tx.close();
    }
}

impl Transport for MemoryEnd {
    fn read(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        let deadline = Instant::now() + timeout;
        let mut st = self.rx.lock();
        loop {
            if !st.data.is_empty() {
                let n = buf.len().min(st.data.len());
                for (dst, src) in buf.iter_mut().zip(st.data.drain(..n)) {
                    *dst = src;
                }
                return Ok(n);
            }
            if st.closed {
                return Err(io::Error::new(io::ErrorKind::UnexpectedEof, "memory peer closed"));
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(0);
            }
            st = self
                .rx
                .ready
                .wait_timeout(st, deadline - now)
                .map(|(g, _)| g)
                .unwrap_or_else(|e| e.into_inner().0);
        }
    }

    fn write_all(&mut self, data: &[u8]) -> io::Result<()> {
        let mut st = self.tx.lock();
        if st.closed {
            return Err(io::Error::new(io::ErrorKind::BrokenPipe, "memory peer closed"));
        }
        st.data.extend(data);
        drop(st);
        self.tx.ready.notify_all();
        Ok(())
    }

    fn describe(&self) -> String {
        self.name.to_owned()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transport::conformance;

    #[test]
    fn conformance_memory_pair() {
        let (a, b) = MemoryPair::new();
        conformance::run(Box::new(a), Box::new(b));
    }

    #[test]
    fn write_after_peer_dropped_fails() {
        let (mut a, b) = MemoryPair::new();
        drop(b);
        assert_eq!(a.write_all(b"x").unwrap_err().kind(), io::ErrorKind::BrokenPipe);
    }
}
