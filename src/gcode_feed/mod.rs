//! The G-code loop shared by every print: lines from a [`GcodeInput`] through the planner's
//! pipeline, step commands handed on as they become final, G28 and the probe commands given to
//! the caller when the MCUs must be in the loop ([`MotionCmd`]), heater/fan/display commands
//! recorded in [`Accessories`]. Errors name the file (or stream) and line.

use std::collections::BTreeSet;
use std::fs::File;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender};
use std::time::Duration;

use planner::gcode::host::{delayed_macro_name, HostAction, IDLE_TIMEOUT_MACRO};
use planner::gcode::macros::{split_command, Macros, Script};
use planner::gcode::respond::{is_respond_command, respond};
use planner::gcode::{parse_line, Command, GcodeError, GcodeLine, GcodeReader, OtherParams};
use planner::machine::Applied;
use planner::pipeline::Pipeline;
use planner::stepgen::StepCmd;

use crate::accessories::Accessories;
use crate::heaters::gcode::{self as heat_gcode, HeatCmd};
use crate::homing::procedure::{HomeOps, HomingProcedure, ProbeScripts, ProcedureError};
use sysconfig::printer::{PROBE_ACTIVATE_MACRO, PROBE_DEACTIVATE_MACRO};

mod error;

pub use error::{BedScrewsFailure, CommandError, FeedError, G28Error, MacroRunError, MacroStepError};

/// Where a print's G-code comes from: a name for messages (the file's path, or a stream's
/// label) and either buffered bytes or a session's channel of commands.
pub struct GcodeInput {
    /// The file, or a stream's label, that errors and warnings name.
    pub name: PathBuf,
    source: Source,
}

enum Source {
    Reader(Box<dyn BufRead + Send>),
    Session(SessionFeed),
}

impl GcodeInput {
    /// Opens a G-code file (64 KiB buffered).
    pub fn open(path: &Path) -> std::io::Result<GcodeInput> {
        let file = File::open(path)?;
        Ok(GcodeInput {
            name: path.to_path_buf(),
            source: Source::Reader(Box::new(BufReader::with_capacity(1 << 16, file))),
        })
    }

    /// G-code from any buffered reader (a pipe, a socket, generated text), named `name` in
    /// messages.
    pub fn from_reader(name: impl Into<PathBuf>, reader: impl BufRead + Send + 'static) -> GcodeInput {
        GcodeInput {
            name: name.into(),
            source: Source::Reader(Box::new(reader)),
        }
    }

    /// Commands sent one at a time over `rx` (a printer session): after `idle` without one the
    /// lookahead is flushed so what was sent moves, and the next command starts from the MCUs'
    /// time then.
    pub(crate) fn session(name: impl Into<PathBuf>, rx: Receiver<FeedMsg>, idle: Duration) -> GcodeInput {
        GcodeInput {
            name: name.into(),
            source: Source::Session(SessionFeed { rx, idle, line_no: 0 }),
        }
    }

    fn is_session(&self) -> bool {
        matches!(self.source, Source::Session(_))
    }

    fn items(self) -> Box<dyn Iterator<Item = FeedItem> + Send> {
        match self.source {
            Source::Reader(r) => Box::new(GcodeReader::new(r).map(FeedItem::Line)),
            Source::Session(s) => Box::new(s),
        }
    }
}

impl std::fmt::Debug for GcodeInput {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GcodeInput")
            .field("name", &self.name)
            .finish_non_exhaustive()
    }
}

/// What a printer session sends its planner thread.
#[derive(Debug)]
pub(crate) enum FeedMsg {
    /// One line of G-code.
    Line(String),
    /// Everything before it is planned and handed on when the planner answers.
    Barrier(SyncSender<()>),
    /// One line of G-code whose outcome is answered on the channel once it is planned: a
    /// command the planner refuses (a parse error, an unknown command, a move out of range, a
    /// macro error) is answered with its error and the session goes on; an error of the MCUs
    /// or a stop is answered too and ends the session.
    Checked(String, SyncSender<Result<(), LineError>>),
}

/// Why a [`FeedMsg::Checked`] line failed.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct LineError {
    pub message: String,
    /// The error came from the MCUs, the hand-off or a stop: the session ends.
    pub ends_session: bool,
}

/// The planner's view of a feed. Lines stay inline: boxing them would allocate per line on
/// the planner thread.
#[allow(clippy::large_enum_variant)]
enum FeedItem {
    Line(Result<GcodeLine, GcodeError>),
    /// Nothing came for a while: flush the lookahead.
    Idle,
    Barrier(SyncSender<()>),
    Checked(Result<GcodeLine, GcodeError>, SyncSender<Result<(), LineError>>),
}

/// A session's commands as feed items (ends when the session's sender is dropped).
struct SessionFeed {
    rx: Receiver<FeedMsg>,
    idle: Duration,
    line_no: usize,
}

impl SessionFeed {
    /// The next line of the session (`None`: blank or a comment).
    fn parse(&mut self, text: &str) -> Option<Result<GcodeLine, GcodeError>> {
        self.line_no += 1;
        let raw = text.trim_end_matches(['\n', '\r']).as_bytes();
        match parse_line(self.line_no, raw) {
            Ok(Some(cmd)) => Some(Ok(GcodeLine {
                line_no: self.line_no,
                cmd,
            })),
            Ok(None) => None,
            Err(e) => Some(Err(e)),
        }
    }
}

impl Iterator for SessionFeed {
    type Item = FeedItem;

    fn next(&mut self) -> Option<FeedItem> {
        loop {
            match self.rx.recv_timeout(self.idle) {
                Ok(FeedMsg::Line(text)) => match self.parse(&text) {
                    Some(line) => return Some(FeedItem::Line(line)),
                    None => continue,
                },
                Ok(FeedMsg::Checked(text, reply)) => match self.parse(&text) {
                    Some(line) => return Some(FeedItem::Checked(line, reply)),
                    None => {
                        // A blank line or a comment: nothing to plan.
                        let _ = reply.try_send(Ok(()));
                        continue;
                    }
                },
                Ok(FeedMsg::Barrier(done)) => return Some(FeedItem::Barrier(done)),
                Err(RecvTimeoutError::Timeout) => return Some(FeedItem::Idle),
                Err(RecvTimeoutError::Disconnected) => return None,
            }
        }
    }
}

/// Where the G-code loop hands its results: the live planner thread or a batch print.
pub(crate) trait FeedTarget {
    /// Why the target failed: the MCUs, the hand-off, a stop, a refused heater command.
    type Error: std::error::Error + 'static;
    /// Step commands that became final (the target may leave `cmds` as it is: it is cleared).
    fn emit(&mut self, cmds: &mut Vec<(usize, StepCmd)>) -> Result<(), Self::Error>;
    /// Runs between batches: flow control, MCU and stop checks, status.
    fn pace(&mut self, pipeline: &mut Pipeline) -> Result<(), Self::Error>;
    /// Runs G28 or a probe command with the MCUs in the loop (true), or leaves it to the
    /// planner (false).
    fn motion(&mut self, pipeline: &mut Pipeline, cmd: &MotionCmd<'_>) -> Result<bool, Self::Error>;
    /// The earliest print time a move may start at after the feed was idle.
    fn resume_at(&self) -> f64;
    /// A warning about the G-code.
    fn warn(&mut self, text: String);
    /// The feed went idle (`true`) or got a command after being idle (`false`).
    fn idle(&mut self, _idle: bool, _pipeline: &Pipeline) {}
    /// A heater or fan command ([`HeatCmd`]; waits hold the G-code, with the moves before
    /// them flushed; M105 reports). Without heaters (batch) nothing.
    fn heat(&mut self, _pipeline: &mut Pipeline, _cmd: &HeatCmd) -> Result<(), Self::Error> {
        Ok(())
    }
    /// An extruding move of extruder `extruder` (its heater's name) is allowed (it is at
    /// `min_extrude_temp` or above).
    fn can_extrude(&self, _extruder: &str) -> Result<(), Self::Error> {
        Ok(())
    }
    /// M84/M18 after the moves before it were planned: the drivers go off once they ran.
    fn motors_off(&mut self, _pipeline: &mut Pipeline) -> Result<(), Self::Error> {
        Ok(())
    }
}

/// The outcome of a step of the loop fed to target `T`.
type Fed<T, R = ()> = Result<R, FeedError<<T as FeedTarget>::Error>>;

/// Reports G-code commands the planner does not know, once per name, in Klipper's words.
#[derive(Debug, Default)]
struct Warnings {
    seen: BTreeSet<String>,
}

impl Warnings {
    fn unsupported(&mut self, file: &Path, line: usize, name: &str, target: &mut impl FeedTarget) {
        // Look up first: the name is copied (allocated) only the first time it is seen.
        if !self.seen.contains(name) && self.seen.insert(name.to_string()) {
            target.warn(format!(
                "{}:{line}: Unknown command:\"{name}\" (skipped as Klipper does, reported once; \
                 --strict or `unknown_commands: error` in [gcode] stops the print instead)",
                file.display()
            ));
        }
    }
}

/// A G-code command that moves with the MCUs in the loop: `motion` in [`plan_file`] runs it on a
/// live print (and says so) or leaves it to the planner.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum MotionCmd<'a> {
    /// G28 with the axes to home.
    Home([bool; 3]),
    /// PROBE, PROBE_ACCURACY or QUERY_PROBE, as written.
    Probe { name: &'a str, raw: &'a str },
    /// SET_TMC_CURRENT, SET_TMC_FIELD, DUMP_TMC or INIT_TMC, as written.
    Tmc { name: &'a str, raw: &'a str },
}

impl MotionCmd<'_> {
    /// The command's name for errors.
    fn name(&self) -> &str {
        match self {
            MotionCmd::Home(_) => "G28",
            MotionCmd::Probe { name, .. } | MotionCmd::Tmc { name, .. } => name,
        }
    }
}

/// Feeds the G-code through the planner, handing step commands to `target` as they become
/// final; G28 and the probe commands go to [`FeedTarget::motion`] first. Heater, fan, display
/// and M114 commands go to `accessories`. A session's idle spells flush the lookahead; the
/// next command then starts no earlier than [`FeedTarget::resume_at`]. Returns the commands
/// planned.
pub(crate) fn plan_file<T: FeedTarget>(
    input: GcodeInput,
    pipeline: &mut Pipeline,
    accessories: &mut Accessories,
    macros: &mut Macros,
    homing: &HomingProcedure,
    target: &mut T,
) -> Fed<T, u64> {
    let mut st = FeedState {
        warnings: Warnings::default(),
        out: Vec::with_capacity(4096),
        file: input.name.clone(),
        // A session starts idle: its first command starts from the MCUs' time then.
        idle: input.is_session(),
        lines: 0,
        probe_scripts: homing.probe_scripts,
    };
    if st.idle {
        target.idle(true, pipeline);
    }
    for item in input.items() {
        let (line, reply) = match item {
            FeedItem::Line(line) => (line, None),
            FeedItem::Checked(line, reply) => (line, Some(reply)),
            FeedItem::Idle => {
                st.quiet_turn(pipeline, accessories, macros, target)?;
                continue;
            }
            FeedItem::Barrier(done) => {
                st.quiet_turn(pipeline, accessories, macros, target)?;
                // The sender waits for it; a sender that gave up is no error.
                let _ = done.try_send(());
                continue;
            }
        };
        st.lines += 1;
        let mut feed = st.feed(pipeline, accessories, macros);
        // `[delayed_gcode]` timers that came due on the print timeline run before the line.
        macros.host_mut().set_now(feed.pipeline.planned_until());
        if macros.host().due_timer().is_some() {
            let line_no = line.as_ref().map_or(0, |l| l.line_no);
            feed.run_due_timers(line_no, None, macros, target)?;
        }
        let line = line.map_err(|source| FeedError::Read {
            file: feed.file.to_path_buf(),
            source,
        });
        match reply {
            None => feed.run_line(&line?, macros, homing, target)?,
            Some(reply) => feed.run_checked(line, reply, macros, homing, target)?,
        }
    }
    st.run_last_timers(pipeline, accessories, macros, target)?;
    pipeline.finish(&mut st.out);
    target.emit(&mut st.out).map_err(FeedError::Target)?;
    Ok(st.lines)
}

/// What the loop keeps from one command to the next.
struct FeedState {
    warnings: Warnings,
    out: Vec<(usize, StepCmd)>,
    /// The file, or the stream's label, errors name.
    file: PathBuf,
    /// The feed is idle: the lookahead was flushed and the next command starts anew.
    idle: bool,
    /// Commands planned so far.
    lines: u64,
    /// `[probe]`'s scripts around probing sessions.
    probe_scripts: ProbeScripts,
}

impl FeedState {
    /// What the next command is planned with.
    fn feed<'a>(
        &'a mut self,
        pipeline: &'a mut Pipeline,
        accessories: &'a mut Accessories,
        macros: &Macros,
    ) -> Feed<'a> {
        Feed {
            force_move: macros.host().force_move(),
            file: &self.file,
            pipeline,
            accessories,
            warnings: &mut self.warnings,
            out: &mut self.out,
            idle: &mut self.idle,
            probe_scripts: self.probe_scripts,
            in_probe_script: false,
        }
    }

    /// A session was quiet for a while, or asked for a barrier: the lookahead is flushed, the
    /// printer's timeline goes on (timers and the idle timeout run from it).
    fn quiet_turn<T: FeedTarget>(
        &mut self,
        pipeline: &mut Pipeline,
        accessories: &mut Accessories,
        macros: &mut Macros,
        target: &mut T,
    ) -> Fed<T> {
        if !self.idle {
            pipeline.flush_lookahead();
            release(pipeline, &mut self.out, target)?;
            self.idle = true;
            target.idle(true, pipeline);
        }
        target.pace(pipeline).map_err(FeedError::Target)?;
        macros.host_mut().quiet(target.resume_at());
        if macros.host().due_timer().is_some() || macros.host_mut().idle_timeout_due() {
            let quiet = macros.host().due_timer().is_none();
            self.feed(pipeline, accessories, macros)
                .run_line_idle(quiet, macros, target)?;
        }
        Ok(())
    }

    /// At the end of the G-code: timers due while the last moves run fire; later ones are
    /// said not to.
    fn run_last_timers<T: FeedTarget>(
        &mut self,
        pipeline: &mut Pipeline,
        accessories: &mut Accessories,
        macros: &mut Macros,
        target: &mut T,
    ) -> Fed<T> {
        if macros.host().pending_timers().is_empty() {
            return Ok(());
        }
        pipeline.flush_lookahead();
        release(pipeline, &mut self.out, target)?;
        let end = pipeline.planned_until();
        macros.host_mut().set_now(end);
        let lines = self.lines as usize;
        self.feed(pipeline, accessories, macros)
            .run_due_timers(lines, Some(end), macros, target)?;
        for (id, due) in macros.host().pending_timers() {
            target.warn(format!(
                "{}: [delayed_gcode {id}] was due {:.1} s after the print's last move: not run",
                self.file.display(),
                due - end
            ));
        }
        Ok(())
    }
}

/// What one command line is planned with.
struct Feed<'a> {
    /// `SET_KINEMATIC_POSITION` is a command (`[force_move]`).
    force_move: bool,
    file: &'a Path,
    pipeline: &'a mut Pipeline,
    accessories: &'a mut Accessories,
    warnings: &'a mut Warnings,
    out: &'a mut Vec<(usize, StepCmd)>,
    /// The feed is idle (see [`FeedState::idle`]).
    idle: &'a mut bool,
    /// `[probe]`'s scripts around probing sessions.
    probe_scripts: ProbeScripts,
    /// A probe script is running (a probing command in it is no new session).
    in_probe_script: bool,
}

impl Feed<'_> {
    /// The first command after an idle spell starts from the MCUs' time then.
    fn wake<T: FeedTarget>(&mut self, target: &mut T) -> Fed<T> {
        if *self.idle {
            *self.idle = false;
            self.pipeline
                .raise_print_time(target.resume_at())
                .map_err(|source| FeedError::Plan {
                    file: self.file.to_path_buf(),
                    source,
                })?;
            target.idle(false, self.pipeline);
        }
        Ok(())
    }

    /// One command line of the feed: a macro call or a planned command, after an idle spell
    /// from the MCUs' time then.
    fn run_line<T: FeedTarget>(
        &mut self,
        line: &GcodeLine,
        macros: &mut Macros,
        homing: &HomingProcedure,
        target: &mut T,
    ) -> Fed<T> {
        self.wake(target)?;
        match &line.cmd {
            Command::Other { name, raw } => macros.host_mut().observe(name, raw),
            _ => macros.host_mut().observe("", ""),
        }
        match line.cmd {
            // `[safe_z_home]` / `[homing_override]` (unless a `[gcode_macro G28]` replaces G28).
            Command::Home { x, y, z } if homing.is_custom() && !macros.is_macro("G28") => {
                let mut ops = FeedHoming {
                    feed: self,
                    macros,
                    target,
                    line_no: line.line_no,
                };
                homing.g28([x, y, z], &mut ops)?;
            }
            _ => {
                if !self.run_macro_or_variable(line, macros, target)? {
                    self.plan_or_tool(line, macros, target)?;
                }
            }
        }
        Ok(())
    }

    /// Plans one command (with the probe's scripts around it when it probes), or runs it as a
    /// command of `[bed_screws]`'s tool when it is one.
    fn plan_or_tool<T: FeedTarget>(
        &mut self,
        line: &GcodeLine,
        macros: &mut Macros,
        target: &mut T,
    ) -> Fed<T> {
        if !self.run_bed_screws(line, macros, target)? {
            self.plan_probing(line, macros, target)?;
        }
        Ok(())
    }

    /// A command of `[bed_screws]`'s tool (`BED_SCREWS_ADJUST`, and `ACCEPT`, `ADJUSTED`,
    /// `ABORT` while it runs: see `planner::gcode::bed_screws`): its moves made as toolhead
    /// moves (as Klipper's manual moves: in the toolhead's coordinates, whatever the G-code
    /// mode and offsets), its prompt said; false for any other command. A move the planner
    /// refuses ends the tool.
    fn run_bed_screws<T: FeedTarget>(
        &mut self,
        line: &GcodeLine,
        macros: &mut Macros,
        target: &mut T,
    ) -> Fed<T, bool> {
        let Command::Other { name, .. } = &line.cmd else {
            return Ok(false);
        };
        let name = name.as_str();
        let Some(tool) = macros.host_mut().bed_screws_mut() else {
            return Ok(false);
        };
        if !tool.handles(name) {
            return Ok(false);
        }
        let (file, line_no) = (self.file, line.line_no);
        let fail = |source: BedScrewsFailure| {
            let cmd = name.to_string();
            FeedError::at(file, line_no, CommandError::BedScrews { cmd, source })
        };
        if !tool.is_active() {
            let homed = self.pipeline.gcode_state().homed();
            if let Some(axis) = homed.iter().position(|h| !h) {
                return Err(fail(BedScrewsFailure::NotHomed(['X', 'Y', 'Z'][axis])));
            }
        }
        let step = tool.run(name).map_err(|e| fail(e.into()))?;
        for m in &step.moves {
            let mut pos = self.pipeline.position();
            for (p, v) in pos.iter_mut().zip(m.xyz) {
                *p = v.unwrap_or(*p);
            }
            if let Err(e) = self.pipeline.home_move(pos, m.speed) {
                if let Some(tool) = macros.host_mut().bed_screws_mut() {
                    tool.abort();
                }
                return Err(fail(e.into()));
            }
            release(self.pipeline, self.out, target)?;
        }
        for text in step.message.iter().flat_map(|m| m.lines()) {
            target.warn(text.to_string());
        }
        Ok(true)
    }

    /// A checked command of a session: its own error is answered and the session goes on; an
    /// error of the target (the MCUs, the hand-off, a stop) ends the session as for any line.
    fn run_checked<T: FeedTarget>(
        &mut self,
        line: Fed<T, GcodeLine>,
        reply: SyncSender<Result<(), LineError>>,
        macros: &mut Macros,
        homing: &HomingProcedure,
        target: &mut T,
    ) -> Fed<T> {
        let mut checked = Checked {
            target,
            failed: false,
        };
        let result = line.and_then(|line| self.run_line(&line, macros, homing, &mut checked));
        let failed = checked.failed;
        // The sender waits for the answer; a sender that gave up is no error.
        let _ = reply.try_send(match &result {
            Ok(()) => Ok(()),
            Err(e) => Err(LineError {
                message: e.to_string(),
                ends_session: failed,
            }),
        });
        match failed {
            true => result,
            false => Ok(()),
        }
    }

    /// Runs the `[delayed_gcode]` timers due at or before `until` (default: now), earliest
    /// first, each script as a macro reported under line `line_no`.
    fn run_due_timers<T: FeedTarget>(
        &mut self,
        line_no: usize,
        until: Option<f64>,
        macros: &mut Macros,
        target: &mut T,
    ) -> Fed<T> {
        loop {
            let host = macros.host();
            let due = match until {
                Some(t) => host.due_before(t),
                None => host.due_timer(),
            };
            let Some(i) = due else {
                return Ok(());
            };
            let name = delayed_macro_name(macros.host().timer_id(i));
            let fired = macros.host_mut().timer_started(i);
            let result = self.run_script(&name, "", line_no, macros, target);
            macros.host_mut().timer_done(i, fired);
            result?;
        }
    }

    /// A quiet session's turn: due timers run, or (`idle_timeout`) the `[idle_timeout]`
    /// script; the lookahead is flushed after them, as after any command of a session.
    fn run_line_idle<T: FeedTarget>(
        &mut self,
        idle_timeout: bool,
        macros: &mut Macros,
        target: &mut T,
    ) -> Fed<T> {
        self.wake(target)?;
        if idle_timeout {
            self.run_script(IDLE_TIMEOUT_MACRO, "", 0, macros, target)?;
        } else {
            self.run_due_timers(0, None, macros, target)?;
        }
        self.pipeline.flush_lookahead();
        release(self.pipeline, self.out, target)?;
        *self.idle = true;
        target.idle(true, self.pipeline);
        Ok(())
    }

    /// `SET_KINEMATIC_POSITION [X=] [Y=] [Z=] [SET_HOMED=xyz] [CLEAR_HOMED=]` (`[force_move]
    /// enable_force_move`): the toolhead is declared at the position, without moving, and the
    /// axes homed or not, as Klipper's force_move does.
    fn set_kinematic_position<T: FeedTarget>(
        &mut self,
        line: &GcodeLine,
        raw: &str,
        target: &mut T,
    ) -> Fed<T> {
        let at = |source| {
            let cmd = "SET_KINEMATIC_POSITION";
            FeedError::at(self.file, line.line_no, CommandError::Param { cmd, source })
        };
        let p = OtherParams::parse(raw).map_err(at)?;
        let mut pos = self.pipeline.position();
        for (i, key) in ["X", "Y", "Z"].into_iter().enumerate() {
            if let Some(v) = p.float(key).map_err(at)? {
                pos[i] = v;
            }
        }
        let set = p.get("SET_HOMED").unwrap_or("xyz").to_ascii_lowercase();
        let clear = p
            .get("CLEAR_HOMED")
            .or_else(|| p.get("CLEAR"))
            .unwrap_or("")
            .to_ascii_lowercase();
        let mut homed = self.pipeline.gcode_state().homed();
        for (i, axis) in ['x', 'y', 'z'].into_iter().enumerate() {
            if set.contains(axis) {
                homed[i] = true;
            }
            if clear.contains(axis) {
                homed[i] = false;
            }
        }
        self.pipeline.set_toolhead_position(pos);
        self.pipeline.set_homed(homed);
        release(self.pipeline, self.out, target)
    }

    /// `FORCE_MOVE STEPPER= DISTANCE= VELOCITY= [ACCEL=]` or `STEPPER_BUZZ STEPPER=`: one
    /// stepper moved on its own (Klipper's `[force_move]`), its steps sent at once.
    fn forced_move<T: FeedTarget>(
        &mut self,
        line: &GcodeLine,
        cmd: &'static str,
        raw: &str,
        target: &mut T,
    ) -> Fed<T> {
        let (file, line_no) = (self.file, line.line_no);
        let at = |source| FeedError::at(file, line_no, source);
        let param = |source| at(CommandError::Param { cmd, source });
        let missing = |key| at(CommandError::Missing { cmd, key });
        let p = OtherParams::parse(raw).map_err(param)?;
        let stepper = p.get("STEPPER").ok_or_else(|| missing("STEPPER"))?;
        let num = |k: &str| p.float(k).map_err(param);
        // Everything planned so far goes out first.
        self.pipeline.flush_lookahead();
        release(self.pipeline, self.out, target)?;
        let done = if cmd == "STEPPER_BUZZ" {
            self.pipeline.stepper_buzz(stepper, self.out)
        } else {
            let distance = num("DISTANCE")?.ok_or_else(|| missing("DISTANCE"))?;
            let velocity = num("VELOCITY")?.ok_or_else(|| missing("VELOCITY"))?;
            let accel = num("ACCEL")?.unwrap_or(0.0);
            self.pipeline
                .force_move(stepper, distance, velocity, accel, self.out)
        };
        done.map_err(|e| at(CommandError::Forced { cmd, source: e.kind }))?;
        if !self.out.is_empty() {
            target.emit(self.out).map_err(FeedError::Target)?;
            self.out.clear();
            target.pace(self.pipeline).map_err(FeedError::Target)?;
        }
        Ok(())
    }

    /// Plans one command and hands on what became final.
    fn plan<T: FeedTarget>(&mut self, line: &GcodeLine, target: &mut T) -> Fed<T> {
        if let Command::Other { name, raw } = &line.cmd {
            if name.as_str() == "SET_KINEMATIC_POSITION" && self.force_move {
                return self.set_kinematic_position(line, raw.as_str(), target);
            }
            // FORCE_MOVE only with `enable_force_move: True` (otherwise an unknown command, as
            // Klipper registers it only then); STEPPER_BUZZ always.
            if name.as_str() == "FORCE_MOVE" && self.force_move {
                return self.forced_move(line, "FORCE_MOVE", raw.as_str(), target);
            }
            if name.as_str() == "STEPPER_BUZZ" {
                return self.forced_move(line, "STEPPER_BUZZ", raw.as_str(), target);
            }
        }
        if plan_line(
            line,
            self.file,
            self.pipeline,
            self.accessories,
            self.warnings,
            target,
        )? {
            release(self.pipeline, self.out, target)?;
        }
        Ok(())
    }

    /// `line` planned; a probing session (see [`ProbeScripts::around`]) between `[probe]`'s
    /// `activate_gcode` and `deactivate_gcode` (run also when the session failed; its error is
    /// the one reported), as Klipper runs them around its probe's use.
    fn plan_probing<T: FeedTarget>(
        &mut self,
        line: &GcodeLine,
        macros: &mut Macros,
        target: &mut T,
    ) -> Fed<T> {
        let (name, home) = match &line.cmd {
            Command::Home { x, y, z } => ("G28", Some([*x, *y, *z])),
            Command::Other { name, .. } => (name.as_str(), None),
            _ => ("", None),
        };
        if self.in_probe_script || !self.probe_scripts.around(name, home) {
            return self.plan(line, target);
        }
        if self.probe_scripts.activate {
            self.probe_script(
                PROBE_ACTIVATE_MACRO,
                "activate_gcode",
                line.line_no,
                macros,
                target,
            )?;
        }
        let r = self.plan(line, target);
        if self.probe_scripts.deactivate {
            let d = self.probe_script(
                PROBE_DEACTIVATE_MACRO,
                "deactivate_gcode",
                line.line_no,
                macros,
                target,
            );
            r?;
            return d;
        }
        r
    }

    /// Runs probe script `name` (`option` of `[probe]`) for line `line_no`: the toolhead must
    /// stay where it is.
    fn probe_script<T: FeedTarget>(
        &mut self,
        name: &str,
        option: &'static str,
        line_no: usize,
        macros: &mut Macros,
        target: &mut T,
    ) -> Fed<T> {
        let before = self.pipeline.position();
        self.in_probe_script = true;
        let r = self.run_script(name, "", line_no, macros, target);
        self.in_probe_script = false;
        r?;
        if self.pipeline.position()[..3] != before[..3] {
            return Err(FeedError::at(
                self.file,
                line_no,
                CommandError::ProbeScriptMoved { option },
            ));
        }
        Ok(())
    }

    /// A `[gcode_macro]` call (run to its end, nested macros rendered when reached, with
    /// Klipper's semantics: see `planner::gcode::macros`), `SET_GCODE_VARIABLE` or a `[respond]`
    /// command; false for any other command. Macro lines are reported under the calling line's
    /// number.
    fn run_macro_or_variable<T: FeedTarget>(
        &mut self,
        line: &GcodeLine,
        macros: &mut Macros,
        target: &mut T,
    ) -> Fed<T, bool> {
        let pipeline = &*self.pipeline;
        let status = || macro_status(pipeline);
        let Some(mut run) = MacroRun::start(line, macros, status, self.file, &mut |m| target.warn(m))? else {
            return Ok(false);
        };
        self.run_to_end(&mut run, macros, target)?;
        Ok(true)
    }

    /// Runs macro `name` called with `rawparams` from line `line_no` to its end (the
    /// `[homing_override]` script).
    fn run_script<T: FeedTarget>(
        &mut self,
        name: &str,
        rawparams: &str,
        line_no: usize,
        macros: &mut Macros,
        target: &mut T,
    ) -> Fed<T> {
        let status = macro_status(self.pipeline);
        let mut run = MacroRun::call(name, rawparams, line_no, macros, &status, self.file, &mut |m| {
            target.warn(m)
        })?;
        self.run_to_end(&mut run, macros, target)
    }

    /// Plans the lines of a started macro run until it ends.
    fn run_to_end<T: FeedTarget>(
        &mut self,
        run: &mut MacroRun,
        macros: &mut Macros,
        target: &mut T,
    ) -> Fed<T> {
        loop {
            let status = macro_status(self.pipeline);
            let Some(sub) = run.next(macros, &status, self.file, &mut |m| target.warn(m))? else {
                return Ok(());
            };
            self.plan_or_tool(&sub, macros, target)
                .map_err(|e| FeedError::InMacro {
                    source: Box::new(e),
                    via: run.via().to_string(),
                })?;
        }
    }
}

/// One feed command run as a print runs it: a macro call's lines pulled one at a time, each
/// macro rendered when its call line is reached (so it sees the state the lines before it
/// left), `SET_GCODE_VARIABLE` and `[respond]`'s commands answered on the way. Used by the
/// print's feed and by `decode --check`, which pulls planned lines as the stream needs them.
pub(crate) struct MacroRun {
    script: Script,
    /// The calling line's number (every line of the run is reported under it).
    line_no: usize,
    /// The macros the last line came through (`OUTER > INNER`).
    via: String,
}

impl MacroRun {
    /// Starts `line` when it is a macro call, `SET_GCODE_VARIABLE` or (with `[respond]`)
    /// `RESPOND`/`M118`; `None` (without allocating) for any other command. `printer` gives
    /// the status objects a macro sees ([`macro_status`]), asked only for a feed command;
    /// messages go to `say`.
    pub(crate) fn start(
        line: &GcodeLine,
        macros: &mut Macros,
        printer: impl FnOnce() -> serde_json::Value,
        file: &Path,
        say: &mut dyn FnMut(String),
    ) -> Result<Option<MacroRun>, MacroRunError> {
        let Some((name, rawparams)) = macro_call(&line.cmd, macros) else {
            return Ok(None);
        };
        let printer = printer();
        MacroRun::call(&name, &rawparams, line.line_no, macros, &printer, file, say).map(Some)
    }

    /// Starts a call of `name` with `rawparams` from line `line_no` (a macro,
    /// `SET_GCODE_VARIABLE` or a `[respond]` command).
    pub(crate) fn call(
        name: &str,
        rawparams: &str,
        line_no: usize,
        macros: &mut Macros,
        printer: &serde_json::Value,
        file: &Path,
        say: &mut dyn FnMut(String),
    ) -> Result<MacroRun, MacroRunError> {
        let mut run = MacroRun {
            script: Script::new(),
            line_no,
            via: String::new(),
        };
        macro_step(name, rawparams, macros, &mut run.script, printer, say).map_err(|source| {
            MacroRunError {
                file: file.to_path_buf(),
                line: line_no,
                via: None,
                source: Box::new(source),
            }
        })?;
        Ok(run)
    }

    /// The macros the last line returned came through, for errors.
    pub(crate) fn via(&self) -> &str {
        &self.via
    }

    /// The next line to plan (`None` once the call has run to its end); nested calls,
    /// variables and `[respond]` commands are run here. `rename_existing` names run the
    /// command the macro replaced.
    pub(crate) fn next(
        &mut self,
        macros: &mut Macros,
        printer: &serde_json::Value,
        file: &Path,
        say: &mut dyn FnMut(String),
    ) -> Result<Option<GcodeLine>, MacroRunError> {
        let at = |via: &str, source: MacroStepError| MacroRunError {
            file: file.to_path_buf(),
            line: self.line_no,
            via: Some(via.to_string()),
            source: Box::new(source),
        };
        while let Some(next) = self.script.next_line() {
            self.via = next.macros.join(" > ");
            let Some((called, rest)) = split_command(&next.text) else {
                continue;
            };
            if macros.is_feed_command(&called) {
                macro_step(&called, rest, macros, &mut self.script, printer, say)
                    .map_err(|e| at(&self.via, e))?;
                continue;
            }
            if called == "M117" {
                macros.host_mut().observe(&called, &next.text);
            }
            let text = match macros.original_of(&called) {
                Some(original) => format!("{original} {rest}"),
                None => next.text,
            };
            match parse_line(self.line_no, text.as_bytes()) {
                Ok(Some(cmd)) => {
                    return Ok(Some(GcodeLine {
                        line_no: self.line_no,
                        cmd,
                    }))
                }
                Ok(None) => continue,
                Err(e) => return Err(at(&self.via, e.into())),
            }
        }
        Ok(None)
    }
}

/// `SET_GCODE_VARIABLE`, a `[respond]` command, or a call of macro `name` (rendered now, its
/// lines pushed on `script`, its `action_respond_info` messages handed to `say`). The error
/// has no location: the caller names the line and the macros it came through.
fn macro_step(
    name: &str,
    rawparams: &str,
    macros: &mut Macros,
    script: &mut Script,
    printer: &serde_json::Value,
    say: &mut dyn FnMut(String),
) -> Result<(), MacroStepError> {
    if name == "SET_GCODE_VARIABLE" {
        return Ok(macros.set_variable(rawparams)?);
    }
    if let Some(prefix) = macros.respond_prefix().filter(|_| is_respond_command(name)) {
        if !macros.is_macro(name) {
            say(respond(prefix, name, rawparams)?);
            return Ok(());
        }
    }
    if macros.host().handles(name) && !macros.is_macro(name) {
        match macros.host_mut().command(name, rawparams)? {
            HostAction::Done => {}
            HostAction::Respond(text) => say(text),
            HostAction::Save { path, text } => {
                std::fs::write(&path, text).map_err(|source| MacroStepError::Save { path, source })?
            }
        }
        return Ok(());
    }
    let said = script.call(macros, name, rawparams, printer)?;
    said.into_iter().for_each(|m| say(format!("{name}: {m}")));
    Ok(())
}

/// The `printer` objects a macro sees: `toolhead` and `gcode_move` positions and the homed
/// axes, and with `[exclude_object]` its objects, as Klipper names them.
pub(crate) fn macro_status(pipeline: &Pipeline) -> serde_json::Value {
    let [x, y, z, e] = pipeline.position();
    let homed = pipeline.gcode_state().homed();
    let homed_axes: String = ["x", "y", "z"]
        .iter()
        .zip(homed)
        .filter(|(_, h)| *h)
        .map(|(a, _)| *a)
        .collect();
    let position = serde_json::json!({"x": x, "y": y, "z": z, "e": e});
    let mut status = serde_json::json!({
        "toolhead": {"position": position.clone(), "homed_axes": homed_axes},
        "gcode_move": {"position": position.clone(), "gcode_position": position},
    });
    if let (Some(objects), Some(map)) = (pipeline.gcode_state().exclude_objects(), status.as_object_mut()) {
        map.insert("exclude_object".to_string(), objects.status());
    }
    status
}

/// The printer a G28 procedure ([`HomingProcedure`]) runs on: the feed's planner, the printer's
/// own G28 (with the MCUs where they home) and the `[homing_override]` script, errors located
/// at the G28's line.
struct FeedHoming<'f, 'a, T> {
    feed: &'f mut Feed<'a>,
    macros: &'f mut Macros,
    target: &'f mut T,
    line_no: usize,
}

impl<T: FeedTarget> HomeOps for FeedHoming<'_, '_, T> {
    type Error = FeedError<T::Error>;

    fn homed(&self) -> [bool; 3] {
        self.feed.pipeline.gcode_state().homed()
    }

    fn position(&self) -> [f64; 4] {
        self.feed.pipeline.position()
    }

    fn set_position(&mut self, pos: [f64; 4], homed: [bool; 3]) {
        self.feed.pipeline.set_toolhead_position(pos);
        self.feed.pipeline.set_homed(homed);
    }

    fn home(&mut self, axes: [bool; 3]) -> Fed<T> {
        let [x, y, z] = axes;
        let line = GcodeLine {
            line_no: self.line_no,
            cmd: Command::Home { x, y, z },
        };
        self.feed.plan_probing(&line, self.macros, self.target)
    }

    fn move_to(&mut self, pos: [f64; 4], speed: f64) -> Fed<T> {
        if let Err(e) = self.feed.pipeline.home_move(pos, speed) {
            return Err(self.located(G28Error::Move(e)));
        }
        release(self.feed.pipeline, self.feed.out, self.target)
    }

    fn run_override(&mut self, rawparams: &str) -> Fed<T> {
        let name = sysconfig::printer::HOMING_OVERRIDE_MACRO;
        self.feed
            .run_script(name, rawparams, self.line_no, self.macros, self.target)
    }

    fn fail(&self, why: ProcedureError) -> FeedError<T::Error> {
        self.located(G28Error::Procedure(why))
    }
}

impl<T: FeedTarget> FeedHoming<'_, '_, T> {
    /// `why`, at the G28's line.
    fn located(&self, why: G28Error) -> FeedError<T::Error> {
        FeedError::at(self.feed.file, self.line_no, CommandError::Homing(why))
    }
}

/// The name and parameters of a command that is a macro call or `SET_GCODE_VARIABLE`:
/// extended and M commands (`START_PRINT BED=60`, `M600`) and G28 (often overridden with
/// `rename_existing`). Other commands return `None` without allocating (the planner thread's
/// steady state stays allocation-free for files without macros).
fn macro_call(cmd: &Command, macros: &Macros) -> Option<(String, String)> {
    match cmd {
        Command::Other { name, raw } => {
            let name = name.as_str();
            if !macros.is_feed_command(name) {
                return None;
            }
            let rest = split_command(raw.as_str()).map(|(_, rest)| rest).unwrap_or("");
            Some((name.to_string(), rest.to_string()))
        }
        Command::Home { x, y, z } if macros.is_macro("G28") => {
            let axes: Vec<&str> = [(*x, "X"), (*y, "Y"), (*z, "Z")]
                .iter()
                .filter(|(on, _)| *on)
                .map(|(_, a)| *a)
                .collect();
            Some(("G28".to_string(), axes.join(" ")))
        }
        _ => None,
    }
}

/// A target that notes whether one of its own calls failed: such an error ends the session,
/// while the command's own errors (parse, planner, macro) only fail that command.
struct Checked<'t, T> {
    target: &'t mut T,
    failed: bool,
}

impl<T> Checked<'_, T> {
    fn note<R, E>(&mut self, r: Result<R, E>) -> Result<R, E> {
        self.failed |= r.is_err();
        r
    }
}

impl<T: FeedTarget> FeedTarget for Checked<'_, T> {
    type Error = T::Error;

    fn emit(&mut self, cmds: &mut Vec<(usize, StepCmd)>) -> Result<(), T::Error> {
        let r = self.target.emit(cmds);
        self.note(r)
    }
    fn pace(&mut self, pipeline: &mut Pipeline) -> Result<(), T::Error> {
        let r = self.target.pace(pipeline);
        self.note(r)
    }
    fn motion(&mut self, pipeline: &mut Pipeline, cmd: &MotionCmd<'_>) -> Result<bool, T::Error> {
        let r = self.target.motion(pipeline, cmd);
        self.note(r)
    }
    fn resume_at(&self) -> f64 {
        self.target.resume_at()
    }
    fn warn(&mut self, text: String) {
        self.target.warn(text);
    }
    fn idle(&mut self, idle: bool, pipeline: &Pipeline) {
        self.target.idle(idle, pipeline);
    }
    // A heater command's error (a target out of range, a fault met while waiting) fails the
    // command; a fault also ends the session at the target's next check.
    fn heat(&mut self, pipeline: &mut Pipeline, cmd: &HeatCmd) -> Result<(), T::Error> {
        self.target.heat(pipeline, cmd)
    }
    fn can_extrude(&self, extruder: &str) -> Result<(), T::Error> {
        self.target.can_extrude(extruder)
    }
}

/// Hands the step commands that became final to the target, then paces.
fn release<T: FeedTarget>(
    pipeline: &mut Pipeline,
    out: &mut Vec<(usize, StepCmd)>,
    target: &mut T,
) -> Fed<T> {
    pipeline.generate(out);
    if !out.is_empty() {
        target.emit(out).map_err(FeedError::Target)?;
        out.clear();
        target.pace(pipeline).map_err(FeedError::Target)?;
    }
    Ok(())
}

/// One G-code command: with the MCUs in the loop (G28 with motion, probing: false) or planned
/// (true: steps may be ready).
fn plan_line<T: FeedTarget>(
    line: &GcodeLine,
    file: &Path,
    pipeline: &mut Pipeline,
    accessories: &mut Accessories,
    warnings: &mut Warnings,
    target: &mut T,
) -> Fed<T, bool> {
    let at = |source| FeedError::at(file, line.line_no, source);
    let refused = |e| at(CommandError::Target(e));
    if let Some(heat) = heat_gcode::parse(&line.cmd) {
        let heat = heat.map_err(|e| at(e.into()))?;
        target.heat(pipeline, &heat).map_err(refused)?;
        return Ok(true);
    }
    // G28 with real motion where the printer can home; otherwise the planner's own G28
    // (which sets the configured endstop positions). The probe and TMC commands likewise.
    if let Some(cmd) = motion_cmd(&line.cmd) {
        let moved = target.motion(pipeline, &cmd).map_err(|source| {
            let cmd = cmd.name().to_string();
            at(CommandError::Motion { cmd, source })
        })?;
        if moved {
            return Ok(false);
        }
    }
    let extrudes = matches!(
        line.cmd,
        Command::Move { e: Some(_), .. } | Command::Arc { e: Some(_), .. }
    );
    let e_before = pipeline.position()[3];
    let applied = pipeline.apply(line).map_err(|source| FeedError::Plan {
        file: file.to_path_buf(),
        source,
    })?;
    if let Applied::Unsupported(name) = &applied {
        warnings.unsupported(file, line.line_no, name, target);
    }
    if let Some(w) = accessories.record(line.line_no, &applied) {
        target.warn(format!("{}: {w}", file.display()));
    }
    if applied == Applied::MotorsOff {
        target.motors_off(pipeline).map_err(refused)?;
    }
    if extrudes && pipeline.position()[3] != e_before {
        let active = pipeline.gcode_state().extruders().active();
        target
            .can_extrude(planner::extruders::EXTRUDER_NAMES[active])
            .map_err(refused)?;
    }
    if let Some(heat) = heat_gcode::of_applied(&applied) {
        target.heat(pipeline, &heat).map_err(refused)?;
    }
    Ok(true)
}

/// The command as one the MCUs must be in the loop for, if it is one.
fn motion_cmd(cmd: &Command) -> Option<MotionCmd<'_>> {
    match cmd {
        Command::Home { x, y, z } => Some(MotionCmd::Home([*x, *y, *z])),
        Command::Other { name, raw } if crate::homing::probe::is_probe_command(name) => {
            Some(MotionCmd::Probe { name, raw })
        }
        Command::Other { name, raw } if crate::tmc::gcode::is_tmc_command(name) => {
            Some(MotionCmd::Tmc { name, raw })
        }
        _ => None,
    }
}
