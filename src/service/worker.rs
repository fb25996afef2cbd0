//! The thread that owns the service's [`Printer`]: opens it (after a failed start, again every
//! [`ServiceOptions::retry_s`] with the reason in the `error` state's message), runs the
//! G-code scripts the API hands it one command at a time, reopens the printer on `RESTART` /
//! `FIRMWARE_RESTART` and after `SAVE_CONFIG` wrote the config, and stops motion and closes it when the service quits.

use std::sync::atomic::Ordering;
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, TryRecvError};
use std::sync::Arc;
use std::time::Duration;

use serde_json::Value;

use crate::events::{Event, PrinterState};
use crate::printer::{Printer, PrinterSource};

use super::objects::ConfigFacts;
use super::reply::ReplyError;
use super::sdcard::{PrintState, SdCard, SdError};
use super::{
    shutdown_message, ServiceOptions, ServiceState, Shared, HELP_ERROR, MESSAGE_READY, MESSAGE_STARTUP,
};

/// Who asked: the API client and its request id (answered through [`ToApi::Reply`]), or
/// another front end (the G-code pseudo-terminal) waiting on its own channel.
#[derive(Debug, Clone)]
pub struct Asker {
    pub client: u64,
    pub id: Option<Value>,
    pub via: Option<Sender<Result<Value, ReplyError>>>,
}

/// Answers `asker`.
fn answer(to_api: &Sender<ToApi>, asker: Asker, result: Result<Value, ReplyError>) {
    match &asker.via {
        Some(tx) => {
            let _ = tx.send(result);
        }
        None => {
            let _ = to_api.send(ToApi::Reply { asker, result });
        }
    }
}

/// What the API asks of the worker.
#[derive(Debug)]
pub enum Job {
    /// Run a G-code script (lines in order; the first refused one ends it with its error).
    Script { text: String, asker: Asker },
    /// Close the printer and open it again (`gcode/restart`, `gcode/firmware_restart`).
    Restart { asker: Asker },
}

/// What the worker tells the API.
#[derive(Debug)]
pub enum ToApi {
    /// The answer to a request.
    Reply {
        asker: Asker,
        result: Result<Value, ReplyError>,
    },
    /// A line of G-code output (`notify_gcode_response`).
    Output(String),
}

/// How one opened printer's service ended.
enum Next {
    Reopen,
    Quit,
}

/// Runs until the service quits (the shared quit flag, or the API gone).
pub fn run(opts: &ServiceOptions, shared: &Shared, jobs: &Receiver<Job>, to_api: &Sender<ToApi>) {
    let mut pending_restart: Option<Asker> = None;
    loop {
        if shared.quit.load(Ordering::Acquire) {
            return;
        }
        shared.set(|p| {
            p.state = ServiceState::Startup;
            p.message = MESSAGE_STARTUP.to_string();
            p.handle = None;
        });
        let opened = open(opts);
        if let Some(asker) = pending_restart.take() {
            answer(to_api, asker, Ok(Value::Object(Default::default())));
        }
        let next = match opened {
            Ok((printer, facts)) => serve_printer(
                printer,
                facts,
                shared,
                jobs,
                to_api,
                &mut pending_restart,
                opts.virtual_sdcard.clone(),
            ),
            Err(why) => {
                eprintln!("cadence serve: the printer did not start: {why}");
                let message = format!("{why}\n{HELP_ERROR}");
                shared.set(|p| {
                    p.state = ServiceState::Error;
                    p.message = message.clone();
                });
                wait_failed(opts, shared, jobs, to_api, &message, &mut pending_restart)
            }
        };
        if let Next::Quit = next {
            return;
        }
    }
}

/// Loads the config and opens the printer.
fn open(opts: &ServiceOptions) -> Result<(Printer, ConfigFacts), crate::printer::OpenError> {
    let (cfg, ini) = match &opts.source {
        PrinterSource::Simulated => (crate::hardware::load_config(None), None),
        PrinterSource::ConfigFile(p) => (crate::hardware::load_config(Some(p)), Some(p.clone())),
        PrinterSource::Config(c) => (Ok((**c).clone()), None),
    };
    let cfg = cfg?;
    let facts = ConfigFacts::new(&cfg, ini.as_deref());
    let printer = Printer::open(PrinterSource::Config(Box::new(cfg)), opts.printer.clone())?;
    Ok((printer, facts))
}

/// The printer did not start: answer scripts with the reason, retry after a while or at once
/// on a restart request.
fn wait_failed(
    opts: &ServiceOptions,
    shared: &Shared,
    jobs: &Receiver<Job>,
    to_api: &Sender<ToApi>,
    message: &str,
    pending_restart: &mut Option<Asker>,
) -> Next {
    let until = std::time::Instant::now() + Duration::from_secs_f64(opts.retry_s.max(0.1));
    loop {
        if shared.quit.load(Ordering::Acquire) {
            return Next::Quit;
        }
        let left = until.saturating_duration_since(std::time::Instant::now());
        if left.is_zero() {
            return Next::Reopen;
        }
        match jobs.recv_timeout(left.min(Duration::from_millis(100))) {
            Ok(Job::Script { asker, .. }) => {
                let message = message.to_string();
                answer(to_api, asker, Err(ReplyError::NotReady { message }));
            }
            Ok(Job::Restart { asker }) => {
                *pending_restart = Some(asker);
                return Next::Reopen;
            }
            Err(RecvTimeoutError::Timeout) => {}
            Err(RecvTimeoutError::Disconnected) => return Next::Quit,
        }
    }
}

/// Serves one opened printer until it is restarted or the service quits.
fn serve_printer(
    mut printer: Printer,
    facts: ConfigFacts,
    shared: &Shared,
    jobs: &Receiver<Job>,
    to_api: &Sender<ToApi>,
    pending_restart: &mut Option<Asker>,
    sdcard_dir: Option<std::path::PathBuf>,
) -> Next {
    let handle = printer.handle();
    spawn_forwarder(&mut printer, to_api);
    let mcus: Vec<String> = printer.status().mcus.into_iter().map(|(n, _)| n).collect();
    let mut sd = SdCard::new(sdcard_dir.or_else(|| facts.sdcard.clone()));
    shared.set(|p| {
        p.state = ServiceState::Ready;
        p.message = MESSAGE_READY.to_string();
        p.handle = Some(handle.clone());
        p.config = Some(Arc::new(facts));
        p.mcus = mcus;
        p.print = sd.info.clone();
    });
    let mut ctx = Ctx {
        printer: &printer,
        sd: &mut sd,
        out: to_api,
        shared,
    };
    let mut shut_down = false;
    let next = loop {
        if shared.quit.load(Ordering::Acquire) {
            // Stop motion: an emergency stop when something moves, else a plain stop.
            if handle.state() == PrinterState::Printing || ctx.sd.info.is_active() {
                handle.emergency_stop();
            } else {
                handle.stop();
            }
            break Next::Quit;
        }
        // While a file prints, requests are taken between its lines.
        let job = if ctx.sd.info.is_active() {
            match jobs.try_recv() {
                Ok(job) => Ok(job),
                Err(TryRecvError::Empty) => Err(RecvTimeoutError::Timeout),
                Err(TryRecvError::Disconnected) => Err(RecvTimeoutError::Disconnected),
            }
        } else {
            jobs.recv_timeout(Duration::from_millis(100))
        };
        match job {
            Ok(Job::Script { text, asker }) => {
                let (result, restart) = ctx.run_script(&text);
                if let Err(e) = &result {
                    ctx.say(format!("!! {e}"));
                }
                answer(to_api, asker, result.map(|()| Value::Object(Default::default())));
                if restart {
                    break Next::Reopen;
                }
            }
            Ok(Job::Restart { asker }) => {
                *pending_restart = Some(asker);
                break Next::Reopen;
            }
            Err(RecvTimeoutError::Timeout) => {}
            Err(RecvTimeoutError::Disconnected) => break Next::Quit,
        }
        // What a request changed shows at once (a turn of the print may take a while).
        shared.set(|p| p.print = ctx.sd.info.clone());
        if ctx.sd.info.is_active() {
            if let Some(restart) = ctx.print_some() {
                if restart {
                    break Next::Reopen;
                }
            }
        }
        shared.set(|p| p.print = ctx.sd.info.clone());
        if !shut_down {
            shut_down = ctx.note_shutdown(handle.state());
        }
    };
    shared.set(|p| p.handle = None);
    match printer.close() {
        Ok(report) => {
            for line in report.rt_report {
                eprintln!("cadence serve: {line}");
            }
        }
        Err(e) => eprintln!("cadence serve: printer closed: {}", e.reason),
    }
    next
}

/// The printer's messages forwarded as G-code output by a thread of their own.
fn spawn_forwarder(printer: &mut Printer, to_api: &Sender<ToApi>) {
    if let Some(events) = printer.events() {
        let out = to_api.clone();
        let spawned = std::thread::Builder::new()
            .name("serve-events".to_string())
            .spawn(move || forward_events(&events, &out));
        if let Err(e) = spawned {
            eprintln!("cadence serve: G-code output will not be forwarded: {e}");
        }
    }
}

/// What a command line runs with: the printer, the sdcard, the G-code output.
struct Ctx<'a> {
    printer: &'a Printer,
    sd: &'a mut SdCard,
    out: &'a Sender<ToApi>,
    shared: &'a Shared,
}

/// Lines of a printing file run per turn of the worker's loop at most (requests are taken and
/// the status published between turns)...
const LINES_PER_TURN: usize = 64;
/// ...and the time a turn may take (a line waits while the planner's buffer is full).
const TURN: Duration = Duration::from_millis(50);

impl Ctx<'_> {
    /// A printer in `state` that shut down: the print ends in error and the service is in
    /// `shutdown` with the reason; true once that happened.
    fn note_shutdown(&mut self, state: PrinterState) -> bool {
        let PrinterState::Shutdown { reason } = state else {
            return false;
        };
        eprintln!("cadence serve: printer shut down: {reason}");
        if self.sd.info.state == PrintState::Printing || self.sd.info.state == PrintState::Paused {
            self.sd.end(PrintState::Error, &reason);
        }
        let message = shutdown_message(&reason);
        let print = self.sd.info.clone();
        self.shared.set(|p| {
            p.state = ServiceState::Shutdown;
            p.message = message;
            p.print = print;
        });
        true
    }

    /// A line of G-code output.
    fn say(&self, line: String) {
        let _ = self.out.send(ToApi::Output(line));
    }

    /// Runs a script's lines in order; the first error ends it. `true` when it asked for a
    /// restart (`RESTART` or `FIRMWARE_RESTART`).
    fn run_script(&mut self, text: &str) -> (Result<(), ReplyError>, bool) {
        for line in text.lines() {
            match self.run_line(line) {
                Ok(false) => {}
                Ok(true) => return (Ok(()), true),
                Err(e) => return (Err(e), false),
            }
        }
        // The next script may come any time later: what this one planned moves now (a
        // printing file goes on instead).
        if self.shared.get().state != ServiceState::Ready || self.sd.info.is_active() {
            return (Ok(()), false);
        }
        (self.printer.flush().map_err(ReplyError::from), false)
    }

    /// Up to [`LINES_PER_TURN`] lines of the printing file (or [`TURN`] of them); `Some(true)` when one asked for a
    /// restart. A failed line ends the print in `error` with its message.
    fn print_some(&mut self) -> Option<bool> {
        let started = std::time::Instant::now();
        for _ in 0..LINES_PER_TURN {
            if started.elapsed() > TURN {
                return None;
            }
            let line = match self.sd.next_line() {
                None => {
                    if self.sd.info.is_active() {
                        let flushed = self.printer.flush();
                        match flushed {
                            Ok(()) => {
                                self.sd.end(PrintState::Complete, "");
                                self.say("Done printing file".into());
                            }
                            Err(e) => self.sd.end(PrintState::Error, &e.to_string()),
                        }
                    }
                    return None;
                }
                Some(Err(e)) => {
                    let e = e.to_string();
                    self.say(format!("!! {e}"));
                    self.sd.end(PrintState::Error, &e);
                    return None;
                }
                Some(Ok(line)) => line.to_string(),
            };
            match self.run_line(&line) {
                Ok(false) => {}
                Ok(true) => return Some(true),
                Err(e) => {
                    let e = e.to_string();
                    self.say(format!("!! {e}"));
                    self.sd.end(PrintState::Error, &e);
                    return None;
                }
            }
            if !self.sd.info.is_active() {
                return None;
            }
        }
        None
    }

    /// One command: the service's own (restarts, M112, the sdcard and print commands, M73,
    /// M117) or the printer's. `Ok(true)`: restart the printer.
    fn run_line(&mut self, line: &str) -> Result<bool, ReplyError> {
        let code = line.split(';').next().unwrap_or("").trim();
        let (word, rest) = match code.split_once(char::is_whitespace) {
            Some((w, r)) => (w.to_ascii_uppercase(), r.trim()),
            None => (code.to_ascii_uppercase(), ""),
        };
        match word.as_str() {
            "RESTART" | "FIRMWARE_RESTART" => return Ok(true),
            "SAVE_CONFIG" => {
                // The printer writes its config file; then it restarts to read it, as
                // Klipper's SAVE_CONFIG does.
                return self
                    .printer
                    .run_command(line)
                    .map(|()| true)
                    .map_err(ReplyError::from);
            }
            "M112" => {
                self.printer.handle().emergency_stop();
                return Ok(false);
            }
            "SDCARD_PRINT_FILE" => {
                let name = param(rest, "FILENAME").ok_or(ReplyError::MissingArgument("FILENAME"))?;
                let opened = self.sd.load(&name)?;
                self.say(opened);
                self.sd.start()?;
                return Ok(false);
            }
            "M23" => {
                let opened = self.sd.load(rest)?;
                self.say(opened);
                self.say("File selected".into());
                return Ok(false);
            }
            "M24" => return Ok(self.sd.start().map(|()| false)?),
            "RESUME" => {
                if self.sd.info.state != PrintState::Paused {
                    return Err(ReplyError::NotPaused);
                }
                return Ok(self.sd.start().map(|()| false)?);
            }
            "M25" | "PAUSE" => {
                self.sd.pause()?;
                // What was planned moves; the next line starts from the MCUs' time then.
                self.printer.flush()?;
                return Ok(false);
            }
            "CANCEL_PRINT" => {
                if matches!(self.sd.info.state, PrintState::Printing | PrintState::Paused) {
                    self.sd.end(PrintState::Cancelled, "");
                }
                self.printer.flush()?;
                return Ok(false);
            }
            "SDCARD_RESET_FILE" => {
                if self.sd.info.is_active() {
                    return Err(SdError::Busy.into());
                }
                self.sd.end(PrintState::Standby, "");
                return Ok(false);
            }
            "M26" => {
                let pos = param(rest, "S")
                    .and_then(|v| v.parse::<u64>().ok())
                    .ok_or(ReplyError::M26Position)?;
                return Ok(self.sd.set_position(pos).map(|()| false)?);
            }
            "M27" => {
                self.say(self.sd.report());
                return Ok(false);
            }
            "M73" => {
                if let Some(p) = param(rest, "P").and_then(|v| v.parse::<f64>().ok()) {
                    self.sd.info.m73_progress = Some((p / 100.0).clamp(0.0, 1.0));
                }
                return Ok(false);
            }
            "M117" => {
                // The message as written (after the command word), comments included.
                let text = line.trim().get(4..).unwrap_or("").trim();
                self.sd.info.display_message = (!text.is_empty()).then(|| text.to_string());
                return Ok(false);
            }
            _ => {}
        }
        let state = self.shared.get();
        if state.state != ServiceState::Ready {
            return Err(ReplyError::NotReady {
                message: state.message,
            });
        }
        self.printer.run_command(line)?;
        Ok(false)
    }
}

/// A `NAME=value` parameter of an extended command (`FILENAME="a b.gcode"`), or a classic
/// one (`S100`, `P50`); names are case-insensitive.
fn param(rest: &str, name: &str) -> Option<String> {
    let upper = rest.to_ascii_uppercase();
    if name.len() > 1 {
        let key = format!("{name}=");
        let at = upper.find(&key)? + key.len();
        let value = &rest[at..];
        return Some(match value.strip_prefix('"') {
            Some(quoted) => quoted.split('"').next().unwrap_or("").to_string(),
            None => value.split_whitespace().next().unwrap_or("").to_string(),
        });
    }
    rest.split_whitespace()
        .find(|w| w.to_ascii_uppercase().starts_with(name))
        .map(|w| w[name.len()..].to_string())
}

/// Hands the printer's messages to the API as G-code output, Klipper-style: `// ` for
/// information, `!! ` for a shutdown.
fn forward_events(events: &Receiver<Event>, out: &Sender<ToApi>) {
    for event in events {
        let line = match event {
            Event::Response(s) => s,
            Event::Warning(s) => format!("// {s}"),
            Event::State(PrinterState::Shutdown { reason }) => format!("!! {reason}"),
            Event::State(_) | Event::Homed(_) => continue,
        };
        if out.send(ToApi::Output(line)).is_err() {
            return;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::param;

    #[test]
    fn parameters_of_extended_and_classic_commands() {
        assert_eq!(
            param("FILENAME=\"my print.gcode\"", "FILENAME").as_deref(),
            Some("my print.gcode")
        );
        assert_eq!(
            param("filename=a.gcode X=1", "FILENAME").as_deref(),
            Some("a.gcode")
        );
        assert_eq!(param("S1234", "S").as_deref(), Some("1234"));
        assert_eq!(param("P50 R10", "P").as_deref(), Some("50"));
        assert_eq!(param("X=1", "FILENAME"), None);
    }
}
