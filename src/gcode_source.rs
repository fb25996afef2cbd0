//! The G-code file as `cadence print` feeds it to the planner: counts the bytes and lines read
//! (for the progress display and the "interrupted at line N" note) and the layers begun (the
//! slicers' layer comments at a line start: `;LAYER_CHANGE` from PrusaSlicer, SuperSlicer and
//! OrcaSlicer, `;LAYER:N` from Cura), skips a UTF-8 byte-order
//! mark at the start, and ends at the next line boundary once a stop was asked for: one more
//! line, `M84` (motors off: the axes are no longer homed), then the end of the input, so the
//! planner finishes as at the end of a file (what it already planned still moves).

use std::fs::File;
use std::io::{BufRead, BufReader, Read};
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicI32, AtomicU64, Ordering};
use std::sync::Arc;

use nix::sys::signal::Signal;

/// The signal that asked the print to stop (0: none yet), shared between whoever takes the
/// signals and the G-code reader.
#[derive(Debug, Clone, Default)]
pub struct StopRequest(Arc<AtomicI32>);

impl StopRequest {
    /// The signal received, if any.
    pub fn signal(&self) -> Option<Signal> {
        match self.0.load(Ordering::Acquire) {
            0 => None,
            n => Signal::try_from(n).ok(),
        }
    }

    /// True once a stop was asked for.
    pub fn is_set(&self) -> bool {
        self.0.load(Ordering::Acquire) != 0
    }

    /// Asks for a stop because of `sig`.
    pub fn set(&self, sig: Signal) {
        self.0.store(sig as i32, Ordering::Release);
    }
}

const BOM: &[u8] = b"\xEF\xBB\xBF";
/// The line fed after a stop.
const AFTER_STOP: &[u8] = b"M84\n";

/// How far the planner has read (shared with the progress display).
#[derive(Debug, Default)]
pub struct ReadPosition {
    pub bytes: AtomicU64,
    pub lines: AtomicU64,
    /// Slicer layer comments read (`;LAYER_CHANGE`, `;LAYER:N`).
    pub layers: AtomicU64,
    /// The reader ended early because of a stop request.
    pub cut: AtomicBool,
}

/// A buffered file reader that counts, skips a BOM and stops at a line boundary on request.
#[derive(Debug)]
pub struct GcodeSource {
    inner: BufReader<File>,
    pos: Arc<ReadPosition>,
    stop: StopRequest,
    /// The last byte handed out ended a line (or nothing was handed out yet).
    at_line_start: bool,
    started: bool,
    /// Bytes of [`AFTER_STOP`] handed out.
    tail: usize,
    /// The start of the line being read, up to the longest layer comment.
    prefix: [u8; LAYER_CHANGE.len()],
    prefix_len: usize,
}

/// PrusaSlicer's, SuperSlicer's and OrcaSlicer's layer comment.
const LAYER_CHANGE: &[u8] = b";LAYER_CHANGE";
/// Cura's (followed by the layer's number).
const CURA_LAYER: &[u8] = b";LAYER:";

impl GcodeSource {
    /// Opens `path`.
    pub fn open(path: &Path, stop: StopRequest) -> std::io::Result<(GcodeSource, Arc<ReadPosition>)> {
        let pos = Arc::new(ReadPosition::default());
        let src = GcodeSource {
            inner: BufReader::with_capacity(1 << 16, File::open(path)?),
            pos: Arc::clone(&pos),
            stop,
            at_line_start: true,
            started: false,
            tail: 0,
            prefix: [0; LAYER_CHANGE.len()],
            prefix_len: 0,
        };
        Ok((src, pos))
    }
}

impl Read for GcodeSource {
    fn read(&mut self, out: &mut [u8]) -> std::io::Result<usize> {
        let n = {
            let buf = self.fill_buf()?;
            let n = buf.len().min(out.len());
            out[..n].copy_from_slice(&buf[..n]);
            n
        };
        self.consume(n);
        Ok(n)
    }
}

impl BufRead for GcodeSource {
    fn fill_buf(&mut self) -> std::io::Result<&[u8]> {
        if !self.started {
            self.started = true;
            let buf = self.inner.fill_buf()?;
            if buf.starts_with(BOM) {
                self.inner.consume(BOM.len());
                self.pos.bytes.fetch_add(BOM.len() as u64, Ordering::Relaxed);
            }
        }
        if self.stop.is_set() {
            if self.at_line_start {
                self.pos.cut.store(true, Ordering::Release);
                return Ok(&AFTER_STOP[self.tail..]);
            }
            // Finish the line being read, nothing more.
            let buf = self.inner.fill_buf()?;
            let end = buf.iter().position(|&b| b == b'\n').map_or(buf.len(), |i| i + 1);
            return Ok(&buf[..end]);
        }
        self.inner.fill_buf()
    }

    fn consume(&mut self, n: usize) {
        if n == 0 {
            return;
        }
        if self.pos.cut.load(Ordering::Relaxed) {
            self.tail = (self.tail + n).min(AFTER_STOP.len());
            return;
        }
        if let Ok(buf) = self.inner.fill_buf() {
            let taken = &buf[..n.min(buf.len())];
            let mut newlines = 0;
            let mut layers = 0;
            for &b in taken {
                if b == b'\n' {
                    newlines += 1;
                    self.prefix_len = 0;
                    continue;
                }
                if let Some(slot) = self.prefix.get_mut(self.prefix_len) {
                    *slot = b;
                    self.prefix_len += 1;
                    let start = &self.prefix[..self.prefix_len];
                    if start == LAYER_CHANGE || start == CURA_LAYER {
                        layers += 1;
                    }
                }
            }
            self.at_line_start = taken.last() == Some(&b'\n');
            self.pos.lines.fetch_add(newlines, Ordering::Relaxed);
            self.pos.layers.fetch_add(layers, Ordering::Relaxed);
        }
        self.inner.consume(n);
        self.pos.bytes.fetch_add(n as u64, Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    fn source(text: &[u8]) -> (GcodeSource, Arc<ReadPosition>, StopRequest, tempfile_path::Tmp) {
        let tmp = tempfile_path::Tmp::new(text);
        let stop = StopRequest::default();
        let (src, pos) = GcodeSource::open(&tmp.0, stop.clone()).unwrap();
        (src, pos, stop, tmp)
    }

    /// A file in the temp dir, removed on drop.
    mod tempfile_path {
        pub struct Tmp(pub std::path::PathBuf);
        impl Tmp {
            pub fn new(text: &[u8]) -> Tmp {
                static N: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
                let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let p = std::env::temp_dir().join(format!("cadence-src-{}-{n}.gcode", std::process::id()));
                let mut f = std::fs::File::create(&p).unwrap();
                super::Write::write_all(&mut f, text).unwrap();
                Tmp(p)
            }
        }
        impl Drop for Tmp {
            fn drop(&mut self) {
                let _ = std::fs::remove_file(&self.0);
            }
        }
    }

    #[test]
    fn skips_a_bom_and_counts() {
        let (src, pos, _stop, _t) = source(b"\xEF\xBB\xBFG28\nG1 X1\n");
        let lines: Vec<String> = src.lines().map(Result::unwrap).collect();
        assert_eq!(lines, ["G28", "G1 X1"]);
        assert_eq!(pos.lines.load(Ordering::Relaxed), 2);
        assert_eq!(pos.bytes.load(Ordering::Relaxed), 3 + 10);
    }

    #[test]
    fn counts_the_slicers_layer_comments_across_reads() {
        let text = b";LAYER_COUNT:3\n;LAYER:0\nG1 Z.2\n;LAYER_CHANGE\n;Z:0.4\n G1 ;LAYER:9\n;LAYER:1\n";
        let (mut src, pos, _stop, _t) = source(text);
        // Byte by byte: every comment split across reads.
        let mut one = [0u8; 1];
        while src.read(&mut one).unwrap() == 1 {}
        assert_eq!(pos.layers.load(Ordering::Relaxed), 3);
        assert_eq!(pos.lines.load(Ordering::Relaxed), 7);
    }

    #[test]
    fn a_stop_ends_at_the_next_line_boundary() {
        let (mut src, pos, stop, _t) = source(b"G1 X1\nG1 X2 Y3\nG1 X4\n");
        let mut line = String::new();
        src.read_line(&mut line).unwrap();
        assert_eq!(line, "G1 X1\n");
        // Half a line taken, then the stop: the line is finished, nothing after it.
        let mut half = [0u8; 4];
        src.read_exact(&mut half).unwrap();
        stop.set(Signal::SIGINT);
        let mut rest = String::new();
        src.read_to_string(&mut rest).unwrap();
        assert_eq!(rest, "2 Y3\nM84\n");
        assert_eq!(pos.lines.load(Ordering::Relaxed), 2);
        assert!(pos.cut.load(Ordering::Relaxed));
    }

    use nix::sys::signal::Signal;
}
