//! The step trace's file, written by a thread of its own: the event loop fills a buffer and
//! hands each full one over, so it never waits on the disk.
//!
//! A `write` into the page cache is usually a few µs, but on a machine that has just written a
//! lot (a CI run right after a build) the kernel throttles writers while it flushes dirty pages,
//! and a 64 KiB write can block for tens of ms. Done on the event loop that meant steps run
//! late and, during a multi-MCU homing, `trsync_state` reports missing the 25 ms budget: a
//! `Communication timeout during homing` caused by the trace, at the same record count every
//! run. Here the event loop only copies into [`CHUNK`]-sized buffers and sends them through a
//! channel (reusing buffers the writer sends back; a new one is allocated only while the disk
//! is behind); the writer thread does the blocking writes.
//!
//! [`TraceFile::close`] hands over the rest, waits for the writer and reports its first error;
//! dropping a `TraceFile` does the same, ignoring errors.

use std::fs::File;
use std::io::{self, Write};
use std::path::Path;
use std::sync::mpsc::{self, Receiver, Sender};
use std::thread::JoinHandle;

/// Bytes collected before a buffer is handed to the writer.
pub const CHUNK: usize = 1 << 16;

/// A file whose writes are done by a background thread.
#[derive(Debug)]
pub struct TraceFile {
    buf: Vec<u8>,
    full: Option<Sender<Vec<u8>>>,
    spare: Receiver<Vec<u8>>,
    writer: Option<JoinHandle<io::Result<()>>>,
}

impl TraceFile {
    /// Creates (truncates) `path` and starts its writer thread.
    pub fn create(path: &Path) -> io::Result<TraceFile> {
        let file = File::create(path)?;
        TraceFile::over(file)
    }

    /// Writes to `out` from a background thread.
    pub fn over<W: Write + Send + 'static>(mut out: W) -> io::Result<TraceFile> {
        let (full, full_rx) = mpsc::channel::<Vec<u8>>();
        let (spare_tx, spare) = mpsc::channel::<Vec<u8>>();
        let writer = std::thread::Builder::new()
            .name("trace-writer".into())
            .spawn(move || {
                for mut buf in full_rx {
                    out.write_all(&buf)?;
                    buf.clear();
                    // The event loop may have finished: then the buffer is simply dropped.
                    let _ = spare_tx.send(buf);
                }
                out.flush()
            })?;
        Ok(TraceFile {
            buf: Vec::with_capacity(CHUNK),
            full: Some(full),
            spare,
            writer: Some(writer),
        })
    }

    /// Hands the buffered bytes to the writer (never blocks on the disk).
    fn hand_over(&mut self) -> io::Result<()> {
        if self.buf.is_empty() {
            return Ok(());
        }
        let next = self
            .spare
            .try_recv()
            .unwrap_or_else(|_| Vec::with_capacity(CHUNK));
        let buf = std::mem::replace(&mut self.buf, next);
        let sent = self.full.as_ref().map(|tx| tx.send(buf).is_ok()).unwrap_or(false);
        if sent {
            Ok(())
        } else {
            // The writer stopped: on an error, which `join` returns.
            Err(self
                .join()
                .err()
                .unwrap_or_else(|| io::Error::other("trace writer stopped")))
        }
    }

    /// Closes the channel and waits for the writer; its first error, if any.
    fn join(&mut self) -> io::Result<()> {
        self.full = None;
        match self.writer.take() {
            Some(h) => h
                .join()
                .unwrap_or_else(|_| Err(io::Error::other("trace writer panicked"))),
            None => Ok(()),
        }
    }

    /// Writes out everything, waits for the writer, and reports its first error.
    pub fn close(mut self) -> io::Result<()> {
        let handed = self.hand_over();
        let joined = self.join();
        handed.and(joined)
    }
}

impl Write for TraceFile {
    fn write(&mut self, data: &[u8]) -> io::Result<usize> {
        self.buf.extend_from_slice(data);
        if self.buf.len() >= CHUNK {
            self.hand_over()?;
        }
        Ok(data.len())
    }

    /// Hands the buffered bytes to the writer without waiting for them to reach the file
    /// ([`TraceFile::close`] waits).
    fn flush(&mut self) -> io::Result<()> {
        self.hand_over()
    }
}

impl Drop for TraceFile {
    fn drop(&mut self) {
        let _ = self.hand_over();
        let _ = self.join();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::{Arc, Mutex};

    /// A writer that keeps what it got, optionally failing after `fail_after` bytes.
    #[derive(Clone)]
    struct Sink {
        got: Arc<Mutex<Vec<u8>>>,
        fail_after: Option<usize>,
    }

    impl Write for Sink {
        fn write(&mut self, data: &[u8]) -> io::Result<usize> {
            let mut got = self.got.lock().unwrap();
            if self.fail_after.is_some_and(|n| got.len() + data.len() > n) {
                return Err(io::Error::other("disk full"));
            }
            got.extend_from_slice(data);
            Ok(data.len())
        }
        fn flush(&mut self) -> io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn every_byte_arrives_in_order() {
        let sink = Sink {
            got: Arc::default(),
            fail_after: None,
        };
        let mut f = TraceFile::over(sink.clone()).unwrap();
        let mut want = Vec::new();
        for i in 0..50_000u32 {
            let rec = [i.to_le_bytes(), (i ^ 0xdead_beef).to_le_bytes()].concat();
            f.write_all(&rec).unwrap();
            want.extend_from_slice(&rec);
        }
        f.close().unwrap();
        assert_eq!(*sink.got.lock().unwrap(), want);
    }

    #[test]
    fn a_write_error_is_reported() {
        let sink = Sink {
            got: Arc::default(),
            fail_after: Some(CHUNK + 10),
        };
        let mut f = TraceFile::over(sink).unwrap();
        let mut failed = None;
        for _ in 0..10 {
            if let Err(e) = f.write_all(&[7u8; CHUNK]) {
                failed = Some(e);
                break;
            }
            // Give the writer time to hit the error before the next hand-over.
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        let err = match failed {
            Some(e) => e,
            None => f.close().unwrap_err(),
        };
        assert_eq!(err.to_string(), "disk full");
    }

    /// A writer stuck on its disk until the test lets it go: the event loop's writes return
    /// meanwhile (were they done on the caller's thread, the sink would wait out its 10 s and
    /// record that it was never released).
    struct Stuck {
        release: std::sync::mpsc::Receiver<()>,
        released: Arc<Mutex<Option<bool>>>,
    }

    impl Write for Stuck {
        fn write(&mut self, data: &[u8]) -> io::Result<usize> {
            let mut r = self.released.lock().unwrap();
            if r.is_none() {
                let ok = self
                    .release
                    .recv_timeout(std::time::Duration::from_secs(10))
                    .is_ok();
                *r = Some(ok);
            }
            Ok(data.len())
        }
        fn flush(&mut self) -> io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn writes_return_while_the_disk_is_stuck() {
        let (release_tx, release) = std::sync::mpsc::channel();
        let released = Arc::new(Mutex::new(None));
        let stuck = Stuck {
            release,
            released: released.clone(),
        };
        let mut f = TraceFile::over(stuck).unwrap();
        for _ in 0..8 {
            f.write_all(&[1u8; CHUNK]).unwrap();
        }
        release_tx.send(()).unwrap();
        f.close().unwrap();
        assert_eq!(*released.lock().unwrap(), Some(true));
    }

    #[test]
    fn a_file_on_disk_is_complete_after_close() {
        let dir = std::env::temp_dir().join(format!("cadence-trace-file-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("t.bin");
        let mut f = TraceFile::create(&path).unwrap();
        f.write_all(&vec![3u8; 3 * CHUNK + 5]).unwrap();
        f.close().unwrap();
        assert_eq!(std::fs::read(&path).unwrap().len(), 3 * CHUNK + 5);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
