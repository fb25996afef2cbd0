//! The thread that owns the service's [`Printer`]: opens it (after a failed start, again every
//! [`ServiceOptions::retry_s`] with the reason in the `error` state's message), runs the
//! G-code scripts the API hands it one command at a time, reopens the printer on `RESTART` /
//! `FIRMWARE_RESTART`, and stops motion and closes it when the service quits.

use std::sync::atomic::Ordering;
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender};
use std::sync::Arc;
use std::time::Duration;

use serde_json::Value;

use crate::events::{Event, PrinterState};
use crate::printer::{Printer, PrinterError, PrinterSource};

use super::objects::ConfigFacts;
use super::{
    shutdown_message, ServiceOptions, ServiceState, Shared, HELP_ERROR, MESSAGE_READY, MESSAGE_STARTUP,
};

/// Who asked: the API client and its request id (answered through [`ToApi::Reply`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Asker {
    pub client: u64,
    pub id: Option<Value>,
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
        result: Result<Value, String>,
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
            let _ = to_api.send(ToApi::Reply {
                asker,
                result: Ok(Value::Object(Default::default())),
            });
        }
        let next = match opened {
            Ok((printer, facts)) => serve_printer(printer, facts, shared, jobs, to_api, &mut pending_restart),
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
fn open(opts: &ServiceOptions) -> Result<(Printer, ConfigFacts), String> {
    let (cfg, ini) = match &opts.source {
        PrinterSource::Simulated => (crate::hardware::load_config(None), None),
        PrinterSource::ConfigFile(p) => (crate::hardware::load_config(Some(p)), Some(p.clone())),
        PrinterSource::Config(c) => (Ok((**c).clone()), None),
    };
    let cfg = cfg.map_err(|e| format!("printer config: {e}"))?;
    let facts = ConfigFacts::new(&cfg, ini.as_deref());
    let printer = Printer::open(PrinterSource::Config(Box::new(cfg)), opts.printer.clone())
        .map_err(|e| e.to_string())?;
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
                let _ = to_api.send(ToApi::Reply {
                    asker,
                    result: Err(message.to_string()),
                });
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
) -> Next {
    let handle = printer.handle();
    if let Some(events) = printer.events() {
        let out = to_api.clone();
        let spawned = std::thread::Builder::new()
            .name("serve-events".to_string())
            .spawn(move || forward_events(&events, &out));
        if let Err(e) = spawned {
            eprintln!("cadence serve: G-code output will not be forwarded: {e}");
        }
    }
    let mcus: Vec<String> = printer.status().mcus.into_iter().map(|(n, _)| n).collect();
    shared.set(|p| {
        p.state = ServiceState::Ready;
        p.message = MESSAGE_READY.to_string();
        p.handle = Some(handle.clone());
        p.config = Some(Arc::new(facts));
        p.mcus = mcus;
    });
    let mut shut_down = false;
    let next = loop {
        if shared.quit.load(Ordering::Acquire) {
            // Stop motion: an emergency stop when something moves, else a plain stop.
            if handle.state() == PrinterState::Printing {
                handle.emergency_stop();
            } else {
                handle.stop();
            }
            break Next::Quit;
        }
        match jobs.recv_timeout(Duration::from_millis(100)) {
            Ok(Job::Script { text, asker }) => {
                let (result, restart) = run_script(&printer, &text, shared);
                if let Err(e) = &result {
                    let _ = to_api.send(ToApi::Output(format!("!! {e}")));
                }
                let _ = to_api.send(ToApi::Reply {
                    asker,
                    result: result.map(|()| Value::Object(Default::default())),
                });
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
        if !shut_down {
            if let PrinterState::Shutdown { reason } = handle.state() {
                shut_down = true;
                eprintln!("cadence serve: printer shut down: {reason}");
                let message = shutdown_message(&reason);
                shared.set(|p| {
                    p.state = ServiceState::Shutdown;
                    p.message = message;
                });
            }
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

/// Runs a script's lines in order; the first error ends it. `true` when it asked for a
/// restart (`RESTART` or `FIRMWARE_RESTART`).
fn run_script(printer: &Printer, text: &str, shared: &Shared) -> (Result<(), String>, bool) {
    let (result, restart) = run_lines(printer, text, shared);
    if restart || shared.get().state != ServiceState::Ready {
        return (result, restart);
    }
    // The next script may come any time later: what this one planned moves now.
    match (result, printer.flush()) {
        (Err(e), _) => (Err(e), false),
        (Ok(()), Err(e)) => (Err(e.to_string()), false),
        (Ok(()), Ok(())) => (Ok(()), false),
    }
}

/// The lines of [`run_script`].
fn run_lines(printer: &Printer, text: &str, shared: &Shared) -> (Result<(), String>, bool) {
    for line in text.lines() {
        let word = line.split_whitespace().next().unwrap_or("").to_ascii_uppercase();
        match word.as_str() {
            "RESTART" | "FIRMWARE_RESTART" => return (Ok(()), true),
            "M112" => {
                printer.handle().emergency_stop();
                return (Ok(()), false);
            }
            _ => {}
        }
        let state = shared.get();
        if state.state != ServiceState::Ready {
            return (Err(state.message), false);
        }
        match printer.run_command(line) {
            Ok(()) => {}
            Err(PrinterError::Command { message }) => return (Err(message), false),
            Err(e) => return (Err(e.to_string()), false),
        }
    }
    (Ok(()), false)
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
