//! Step trace files written by `cadence-mcu` and read back by tests and the host.
//!
//! Binary layout (little-endian):
//! - header, 24 bytes: magic `b"CDTRACE1"` (0..8), `clock_freq: u64` (8..16),
//!   `time_scale: f64` (16..24);
//! - records, 16 bytes each: `kind: u8` (0), `oid: u8` (1), `dir: u8` (2), pad (3),
//!   `aux: u32` (4..8), `clock: u64` (8..16).
//!
//! Kinds: 0 step (`clock` = scheduled 64-bit step clock, `aux` = lateness in µs of MCU time,
//! actual execution − scheduled, saturating); 1 `queue_step` received (`clock` = MCU clock at
//! receipt, `aux` = lead in µs = first step − receipt, 0 if already late); 2 shutdown
//! (`clock` = MCU clock, `aux` = `static_string_id`); 3 trigger (`clock` = trigger clock,
//! `oid` = the trsync or endstop, `dir` = 0 trsync triggered / 1 endstop confirmed, `aux` = the
//! trigger reason).
//!
//! Kind-3 records are read into [`TraceFile::triggers`] as [`TriggerRecord`]s, apart from
//! [`TraceFile::records`] (kinds 0–2), so code matching exhaustively on [`TraceRecord`] keeps
//! compiling; `triggers` keeps file order, and every record carries its clock.
//!
//! [`TraceRecord`] is the decoded view (an enum per kind); a `queue_step` record keeps the
//! first step as `first_step_clock`, rebuilt on reading from the µs lead and `clock_freq`.
//!
//! The CSV form carries the same fields: a `# CDTRACE1 clock_freq=… time_scale=…` line, a
//! `kind,oid,dir,aux,clock` header line, then one line per record. [`read_trace`] accepts both
//! (it looks at the magic). A binary file cut inside its last record (a killed writer) reads as
//! the complete records before the cut.

use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::Path;

/// First 8 bytes of a binary trace (and the tag of the CSV first line).
pub const MAGIC: &[u8; 8] = b"CDTRACE1";
/// Bytes of the binary header.
pub const HEADER_LEN: usize = 24;
/// Bytes of one binary record.
pub const RECORD_LEN: usize = 16;

/// The record kind byte of the file format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum TraceKind {
    /// A step was executed.
    Step = 0,
    /// A `queue_step` was received.
    QueueStep = 1,
    /// The MCU shut down.
    Shutdown = 2,
}

impl TraceKind {
    /// The kind with wire value `v`.
    pub fn from_u8(v: u8) -> Option<TraceKind> {
        Some(match v {
            0 => TraceKind::Step,
            1 => TraceKind::QueueStep,
            2 => TraceKind::Shutdown,
            _ => return None,
        })
    }
}

/// One trace event. All clocks are 64-bit MCU clocks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum TraceRecord {
    /// Stepper `oid` stepped in direction `dir` (true = +1) at its scheduled `clock`; it ran
    /// `lateness_us` µs of MCU time after that (saturating).
    Step {
        /// Stepper oid.
        oid: u8,
        /// Direction.
        dir: bool,
        /// Scheduled step clock.
        clock: u64,
        /// Execution time − scheduled time, µs of MCU time.
        lateness_us: u32,
    },
    /// A `queue_step` for `oid` arrived at `received_clock`; its first step is due at
    /// `first_step_clock`. The file stores the lead in whole µs, saturating at 0, so a file
    /// read back gives `first_step_clock` rounded down to a µs and, for a late `queue_step`,
    /// equal to `received_clock`.
    QueueStep {
        /// Stepper oid.
        oid: u8,
        /// MCU clock when the command was received.
        received_clock: u64,
        /// Clock of the move's first step.
        first_step_clock: u64,
    },
    /// The MCU shut down at `clock` for the reason with id `static_string_id`.
    Shutdown {
        /// MCU clock of the shutdown.
        clock: u64,
        /// The reason's id in the dictionary's `static_string_id` enumeration.
        static_string_id: u16,
    },
}

/// Kind byte of a trigger record.
pub const TRIGGER_KIND: u8 = 3;

/// A trigger (kind 3): trsync `oid` triggered (`endstop` false), or endstop `oid` confirmed its
/// trigger (`endstop` true), at `clock` with `reason`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct TriggerRecord {
    /// The trsync or endstop oid.
    pub oid: u8,
    /// True for an endstop, false for a trsync.
    pub endstop: bool,
    /// Trigger reason (1 endstop hit, 2 host request, 3 past end time, 4 communication timeout).
    pub reason: u8,
    /// The trigger clock (64-bit MCU clock).
    pub clock: u64,
}

impl TriggerRecord {
    /// The 16-byte binary form.
    pub fn to_bytes(&self) -> [u8; RECORD_LEN] {
        let mut b = [0u8; RECORD_LEN];
        b[0] = TRIGGER_KIND;
        b[1] = self.oid;
        b[2] = self.endstop as u8;
        b[4..8].copy_from_slice(&(self.reason as u32).to_le_bytes());
        b[8..16].copy_from_slice(&self.clock.to_le_bytes());
        b
    }

    fn from_fields(oid: u8, dir: u8, aux: u32, clock: u64) -> TriggerRecord {
        TriggerRecord {
            oid,
            endstop: dir != 0,
            reason: aux as u8,
            clock,
        }
    }
}

/// One line or binary record: a step-trace record or a trigger.
enum Entry {
    Record(TraceRecord),
    Trigger(TriggerRecord),
}

fn entry_from_bytes(b: &[u8; RECORD_LEN], clock_freq: u64) -> Option<Entry> {
    if b[0] == TRIGGER_KIND {
        let mut aux = [0u8; 4];
        aux.copy_from_slice(&b[4..8]);
        let mut clock = [0u8; 8];
        clock.copy_from_slice(&b[8..16]);
        let t = TriggerRecord::from_fields(b[1], b[2], u32::from_le_bytes(aux), u64::from_le_bytes(clock));
        return Some(Entry::Trigger(t));
    }
    TraceRecord::from_bytes(b, clock_freq).map(Entry::Record)
}

fn entry_from_csv(line: &str, clock_freq: u64) -> Option<Entry> {
    let kind: u8 = line.trim().split(',').next()?.trim().parse().ok()?;
    if kind != TRIGGER_KIND {
        return TraceRecord::parse_csv(line, clock_freq).map(Entry::Record);
    }
    let f: Vec<&str> = line.trim().split(',').map(str::trim).collect();
    let [_, oid, dir, aux, clock] = f.as_slice() else {
        return None;
    };
    Some(Entry::Trigger(TriggerRecord::from_fields(
        oid.parse().ok()?,
        dir.parse().ok()?,
        aux.parse().ok()?,
        clock.parse().ok()?,
    )))
}

/// The raw fields of one record: `(kind, oid, dir, aux, clock)`.
type Raw = (TraceKind, u8, u8, u32, u64);

impl TraceRecord {
    /// The record's kind byte.
    pub fn kind(&self) -> TraceKind {
        match self {
            TraceRecord::Step { .. } => TraceKind::Step,
            TraceRecord::QueueStep { .. } => TraceKind::QueueStep,
            TraceRecord::Shutdown { .. } => TraceKind::Shutdown,
        }
    }

    fn to_raw(self, clock_freq: u64) -> Raw {
        match self {
            TraceRecord::Step {
                oid,
                dir,
                clock,
                lateness_us,
            } => (TraceKind::Step, oid, dir as u8, lateness_us, clock),
            TraceRecord::QueueStep {
                oid,
                received_clock,
                first_step_clock,
            } => {
                let lead = first_step_clock.saturating_sub(received_clock);
                (
                    TraceKind::QueueStep,
                    oid,
                    0,
                    ticks_to_us(lead, clock_freq),
                    received_clock,
                )
            }
            TraceRecord::Shutdown {
                clock,
                static_string_id,
            } => (TraceKind::Shutdown, 0, 0, static_string_id as u32, clock),
        }
    }

    fn from_raw((kind, oid, dir, aux, clock): Raw, clock_freq: u64) -> TraceRecord {
        match kind {
            TraceKind::Step => TraceRecord::Step {
                oid,
                dir: dir != 0,
                clock,
                lateness_us: aux,
            },
            TraceKind::QueueStep => TraceRecord::QueueStep {
                oid,
                received_clock: clock,
                first_step_clock: clock.saturating_add(us_to_ticks(aux, clock_freq)),
            },
            TraceKind::Shutdown => TraceRecord::Shutdown {
                clock,
                static_string_id: aux as u16,
            },
        }
    }

    /// The 16-byte binary form (`clock_freq` converts a `queue_step` lead to µs).
    pub fn to_bytes(&self, clock_freq: u64) -> [u8; RECORD_LEN] {
        let (kind, oid, dir, aux, clock) = self.to_raw(clock_freq);
        let mut b = [0u8; RECORD_LEN];
        b[0] = kind as u8;
        b[1] = oid;
        b[2] = dir;
        b[4..8].copy_from_slice(&aux.to_le_bytes());
        b[8..16].copy_from_slice(&clock.to_le_bytes());
        b
    }

    /// Parses the 16-byte binary form (`None` for an unknown kind).
    pub fn from_bytes(b: &[u8; RECORD_LEN], clock_freq: u64) -> Option<TraceRecord> {
        let mut aux = [0u8; 4];
        aux.copy_from_slice(&b[4..8]);
        let mut clock = [0u8; 8];
        clock.copy_from_slice(&b[8..16]);
        let kind = TraceKind::from_u8(b[0])?;
        let raw = (
            kind,
            b[1],
            b[2],
            u32::from_le_bytes(aux),
            u64::from_le_bytes(clock),
        );
        Some(TraceRecord::from_raw(raw, clock_freq))
    }

    fn parse_csv(line: &str, clock_freq: u64) -> Option<TraceRecord> {
        let mut f = line.trim().split(',');
        let mut next = || f.next().map(str::trim);
        let raw = (
            TraceKind::from_u8(next()?.parse().ok()?)?,
            next()?.parse().ok()?,
            next()?.parse().ok()?,
            next()?.parse().ok()?,
            next()?.parse().ok()?,
        );
        next().is_none().then(|| TraceRecord::from_raw(raw, clock_freq))
    }
}

/// `ticks` of a `clock_freq` clock in whole µs (rounded down, saturating).
pub fn ticks_to_us(ticks: u64, clock_freq: u64) -> u32 {
    let us = ticks as u128 * 1_000_000 / clock_freq.max(1) as u128;
    u32::try_from(us).unwrap_or(u32::MAX)
}

/// `us` µs in ticks of a `clock_freq` clock (rounded down).
pub fn us_to_ticks(us: u32, clock_freq: u64) -> u64 {
    let t = us as u128 * clock_freq as u128 / 1_000_000;
    u64::try_from(t).unwrap_or(u64::MAX)
}

/// A whole trace.
#[derive(Debug, Clone, PartialEq)]
pub struct TraceFile {
    /// The MCU's `CLOCK_FREQ`.
    pub clock_freq: u64,
    /// MCU seconds per wall second.
    pub time_scale: f64,
    /// Records (kinds 0–2) in the order they happened.
    pub records: Vec<TraceRecord>,
    /// Trigger records (kind 3) in the order they happened.
    pub triggers: Vec<TriggerRecord>,
}

/// On-disk form of a trace.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TraceFormat {
    /// Fixed 16-byte records.
    Bin,
    /// Text lines.
    Csv,
}

/// Buffered trace writer.
#[derive(Debug)]
pub struct TraceWriter<W: Write> {
    out: W,
    format: TraceFormat,
    clock_freq: u64,
}

impl TraceWriter<BufWriter<File>> {
    /// Creates (truncates) `path` and writes the header.
    pub fn create(path: &Path, format: TraceFormat, clock_freq: u64, time_scale: f64) -> io::Result<Self> {
        let file = BufWriter::with_capacity(1 << 16, File::create(path)?);
        TraceWriter::new(file, format, clock_freq, time_scale)
    }
}

impl<W: Write> TraceWriter<W> {
    /// Writes the header to `out`.
    pub fn new(mut out: W, format: TraceFormat, clock_freq: u64, time_scale: f64) -> io::Result<Self> {
        match format {
            TraceFormat::Bin => {
                out.write_all(MAGIC)?;
                out.write_all(&clock_freq.to_le_bytes())?;
                out.write_all(&time_scale.to_le_bytes())?;
            }
            TraceFormat::Csv => {
                let magic = String::from_utf8_lossy(MAGIC);
                writeln!(out, "# {magic} clock_freq={clock_freq} time_scale={time_scale}")?;
                writeln!(out, "kind,oid,dir,aux,clock")?;
            }
        }
        Ok(TraceWriter {
            out,
            format,
            clock_freq,
        })
    }

    /// Appends one record.
    pub fn write(&mut self, r: &TraceRecord) -> io::Result<()> {
        match self.format {
            TraceFormat::Bin => self.out.write_all(&r.to_bytes(self.clock_freq)),
            TraceFormat::Csv => {
                let (kind, oid, dir, aux, clock) = r.to_raw(self.clock_freq);
                writeln!(self.out, "{},{oid},{dir},{aux},{clock}", kind as u8)
            }
        }
    }

    /// Appends one trigger record.
    pub fn write_trigger(&mut self, t: &TriggerRecord) -> io::Result<()> {
        match self.format {
            TraceFormat::Bin => self.out.write_all(&t.to_bytes()),
            TraceFormat::Csv => writeln!(
                self.out,
                "{TRIGGER_KIND},{},{},{},{}",
                t.oid, t.endstop as u8, t.reason, t.clock
            ),
        }
    }

    /// Flushes and returns the inner writer.
    pub fn finish(mut self) -> io::Result<W> {
        self.out.flush()?;
        Ok(self.out)
    }
}

fn invalid(msg: &str) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidData, msg.to_owned())
}

/// Reads a binary or CSV trace file.
pub fn read_trace(path: impl AsRef<Path>) -> io::Result<TraceFile> {
    parse_trace(&std::fs::read(path)?)
}

/// Reads a trace file record by record without holding it in memory (a whole print's binary
/// trace is 16 bytes per step: hundreds of MB): calls `f` with each record of kinds 0–2 in
/// file order (triggers are skipped) and returns the header's `(clock_freq, time_scale)`. A
/// binary file cut inside its last record reads as the complete records before the cut; a CSV
/// trace is read whole (it is only written for small runs).
pub fn for_each_record(path: impl AsRef<Path>, mut f: impl FnMut(&TraceRecord)) -> io::Result<(u64, f64)> {
    use std::io::Read;
    let mut file = io::BufReader::with_capacity(1 << 16, File::open(path.as_ref())?);
    let mut header = [0u8; HEADER_LEN];
    let mut got = 0;
    while got < HEADER_LEN {
        let n = file.read(&mut header[got..])?;
        if n == 0 {
            break;
        }
        got += n;
    }
    if got < MAGIC.len() || &header[..MAGIC.len()] != MAGIC {
        let t = read_trace(path)?;
        t.records.iter().for_each(&mut f);
        return Ok((t.clock_freq, t.time_scale));
    }
    if got < HEADER_LEN {
        return Err(invalid("trace header truncated"));
    }
    let mut word = [0u8; 8];
    word.copy_from_slice(&header[8..16]);
    let clock_freq = u64::from_le_bytes(word);
    word.copy_from_slice(&header[16..24]);
    let time_scale = f64::from_le_bytes(word);
    let mut b = [0u8; RECORD_LEN];
    loop {
        match file.read_exact(&mut b) {
            Ok(()) => {}
            Err(e) if e.kind() == io::ErrorKind::UnexpectedEof => break,
            Err(e) => return Err(e),
        }
        match entry_from_bytes(&b, clock_freq).ok_or_else(|| invalid("unknown trace record kind"))? {
            Entry::Record(r) => f(&r),
            Entry::Trigger(_) => {}
        }
    }
    Ok((clock_freq, time_scale))
}

/// Parses trace bytes (binary or CSV, told apart by the magic).
pub fn parse_trace(bytes: &[u8]) -> io::Result<TraceFile> {
    if bytes.starts_with(MAGIC) {
        parse_bin(bytes)
    } else {
        parse_csv(std::str::from_utf8(bytes).map_err(|_| invalid("trace is neither binary nor text"))?)
    }
}

fn parse_bin(bytes: &[u8]) -> io::Result<TraceFile> {
    let header = bytes
        .get(..HEADER_LEN)
        .ok_or_else(|| invalid("trace header truncated"))?;
    let mut freq = [0u8; 8];
    freq.copy_from_slice(&header[8..16]);
    let mut scale = [0u8; 8];
    scale.copy_from_slice(&header[16..24]);
    let clock_freq = u64::from_le_bytes(freq);
    let mut records = Vec::with_capacity((bytes.len() - HEADER_LEN) / RECORD_LEN);
    let mut triggers = Vec::new();
    for chunk in bytes[HEADER_LEN..].chunks_exact(RECORD_LEN) {
        let mut b = [0u8; RECORD_LEN];
        b.copy_from_slice(chunk);
        match entry_from_bytes(&b, clock_freq).ok_or_else(|| invalid("unknown trace record kind"))? {
            Entry::Record(r) => records.push(r),
            Entry::Trigger(t) => triggers.push(t),
        }
    }
    Ok(TraceFile {
        clock_freq,
        time_scale: f64::from_le_bytes(scale),
        records,
        triggers,
    })
}

fn parse_csv(text: &str) -> io::Result<TraceFile> {
    let mut lines = text.lines();
    let first = lines.next().ok_or_else(|| invalid("empty trace"))?;
    let tag = format!("# {}", String::from_utf8_lossy(MAGIC));
    let params = first
        .strip_prefix(&tag)
        .ok_or_else(|| invalid("not a cadence trace"))?;
    let (mut clock_freq, mut time_scale) = (None, None);
    for kv in params.split_whitespace() {
        match kv.split_once('=') {
            Some(("clock_freq", v)) => clock_freq = v.parse::<u64>().ok(),
            Some(("time_scale", v)) => time_scale = v.parse::<f64>().ok(),
            _ => {}
        }
    }
    let (Some(clock_freq), Some(time_scale)) = (clock_freq, time_scale) else {
        return Err(invalid("trace header lacks clock_freq or time_scale"));
    };
    let mut records = Vec::new();
    let mut triggers = Vec::new();
    for line in lines {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') || line.starts_with("kind") {
            continue;
        }
        match entry_from_csv(line, clock_freq).ok_or_else(|| invalid("bad trace line"))? {
            Entry::Record(r) => records.push(r),
            Entry::Trigger(t) => triggers.push(t),
        }
    }
    Ok(TraceFile {
        clock_freq,
        time_scale,
        records,
        triggers,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const FREQ: u64 = 50_000_000;

    /// Records that survive the µs resolution of the file exactly at 50 MHz.
    fn record() -> impl Strategy<Value = TraceRecord> {
        prop_oneof![
            (any::<u8>(), any::<bool>(), any::<u64>(), any::<u32>()).prop_map(
                |(oid, dir, clock, lateness_us)| {
                    TraceRecord::Step {
                        oid,
                        dir,
                        clock,
                        lateness_us,
                    }
                }
            ),
            (any::<u8>(), 0u64..1 << 60, any::<u32>()).prop_map(|(oid, received_clock, lead_us)| {
                TraceRecord::QueueStep {
                    oid,
                    received_clock,
                    first_step_clock: received_clock + lead_us as u64 * (FREQ / 1_000_000),
                }
            }),
            (any::<u64>(), any::<u16>()).prop_map(|(clock, static_string_id)| TraceRecord::Shutdown {
                clock,
                static_string_id
            }),
        ]
    }

    fn write_all(format: TraceFormat, freq: u64, scale: f64, recs: &[TraceRecord]) -> Vec<u8> {
        let mut w = TraceWriter::new(Vec::new(), format, freq, scale).unwrap();
        for r in recs {
            w.write(r).unwrap();
        }
        w.finish().unwrap()
    }

    #[test]
    fn golden_binary_record() {
        let r = TraceRecord::QueueStep {
            oid: 3,
            received_clock: 0x1122_3344_5566_7788,
            first_step_clock: 0x1122_3344_5566_7788 + 0x0102_0304 * 50,
        };
        assert_eq!(
            r.to_bytes(FREQ),
            [1, 3, 0, 0, 4, 3, 2, 1, 0x88, 0x77, 0x66, 0x55, 0x44, 0x33, 0x22, 0x11]
        );
        let bytes = write_all(TraceFormat::Bin, FREQ, 2.5, &[r]);
        assert_eq!(&bytes[..8], b"CDTRACE1");
        assert_eq!(bytes.len(), HEADER_LEN + RECORD_LEN);
        assert_eq!(parse_trace(&bytes).unwrap().records, [r]);
        // A cut last record is ignored; a bad kind is an error.
        let t = parse_trace(&bytes[..bytes.len() - 3]).unwrap();
        assert!(t.records.is_empty());
        let mut bad = bytes.clone();
        bad[HEADER_LEN] = 9;
        assert!(parse_trace(&bad).is_err());
    }

    #[test]
    fn late_queue_step_reads_back_with_zero_lead() {
        let r = TraceRecord::QueueStep {
            oid: 0,
            received_clock: 1000,
            first_step_clock: 400,
        };
        let t = parse_trace(&write_all(TraceFormat::Bin, FREQ, 1.0, &[r])).unwrap();
        assert_eq!(
            t.records,
            [TraceRecord::QueueStep {
                oid: 0,
                received_clock: 1000,
                first_step_clock: 1000
            }]
        );
    }

    #[test]
    fn csv_text() {
        let r = TraceRecord::Step {
            oid: 0,
            dir: true,
            clock: 50_000,
            lateness_us: 12,
        };
        let text = String::from_utf8(write_all(TraceFormat::Csv, 1000, 1.0, &[r])).unwrap();
        assert_eq!(
            text,
            "# CDTRACE1 clock_freq=1000 time_scale=1\nkind,oid,dir,aux,clock\n0,0,1,12,50000\n"
        );
        assert!(parse_trace(b"# CDTRACE1 clock_freq=1\n").is_err());
        assert!(parse_trace(b"# CDTRACE1 clock_freq=1 time_scale=1\n0,0,1\n").is_err());
    }

    #[test]
    fn trigger_records_both_formats() {
        let step = TraceRecord::Step {
            oid: 0,
            dir: true,
            clock: 500,
            lateness_us: 1,
        };
        let trig = TriggerRecord {
            oid: 4,
            endstop: true,
            reason: 1,
            clock: 1 << 40,
        };
        for format in [TraceFormat::Bin, TraceFormat::Csv] {
            let mut w = TraceWriter::new(Vec::new(), format, FREQ, 1.0).unwrap();
            w.write(&step).unwrap();
            w.write_trigger(&trig).unwrap();
            let t = parse_trace(&w.finish().unwrap()).unwrap();
            assert_eq!(t.records, [step]);
            assert_eq!(t.triggers, [trig]);
        }
        assert_eq!(trig.to_bytes()[..4], [3, 4, 1, 0]);
    }

    #[test]
    fn streamed_records_equal_the_whole_read() {
        let recs: Vec<TraceRecord> = (0..3000u64)
            .map(|i| TraceRecord::Step {
                oid: (i % 3) as u8,
                dir: i % 2 == 0,
                clock: 1000 + i * 50,
                lateness_us: (i % 7) as u32,
            })
            .collect();
        let dir = std::env::temp_dir().join(format!("cadence-trace-stream-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for (format, name) in [(TraceFormat::Bin, "t.bin"), (TraceFormat::Csv, "t.csv")] {
            let path = dir.join(name);
            let mut bytes = write_all(format, FREQ, 2.0, &recs);
            if format == TraceFormat::Bin {
                // A killed writer: the last record cut short.
                bytes.extend_from_slice(&[0, 1, 2]);
            }
            std::fs::write(&path, &bytes).unwrap();
            let mut seen = Vec::new();
            let header = for_each_record(&path, |r| seen.push(*r)).unwrap();
            assert_eq!(header, (FREQ, 2.0));
            assert_eq!(seen, recs);
        }
        let empty = dir.join("empty.bin");
        std::fs::write(&empty, &MAGIC[..]).unwrap();
        assert!(
            for_each_record(&empty, |_| {}).is_err(),
            "a cut header is an error"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn unit_conversions() {
        assert_eq!(ticks_to_us(50, FREQ), 1);
        assert_eq!(ticks_to_us(49, FREQ), 0);
        assert_eq!(ticks_to_us(u64::MAX, 1), u32::MAX);
        assert_eq!(us_to_ticks(3, FREQ), 150);
        assert_eq!(
            ticks_to_us(5, 0),
            5_000_000,
            "a zero frequency does not divide by zero"
        );
    }

    proptest! {
        #[test]
        fn round_trip_both_formats(scale in 0.001f64..1e6, recs in proptest::collection::vec(record(), 0..50)) {
            for format in [TraceFormat::Bin, TraceFormat::Csv] {
                let t = parse_trace(&write_all(format, FREQ, scale, &recs)).unwrap();
                prop_assert_eq!(t.clock_freq, FREQ);
                prop_assert_eq!(t.time_scale, scale);
                prop_assert_eq!(&t.records, &recs);
            }
        }

        #[test]
        fn parse_never_panics(data in proptest::collection::vec(any::<u8>(), 0..200)) {
            let _ = parse_trace(&data);
            let mut with_magic = MAGIC.to_vec();
            with_magic.extend_from_slice(&data);
            let _ = parse_trace(&with_magic);
            let text = format!("# CDTRACE1 clock_freq=1 time_scale=1\n{}", String::from_utf8_lossy(&data));
            let _ = parse_trace(text.as_bytes());
        }
    }
}
