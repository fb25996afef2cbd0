//! Batch mode (`print --batch`, as Klipper's batch mode): no MCU and no waiting, the exact wire
//! stream of each MCU with steppers written to a file, planned on every core. The bytes are the
//! golden output the reference printers are checked against.

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::time::Instant;

use planner::pipeline::Pipeline;
use planner::stepgen::StepCmd;
use sysconfig::printer::PrinterConfig;

use crate::accessories::Accessories;
use crate::gcode_feed::{plan_file, FeedError, FeedTarget, GcodeInput, MotionCmd};
use crate::hardware::Machine;
use crate::step_stream::sink::{BatchSink, Sink};
use crate::step_stream::StreamError;
use crate::step_stream::{McuParams, StepStreams};

/// What a batch print writes and with what.
#[derive(Debug, Clone, Copy)]
pub struct BatchJob<'a> {
    /// The main MCU's wire stream; another MCU's goes to `OUT-NAME.ext`.
    pub out: &'a Path,
    /// The data dictionary (zlib JSON) to encode with; `None`: the Cadence firmware's.
    pub dictionary: Option<&'a Path>,
    /// Maximum step time error of the compression (µs).
    pub max_error_us: f64,
}

/// The figures of a batch print.
#[derive(Debug, Clone)]
pub struct BatchReport {
    pub file: PathBuf,
    /// The wire files written, the main MCU's first.
    pub outputs: Vec<PathBuf>,
    pub lines: u64,
    pub moves: u64,
    /// Print time at the end of the last move (s).
    pub print_time: f64,
    /// Steps per stepper, in printer.cfg order.
    pub steps: Vec<(String, u64)>,
    pub queue_steps: u64,
    pub blocks: u64,
    pub wire_bytes: u64,
    /// Wall time (s).
    pub wall: f64,
    /// What the G-code asked of heaters, fans and the display.
    pub accessories: Vec<String>,
}

/// Why a batch print failed.
#[derive(Debug, thiserror::Error)]
pub enum BatchError {
    /// The dictionary could not be loaded.
    #[error(transparent)]
    Dictionary(#[from] crate::wire_check::DictionaryError),
    /// The dictionary lacks its clock frequency.
    #[error(transparent)]
    Dict(#[from] links::dict::DictError),
    /// An output file could not be created.
    #[error("{}: {source}", .path.display())]
    Create {
        path: std::path::PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// An MCU's configuration does not encode with the dictionary.
    #[error("mcu '{mcu}': {source}")]
    Configure {
        mcu: String,
        #[source]
        source: Box<crate::mcus::ConfigureError>,
    },
    /// The step streams could not be set up or written.
    #[error(transparent)]
    Stream(#[from] crate::step_stream::StreamError),
    /// The planner could not be set up.
    #[error(transparent)]
    Plan(#[from] planner::machine::PlanError),
    /// The printer's macros.
    #[error(transparent)]
    Macros(#[from] crate::hardware::MacrosError),
    /// The G-code feed stopped (its error, located at its file and line).
    #[error(transparent)]
    Feed(Box<FeedError<crate::step_stream::StreamError>>),
}

from_boxed!(BatchError, Feed, FeedError<crate::step_stream::StreamError>);

/// Batch mode: the wire stream of each MCU with steppers (the main one to `out`, another one
/// to `out` with `-NAME` inserted, as for traces), every MCU encoded with the one dictionary and
/// its clock counted from print time 0.
pub fn run_batch(
    job: &BatchJob<'_>,
    cfg: &PrinterConfig,
    machine: &Machine,
    gcode: GcodeInput,
) -> Result<BatchReport, BatchError> {
    let started = Instant::now();
    let out = job.out;
    let dict = crate::wire_check::load_dictionary(job.dictionary)?;
    let clock_freq = dict.clock_freq()?;
    let names: Vec<&str> = cfg.mcus.iter().map(|m| m.name.as_str()).collect();
    let move_count = 16384;
    let params: Vec<McuParams<'_>> = crate::step_stream::stream_mcus(machine, &names)
        .into_iter()
        .map(|i| McuParams {
            name: names[i],
            mcu_index: i,
            dict: &dict,
            clock_freq,
            move_count,
        })
        .collect();
    let mut sinks = Vec::with_capacity(params.len());
    let mut paths = Vec::with_capacity(params.len());
    for (k, m) in params.iter().enumerate() {
        let path = crate::mcus::trace_path(out, m.name, k == 0);
        let file = File::create(&path).map_err(|source| BatchError::Create {
            path: path.clone(),
            source,
        })?;
        let mut sink = BatchSink::new(BufWriter::with_capacity(1 << 16, file));
        for c in crate::mcus::config_commands(&dict, machine, m.name)
            .map_err(|source| BatchError::Configure {
                mcu: m.name.to_string(),
                source: Box::new(source),
            })?
            .0
        {
            sink.send(c)?;
        }
        sinks.push(sink);
        paths.push(path);
    }
    let mut streams = StepStreams::new(machine, &params)?;
    // Batch mode runs flat out: step generation and compression on every core.
    let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    let mut pipeline = machine.batch_pipeline(clock_freq, job.max_error_us * 1e-6, threads)?;
    let mut accessories = Accessories::new(false);
    let file = gcode.name.clone();
    let mut target = BatchTarget {
        streams: &mut streams,
        sinks: &mut sinks,
    };
    let mut macros = machine.macros(pipeline.planned_until())?;
    let lines = plan_file(
        gcode,
        &mut pipeline,
        &mut accessories,
        &mut macros,
        &machine.homing,
        &mut target,
    )?;
    for s in &mut sinks {
        s.finish()?;
    }
    let stats = pipeline.stats();
    Ok(BatchReport {
        file,
        outputs: paths,
        lines,
        moves: stats.moves,
        print_time: pipeline.planned_until(),
        steps: machine
            .steppers
            .iter()
            .map(|s| s.name.clone())
            .zip(streams.steps_sent())
            .collect(),
        queue_steps: streams.queue_steps(),
        blocks: sinks.iter().map(|s| s.blocks).sum::<u64>(),
        wire_bytes: sinks.iter().map(|s| s.bytes).sum::<u64>(),
        wall: started.elapsed().as_secs_f64(),
        accessories: accessories.lines(),
    })
}

/// The batch print's end of the G-code loop: step commands straight into the files, no
/// pacing, no motion with MCUs.
struct BatchTarget<'a, W: std::io::Write> {
    streams: &'a mut StepStreams,
    sinks: &'a mut [BatchSink<W>],
}

impl<W: std::io::Write> FeedTarget for BatchTarget<'_, W> {
    type Error = StreamError;

    fn emit(&mut self, cmds: &mut Vec<(usize, StepCmd)>) -> Result<(), StreamError> {
        for &(idx, cmd) in cmds.iter() {
            self.streams.push(idx, cmd, self.sinks)?;
        }
        Ok(())
    }

    fn pace(&mut self, _: &mut Pipeline) -> Result<(), StreamError> {
        Ok(())
    }

    fn motion(&mut self, _: &mut Pipeline, _: &MotionCmd<'_>) -> Result<bool, StreamError> {
        Ok(false)
    }

    fn resume_at(&self) -> f64 {
        0.0
    }

    fn warn(&mut self, text: String) {
        eprintln!("cadence: warning: {text}");
    }

    fn motors_off(&mut self, pipeline: &mut Pipeline) -> Result<(), StreamError> {
        let mut out = Vec::new();
        pipeline.flush_lookahead();
        pipeline.generate(&mut out);
        self.emit(&mut out)?;
        self.streams.motors_off(&[], self.sinks)
    }
}
