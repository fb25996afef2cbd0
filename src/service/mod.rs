//! `cadence serve`: the always-on printer service. One thread owns the [`Printer`]
//! ([`worker`]): it opens it (retrying after a failed start), runs G-code scripts one command
//! at a time (a refused command fails alone, the printer stays ready), reopens it on
//! `RESTART`/`FIRMWARE_RESTART`, and notices a shutdown. Front ends attach over Klipper's API
//! socket ([`api`]: framing in [`framing`], status objects in [`objects`]) and G-code senders
//! over a pseudo-terminal ([`gcode_pty`]). The states and their messages are Klipper's:
//! `startup`, `ready`, `error` (the printer could not be opened), `shutdown` (an MCU shutdown,
//! an emergency stop, an error of the running session).
//!
//! Print jobs run as Klipper's `virtual_sdcard` runs them ([`sdcard`]). Not yet served:
//! heaters.

pub mod api;
pub mod framing;
pub mod gcode_pty;
pub mod objects;
pub mod reply;
pub mod sdcard;
pub mod worker;

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex};

use crate::printer::{PrinterHandle, PrinterOptions, PrinterSource};

/// Klipper's `ready` message.
pub const MESSAGE_READY: &str = "Printer is ready";
/// Klipper's `startup` message (the host software named Cadence).
pub const MESSAGE_STARTUP: &str =
    "Printer is not ready\nThe Cadence host software is attempting to connect.  Please\nretry in a few moments.";
/// What follows a shutdown's reason (Klipper's wording).
pub const HELP_SHUTDOWN: &str = "Once the underlying issue is corrected, use the \"FIRMWARE_RESTART\" command to reset the firmware, reload the config, and restart the host software.\nPrinter is shutdown";
/// What follows the reason the printer could not start (Klipper's wording).
pub const HELP_ERROR: &str = "Once the underlying issue is corrected, use the \"RESTART\"\ncommand to reload the config and restart the host software.\nPrinter is halted";

/// The service's state, as Klipper's `webhooks.state` names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ServiceState {
    Startup,
    Ready,
    Error,
    Shutdown,
}

impl ServiceState {
    pub fn name(self) -> &'static str {
        match self {
            ServiceState::Startup => "startup",
            ServiceState::Ready => "ready",
            ServiceState::Error => "error",
            ServiceState::Shutdown => "shutdown",
        }
    }
}

/// What the worker publishes for the API: the state, its message, the open printer's handle
/// and its configuration facts.
#[derive(Debug, Clone)]
pub struct Published {
    pub state: ServiceState,
    pub message: String,
    pub handle: Option<PrinterHandle>,
    pub config: Option<Arc<objects::ConfigFacts>>,
    pub mcus: Vec<String>,
    /// The print job's figures.
    pub print: sdcard::PrintInfo,
}

/// State shared between the worker and the API.
#[derive(Debug)]
pub struct Shared {
    published: Mutex<Published>,
    /// Set by SIGTERM/SIGINT (or a test): the service stops motion and exits.
    pub quit: Arc<AtomicBool>,
}

impl Shared {
    pub fn new(quit: Arc<AtomicBool>) -> Shared {
        Shared {
            published: Mutex::new(Published {
                state: ServiceState::Startup,
                message: MESSAGE_STARTUP.to_string(),
                handle: None,
                config: None,
                mcus: Vec::new(),
                print: sdcard::PrintInfo::default(),
            }),
            quit,
        }
    }

    /// The state now; a printer whose session ended since the worker last looked is reported
    /// shut down with its reason.
    pub fn get(&self) -> Published {
        let mut p = match self.published.lock() {
            Ok(g) => g.clone(),
            Err(e) => e.into_inner().clone(),
        };
        if p.state == ServiceState::Ready {
            if let Some(crate::events::PrinterState::Shutdown { reason }) =
                p.handle.as_ref().map(|h| h.state())
            {
                p.state = ServiceState::Shutdown;
                p.message = shutdown_message(&reason);
            }
        }
        p
    }

    fn set(&self, f: impl FnOnce(&mut Published)) {
        match self.published.lock() {
            Ok(mut g) => f(&mut g),
            Err(e) => f(&mut e.into_inner()),
        }
    }
}

/// A shutdown's state message.
pub fn shutdown_message(reason: &str) -> String {
    format!("{reason}\n{HELP_SHUTDOWN}")
}

/// How the service runs.
#[derive(Debug, Clone)]
pub struct ServiceOptions {
    pub source: PrinterSource,
    /// The config file named in `info` (`None`: the built-in simulated printer).
    pub config_file: Option<PathBuf>,
    pub printer: PrinterOptions,
    /// Klipper's API socket (`-a`).
    pub api_socket: Option<PathBuf>,
    /// The G-code pseudo-terminal's link (`-I`).
    pub gcode_pty: Option<PathBuf>,
    /// The virtual sdcard's directory (else `[virtual_sdcard] path` of the config).
    pub virtual_sdcard: Option<PathBuf>,
    /// Seconds between attempts to open a printer that failed to start.
    pub retry_s: f64,
}

/// Why the service could not run.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// The API socket could not be bound.
    #[error(transparent)]
    Api(#[from] api::ApiError),
    /// The G-code terminal could not be set up.
    #[error(transparent)]
    Pty(#[from] gcode_pty::PtyError),
    /// The G-code terminal's descriptor could not be duplicated.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// A thread of the service did not start (`what`: which one).
    #[error("cannot start the {what}: {source}")]
    Thread {
        what: &'static str,
        #[source]
        source: std::io::Error,
    },
    /// The printer thread panicked.
    #[error("the printer thread panicked")]
    Panicked,
}

/// The CLI's view (the message as shown).
impl From<ServiceError> for String {
    fn from(e: ServiceError) -> String {
        e.to_string()
    }
}

/// Runs the service until `quit` is set (SIGTERM/SIGINT in `cadence serve`): the worker on
/// its own thread, the API server (when a socket is given) on this one. Stops motion and
/// closes the printer before returning.
pub fn run(opts: &ServiceOptions, quit: Arc<AtomicBool>, api_group: Option<u32>) -> Result<(), ServiceError> {
    let listener = match &opts.api_socket {
        Some(path) => Some(api::bind(path, api_group)?),
        None => None,
    };
    let shared = Arc::new(Shared::new(quit));
    let (jobs_tx, jobs_rx) = std::sync::mpsc::channel();
    let (to_api_tx, to_api_rx) = std::sync::mpsc::channel();
    if let Some(path) = &opts.gcode_pty {
        gcode_pty::GcodePty::open(path)?.serve(jobs_tx.clone(), Arc::clone(&shared))?;
    }
    let shared_ref = &*shared;
    std::thread::scope(|scope| {
        let worker = std::thread::Builder::new()
            .name("serve-printer".to_string())
            .spawn_scoped(scope, move || worker::run(opts, shared_ref, &jobs_rx, &to_api_tx))
            .map_err(|source| ServiceError::Thread {
                what: "printer thread",
                source,
            })?;
        match &listener {
            Some(l) => api::serve(
                l,
                &shared,
                &jobs_tx,
                &to_api_rx,
                env!("CARGO_PKG_VERSION"),
                opts.config_file.as_deref(),
                opts.printer.log_file.as_deref(),
            ),
            None => {
                while !shared.quit.load(std::sync::atomic::Ordering::Acquire) {
                    // Nobody reads the output without a socket.
                    while to_api_rx.try_recv().is_ok() {}
                    std::thread::sleep(std::time::Duration::from_millis(50));
                }
            }
        }
        drop(jobs_tx);
        worker.join().map_err(|_| ServiceError::Panicked)
    })?;
    for path in opts.api_socket.iter().chain(&opts.gcode_pty) {
        let _ = std::fs::remove_file(path);
    }
    Ok(())
}
