//! Proves (`cadence decode STREAM --check FILE.gcode`) a wire stream written by `print --batch`
//! against the motion of the G-code it came from.
//!
//! The G-code is planned again with the same printer.cfg, MCU clock and step-time bound,
//! recording every step's ideal time; the stream's `queue_step`, `set_next_step_dir` and
//! `reset_step_clock` are replayed as the MCU runs them, and every step must land within the
//! bound before its ideal time, never before the previous step, in its ideal direction, and
//! every planned step must be in the stream ([`planner::checker`]). Planning is pulled as the
//! stream needs steps, so memory stays bounded by the steps between the stream's order and the
//! planner's, whatever the file size. `[gcode_macro]` calls run as a print runs them (each
//! macro rendered when its call is reached), so a stream of a print with macros checks too.
//!
//! Steppers are matched by step pin: each `config_stepper` of the stream names a step pin,
//! which must be the step pin of a stepper on that MCU in printer.cfg (so the stream's object
//! ids need not be Cadence's). `reset_step_clock` carries the low 32 bits of the clock: the
//! full clock is the one with those bits nearest the stepper's next planned step. A stepper's
//! clock is 0 from its `config_stepper` on, as on the MCU: Klipper's first `queue_step` of a
//! stepper comes before any `reset_step_clock`, its interval counted from 0.

use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};

use links::dict::{Dictionary, Message};
use links::proto::{blocks, StreamItem};
use planner::checker::{CheckStats, Checker, StepCmd};
use planner::gcode::macros::Macros;
use planner::gcode::GcodeReader;
use planner::pipeline::Pipeline;

use crate::gcode_feed::{macro_status, MacroRun};
use crate::hardware::{HardwareError, Machine};

/// Why a data dictionary could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum DictionaryError {
    /// The file could not be read.
    #[error("{}: {source}", .path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The file is not a dictionary.
    #[error("{}: {source}", .path.display())]
    Parse {
        path: PathBuf,
        #[source]
        source: links::dict::DictError,
    },
    /// The built-in firmware's dictionary (a bug).
    #[error("firmware dictionary: {0}")]
    Firmware(#[source] links::dict::DictError),
}

/// The older string-typed layers' view (the message as shown).
impl From<DictionaryError> for String {
    fn from(e: DictionaryError) -> String {
        e.to_string()
    }
}

/// Why a wire stream could not be checked, or is wrong.
#[derive(Debug, thiserror::Error)]
pub enum WireCheckError {
    /// `--max-error-us` out of range.
    #[error("--max-error-us {0}: must be in (0, 1000]")]
    MaxError(f64),
    /// The G-code file could not be opened.
    #[error("{}: {source}", .path.display())]
    Open {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// printer.cfg could not be read or describes no printer Cadence can drive.
    #[error(transparent)]
    Config(#[from] HardwareError),
    /// `--mcu` names an MCU without steppers.
    #[error("--mcu {mcu}: no stepper of the printer config is on that MCU")]
    NoStepperOnMcu { mcu: String },
    /// The dictionary lacks what the check needs.
    #[error(transparent)]
    Dictionary(#[from] links::dict::DictError),
    /// A stepper's step pin is not in the dictionary.
    #[error("[{stepper}] step_pin: {source}")]
    StepPin {
        stepper: String,
        #[source]
        source: links::dict::DictError,
    },
    /// The planner could not be set up.
    #[error(transparent)]
    Plan(#[from] planner::machine::PlanError),
    /// A `[gcode_macro]` does not compile.
    #[error(transparent)]
    Macro(#[from] planner::gcode::macros::MacroError),
    /// A macro call failed while planning (located by the G-code feed).
    #[error(transparent)]
    MacroRun(Box<crate::gcode_feed::MacroRunError>),
    /// A G-code line could not be read.
    #[error("{}: {source}", .file.display())]
    Read {
        file: PathBuf,
        #[source]
        source: planner::gcode::GcodeError,
    },
    /// The planner refused a G-code line (`via`: the macro it came from).
    #[error("{}: {source}{}", .file.display(), .via.as_ref().map(|v| format!(" (in macro {v})")).unwrap_or_default())]
    Line {
        file: PathBuf,
        via: Option<String>,
        #[source]
        source: planner::machine::PlanError,
    },
    /// A block of the stream does not decode or replay.
    #[error("{}: block at byte {pos}: {source}", .stream.display())]
    Block {
        stream: PathBuf,
        pos: usize,
        #[source]
        source: Box<ReplayError>,
    },
    /// Bytes that are not a block.
    #[error("{}: block at byte {pos}: not a valid block", .stream.display())]
    BadBlock { stream: PathBuf, pos: usize },
    /// The stream ends inside a block.
    #[error("{}: block at byte {pos}: truncated block", .stream.display())]
    Truncated { stream: PathBuf, pos: usize },
    /// A stepper's steps differ from the G-code's motion.
    #[error("{stepper}: {source}{}", if *.configured { "" } else { " (the stream never configures this stepper)" })]
    Steps {
        stepper: String,
        configured: bool,
        #[source]
        source: planner::checker::CheckError,
    },
}

/// The CLI's view (the message as shown).
impl From<WireCheckError> for String {
    fn from(e: WireCheckError) -> String {
        e.to_string()
    }
}

/// Why one message of the stream does not replay.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    /// The block does not decode.
    #[error(transparent)]
    Decode(#[from] links::dict::DictError),
    /// A message without a field it must have.
    #[error("{name}: no field '{field}'")]
    NoField { name: String, field: String },
    /// A step command for an oid no `config_stepper` named.
    #[error("{msg}: oid {oid} is not a configured stepper")]
    NotConfigured { msg: String, oid: i64 },
    /// A `config_stepper` whose step pin no stepper of the MCU has.
    #[error("{msg}: no stepper on this MCU in printer.cfg has that step pin")]
    UnknownStepPin { msg: String },
    /// A field out of its range (`field`: `oid`, `count`, `interval`, `add`).
    #[error("{msg}: bad {field}")]
    BadField { msg: String, field: &'static str },
    /// The step command is wrong against the G-code's motion.
    #[error("{stepper}: {source}")]
    Steps {
        stepper: String,
        #[source]
        source: planner::checker::CheckError,
    },
    /// Planning further failed.
    #[error(transparent)]
    Planning(Box<WireCheckError>),
}

/// The data dictionary in `path` (zlib-compressed JSON as served by identify, or plain JSON as
/// Klipper's build writes `out/klipper.dict`), or the Cadence firmware's own when none is given.
pub fn load_dictionary(path: Option<&std::path::Path>) -> Result<Dictionary, DictionaryError> {
    match path {
        Some(p) => {
            let bytes = std::fs::read(p).map_err(|source| DictionaryError::Read {
                path: p.to_path_buf(),
                source,
            })?;
            Dictionary::from_file_bytes(&bytes).map_err(|source| DictionaryError::Parse {
                path: p.to_path_buf(),
                source,
            })
        }
        None => Dictionary::from_compressed(&firmware::dictionary_bytes(50_000_000))
            .map_err(DictionaryError::Firmware),
    }
}

/// What a check needs besides the stream.
#[derive(Debug)]
pub struct CheckSpec<'a> {
    pub gcode: &'a Path,
    pub config: Option<&'a Path>,
    /// The MCU the stream was written for (`mcu`, or the NAME of `[mcu NAME]`).
    pub mcu: &'a str,
    pub max_error_us: f64,
}

/// One stepper of the checked MCU.
struct Checked {
    name: String,
    /// Index in the planner's steppers.
    idx: usize,
    /// The step pin's value in the dictionary's `pin` enumeration.
    step_pin: u32,
    dir_invert: bool,
    checker: Checker,
    /// Seen in a `config_stepper` of the stream.
    configured: bool,
}

/// The G-code side: plans on demand and hands each stepper its ideal steps.
struct Planner {
    pipeline: Pipeline,
    lines: GcodeReader<BufReader<File>>,
    /// The printer's macros, run as a print runs them.
    macros: Macros,
    /// The macro call whose lines are being planned.
    run: Option<MacroRun>,
    done: bool,
    out: Vec<(usize, StepCmd)>,
    /// Planner stepper count (steppers of other MCUs are planned and their steps dropped).
    steppers: usize,
}

impl Planner {
    /// Plans one more G-code line (or finishes at the end); false once everything is planned.
    fn more(&mut self, checked: &mut [Checked], file: &Path) -> Result<bool, WireCheckError> {
        if self.done {
            return Ok(false);
        }
        // Messages of macros and [respond] are not part of the check.
        let say = &mut |_: String| {};
        loop {
            if let Some(run) = self.run.as_mut() {
                let status = macro_status(&self.pipeline);
                match run
                    .next(&mut self.macros, &status, file, say)
                    .map_err(|e| WireCheckError::MacroRun(Box::new(e)))?
                {
                    Some(sub) => {
                        self.pipeline.apply(&sub).map_err(|source| WireCheckError::Line {
                            file: file.to_path_buf(),
                            via: Some(run.via().to_string()),
                            source,
                        })?;
                        self.pipeline.generate(&mut self.out);
                        break;
                    }
                    None => self.run = None,
                }
                continue;
            }
            match self.lines.next() {
                Some(line) => {
                    let line = line.map_err(|source| WireCheckError::Read {
                        file: file.to_path_buf(),
                        source,
                    })?;
                    let pipeline = &self.pipeline;
                    self.run = MacroRun::start(&line, &mut self.macros, || macro_status(pipeline), file, say)
                        .map_err(|e| WireCheckError::MacroRun(Box::new(e)))?;
                    if self.run.is_some() {
                        continue;
                    }
                    self.pipeline
                        .apply(&line)
                        .map_err(|source| WireCheckError::Line {
                            file: file.to_path_buf(),
                            via: None,
                            source,
                        })?;
                    self.pipeline.generate(&mut self.out);
                }
                None => {
                    self.pipeline.finish(&mut self.out);
                    self.done = true;
                }
            }
            break;
        }
        self.out.clear();
        for idx in 0..self.steppers {
            let ideal = self.pipeline.take_ideal(idx);
            if let Some(c) = checked.iter_mut().find(|c| c.idx == idx) {
                c.checker.push_ideal(ideal);
            }
        }
        Ok(true)
    }
}

/// Runs the check of `data` (the stream) and prints one line per stepper.
pub fn run(
    stream: &Path,
    data: &[u8],
    dict: &Dictionary,
    spec: &CheckSpec<'_>,
    out: &mut dyn FnMut(String),
) -> Result<(), WireCheckError> {
    if !(spec.max_error_us > 0.0 && spec.max_error_us <= 1000.0) {
        return Err(WireCheckError::MaxError(spec.max_error_us));
    }
    let gcode = File::open(spec.gcode).map_err(|source| WireCheckError::Open {
        path: spec.gcode.to_path_buf(),
        source,
    })?;
    let cfg = crate::hardware::load_config(spec.config)?;
    let machine = Machine::from_config(&cfg)?;
    if !machine.steppers.iter().any(|s| s.mcu == spec.mcu) {
        return Err(WireCheckError::NoStepperOnMcu {
            mcu: spec.mcu.to_string(),
        });
    }
    let clock_freq = dict.clock_freq()?;
    let mut pipeline = machine.batch_pipeline(clock_freq, spec.max_error_us * 1e-6, 0)?;
    pipeline.set_record_ideal(true);
    let mut checked = checked_steppers(&machine, dict, spec.mcu, pipeline.max_error_ticks())?;
    let mut planner = Planner {
        pipeline,
        lines: GcodeReader::new(BufReader::with_capacity(1 << 16, gcode)),
        macros: Macros::new(machine.macros.clone())?.with_respond(machine.respond_prefix.clone()),
        run: None,
        done: false,
        out: Vec::with_capacity(4096),
        steppers: machine.steppers.len(),
    };
    replay_stream(stream, data, dict, &mut checked, &mut planner, spec.gcode)?;
    while planner.more(&mut checked, spec.gcode)? {}
    report(stream, spec, &machine, &checked, clock_freq, out)
}

/// The checkers of the steppers on MCU `mcu`.
fn checked_steppers(
    machine: &Machine,
    dict: &Dictionary,
    mcu: &str,
    max_ticks: u32,
) -> Result<Vec<Checked>, WireCheckError> {
    let mut checked = Vec::new();
    for (idx, s) in machine.steppers.iter().enumerate() {
        if s.mcu != mcu {
            continue;
        }
        let step_pin = dict
            .pin(&s.step_pin.pin)
            .map_err(|source| WireCheckError::StepPin {
                stepper: s.name.clone(),
                source,
            })?;
        checked.push(Checked {
            name: s.name.clone(),
            idx,
            step_pin,
            dir_invert: s.dir_pin.invert,
            checker: Checker::for_wire(max_ticks),
            configured: false,
        });
    }
    Ok(checked)
}

/// Decodes the stream block by block and replays each message against the planned G-code.
fn replay_stream(
    stream: &Path,
    data: &[u8],
    dict: &Dictionary,
    checked: &mut [Checked],
    planner: &mut Planner,
    gcode: &Path,
) -> Result<(), WireCheckError> {
    // Object id → index in `checked`.
    let mut by_oid: [Option<usize>; 256] = [None; 256];
    let stream_path = stream.to_path_buf();
    let at = |pos: usize, e: ReplayError| WireCheckError::Block {
        stream: stream_path.clone(),
        pos,
        source: Box::new(e),
    };
    for item in blocks(data) {
        match item {
            StreamItem::Block { pos, payload, .. } => {
                let msgs = dict.decode(payload).map_err(|e| at(pos, e.into()))?;
                for m in &msgs {
                    replay(m, checked, &mut by_oid, planner, gcode).map_err(|e| at(pos, e))?;
                }
            }
            StreamItem::Bad { pos, .. } => {
                return Err(WireCheckError::BadBlock {
                    stream: stream_path,
                    pos,
                })
            }
            StreamItem::Truncated { pos, .. } => {
                return Err(WireCheckError::Truncated {
                    stream: stream_path,
                    pos,
                })
            }
        }
    }
    Ok(())
}

/// The check's report: the stream and G-code, then one line per stepper (or its mismatch).
fn report(
    stream: &Path,
    spec: &CheckSpec<'_>,
    machine: &Machine,
    checked: &[Checked],
    clock_freq: f64,
    out: &mut dyn FnMut(String),
) -> Result<(), WireCheckError> {
    out(format!(
        "check: {} against {} (MCU '{}', max error {} µs)",
        stream.display(),
        spec.gcode.display(),
        spec.mcu,
        spec.max_error_us
    ));
    if !machine.host.delayed.is_empty() {
        // The check plans the G-code lines and the macros they call; the live and batch
        // prints also fire timers, which this replay does not (said, not guessed).
        let ids: Vec<&str> = machine.host.delayed.iter().map(|(id, _)| id.as_str()).collect();
        out(format!(
            "  note: [delayed_gcode] timers ({}) are not run by the check (initial_duration and \
             UPDATE_DELAYED_GCODE): steps their scripts moved are not planned here",
            ids.join(", ")
        ));
    }
    for c in checked {
        let stats: CheckStats = c.checker.finish().map_err(|source| WireCheckError::Steps {
            stepper: c.name.clone(),
            configured: c.configured,
            source,
        })?;
        out(format!(
            "  {:<10} {} steps in {} queue_step, {} direction changes, position {}, max early {:.2} µs: ok",
            c.name,
            stats.steps,
            stats.queue_steps,
            stats.dir_changes,
            stats.position,
            stats.max_early_ticks / clock_freq * 1e6
        ));
    }
    Ok(())
}

/// Replays one message of the stream.
fn replay(
    m: &Message,
    checked: &mut [Checked],
    by_oid: &mut [Option<usize>; 256],
    planner: &mut Planner,
    gcode: &Path,
) -> Result<(), ReplayError> {
    let field = |name: &str| {
        m.get(name).ok_or_else(|| ReplayError::NoField {
            name: m.name.clone(),
            field: name.to_string(),
        })
    };
    let target = |by_oid: &[Option<usize>; 256]| -> Result<usize, ReplayError> {
        let oid = field("oid")?;
        usize::try_from(oid)
            .ok()
            .and_then(|o| by_oid.get(o).copied().flatten())
            .ok_or_else(|| ReplayError::NotConfigured {
                msg: m.to_string(),
                oid,
            })
    };
    let bad = |field: &'static str| ReplayError::BadField {
        msg: m.to_string(),
        field,
    };
    let steps = |c: &Checked, source| ReplayError::Steps {
        stepper: c.name.clone(),
        source,
    };
    let more = |checked: &mut [Checked], planner: &mut Planner| {
        planner
            .more(checked, gcode)
            .map_err(|e| ReplayError::Planning(Box::new(e)))
    };
    match m.name.as_str() {
        "config_stepper" => {
            let (oid, pin) = (field("oid")?, field("step_pin")?);
            let i = checked
                .iter()
                .position(|c| i64::from(c.step_pin) == pin)
                .ok_or_else(|| ReplayError::UnknownStepPin { msg: m.to_string() })?;
            checked[i].configured = true;
            // config_stepper starts the stepper's step clock at 0 on the MCU (Klipper's and
            // Cadence's), so a first queue_step before any reset_step_clock counts from 0:
            // Klipper's host sends its first interval that way.
            checked[i]
                .checker
                .check_cmd(&StepCmd::ResetClock { clock: 0 })
                .map_err(|e| steps(&checked[i], e))?;
            let slot = usize::try_from(oid)
                .ok()
                .and_then(|o| by_oid.get_mut(o))
                .ok_or_else(|| bad("oid"))?;
            *slot = Some(i);
        }
        "set_next_step_dir" => {
            let i = target(by_oid)?;
            let c = &mut checked[i];
            let dir = (field("dir")? != 0) != c.dir_invert;
            let cmd = StepCmd::SetDir { dir };
            c.checker.check_cmd(&cmd).map_err(|e| steps(c, e))?;
        }
        "reset_step_clock" => {
            let i = target(by_oid)?;
            // The full clock from its low 32 bits: nearest the next planned step.
            while checked[i].checker.outstanding() == 0 && more(checked, planner)? {}
            let c = &mut checked[i];
            let low = field("clock")? as u64 & 0xffff_ffff;
            let near = c.checker.next_ideal_clock().unwrap_or(0.0).max(0.0) as u64;
            let clock = unwrap_clock(low, near);
            c.checker
                .check_cmd(&StepCmd::ResetClock { clock })
                .map_err(|e| steps(c, e))?;
        }
        "queue_step" => {
            let i = target(by_oid)?;
            let count = field("count")?;
            let count = u16::try_from(count).map_err(|_| bad("count"))?;
            while checked[i].checker.outstanding() < usize::from(count) && more(checked, planner)? {}
            let c = &mut checked[i];
            let cmd = StepCmd::QueueStep {
                interval: u32::try_from(field("interval")?).map_err(|_| bad("interval"))?,
                count,
                add: i16::try_from(field("add")?).map_err(|_| bad("add"))?,
                first_clock: 0,
                last_clock: 0,
            };
            c.checker.check_cmd(&cmd).map_err(|e| steps(c, e))?;
        }
        _ => {}
    }
    Ok(())
}

/// The clock whose low 32 bits are `low`, nearest `near`.
fn unwrap_clock(low: u64, near: u64) -> u64 {
    const SPAN: u64 = 1 << 32;
    let base = (near & !(SPAN - 1)) | low;
    [base.checked_sub(SPAN), Some(base), base.checked_add(SPAN)]
        .into_iter()
        .flatten()
        .min_by_key(|&c| c.abs_diff(near))
        .unwrap_or(base)
}

#[cfg(test)]
mod tests {
    use super::unwrap_clock;

    #[test]
    fn clocks_unwrap_to_the_nearest() {
        let span = 1u64 << 32;
        assert_eq!(unwrap_clock(100, 50), 100);
        assert_eq!(unwrap_clock(100, 3 * span + 200), 3 * span + 100);
        // Just before a wrap, the step just after it.
        assert_eq!(unwrap_clock(5, 3 * span - 10), 3 * span + 5);
        assert_eq!(unwrap_clock(span - 5, 3 * span + 10), 3 * span - 5);
    }
}
