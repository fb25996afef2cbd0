//! The G-code pseudo-terminal (`cadence serve -I PATH`, like Klipper's `/tmp/printer`): a pty
//! whose other end is linked at PATH, for OctoPrint-style senders. Each line is run as a
//! script by the worker; the answer is `ok`, after `!! message` when the command failed. The
//! service keeps the terminal's other end open too, so a sender may close and reopen it; the
//! link is removed when the service stops.

use std::fs::File;
use std::io::{BufRead, BufReader, Write};
use std::os::fd::{AsRawFd, OwnedFd};
use std::path::Path;
use std::sync::atomic::Ordering;
use std::sync::mpsc::{self, Sender};
use std::sync::Arc;

use nix::sys::termios::{cfmakeraw, tcgetattr, tcsetattr, SetArg};

use super::worker::{Asker, Job};
use super::Shared;

/// Why the G-code terminal could not be set up (`what`: the step that failed).
#[derive(Debug, thiserror::Error)]
#[error("G-code terminal {}: {what}: {why}", .path.display())]
pub struct PtyError {
    pub path: std::path::PathBuf,
    pub what: &'static str,
    #[source]
    pub why: PtyFailure,
}

/// What failed under a [`PtyError`].
#[derive(Debug, thiserror::Error)]
pub enum PtyFailure {
    /// A pty or termios call.
    #[error(transparent)]
    Os(#[from] nix::Error),
    /// A file-system call.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// Something that is not a link is in the way.
    #[error("refusing to replace it")]
    NotALink,
}

/// An open G-code terminal: the link at `path` names its other end.
#[derive(Debug)]
pub struct GcodePty {
    master: OwnedFd,
    /// Held open so the master never sees a hang-up when a sender closes its end.
    _slave: OwnedFd,
}

impl GcodePty {
    /// Opens a raw pty and links `path` to its other end (replacing an old link).
    pub fn open(path: &Path) -> Result<GcodePty, PtyError> {
        let err = |what: &'static str| {
            move |why: PtyFailure| PtyError {
                path: path.to_path_buf(),
                what,
                why,
            }
        };
        let pty = nix::pty::openpty(None, None).map_err(|e| err("cannot open a pty")(e.into()))?;
        let mut t = tcgetattr(&pty.slave).map_err(|e| err("termios")(e.into()))?;
        cfmakeraw(&mut t);
        tcsetattr(&pty.slave, SetArg::TCSANOW, &t).map_err(|e| err("termios")(e.into()))?;
        let name = std::fs::read_link(format!("/proc/self/fd/{}", pty.slave.as_raw_fd()))
            .map_err(|e| err("cannot name the pty")(e.into()))?;
        if let Ok(meta) = std::fs::symlink_metadata(path) {
            if !meta.file_type().is_symlink() {
                return Err(err("exists and is not a link")(PtyFailure::NotALink));
            }
            std::fs::remove_file(path).map_err(|e| err("cannot remove the old link")(e.into()))?;
        }
        std::os::unix::fs::symlink(&name, path).map_err(|e| err("cannot link it")(e.into()))?;
        Ok(GcodePty {
            master: pty.master,
            _slave: pty.slave,
        })
    }

    /// Serves the terminal on a thread of its own until the service quits (the thread ends
    /// with the process).
    pub fn serve(self, jobs: Sender<Job>, shared: Arc<Shared>) -> Result<(), super::ServiceError> {
        let reader = File::from(self.master.try_clone()?);
        let writer = File::from(self.master.try_clone()?);
        std::thread::Builder::new()
            .name("serve-pty".to_string())
            .spawn(move || {
                let _keep = self;
                serve_lines(BufReader::new(reader), writer, &jobs, &shared);
            })
            .map(|_| ())
            .map_err(|source| super::ServiceError::Thread {
                what: "G-code terminal thread",
                source,
            })
    }
}

/// Each line → a script → `ok` (after `!! message` on an error).
fn serve_lines(reader: impl BufRead, mut writer: impl Write, jobs: &Sender<Job>, shared: &Shared) {
    for line in reader.split(b'\n') {
        if shared.quit.load(Ordering::Acquire) {
            return;
        }
        let Ok(line) = line else {
            return;
        };
        let text = String::from_utf8_lossy(&line).trim().to_string();
        let reply = if text.is_empty() {
            Ok(())
        } else {
            let (tx, rx) = mpsc::channel();
            let asker = Asker {
                client: 0,
                id: None,
                via: Some(tx),
            };
            if jobs.send(Job::Script { text, asker }).is_err() {
                return;
            }
            match rx.recv() {
                Ok(r) => r.map(|_| ()),
                Err(_) => return,
            }
        };
        let out = match reply {
            Ok(()) => "ok\n".to_string(),
            Err(e) => format!("!! {}\nok\n", e.to_string().lines().next().unwrap_or("")),
        };
        if writer.write_all(out.as_bytes()).is_err() {
            return;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::AtomicBool;

    #[test]
    fn lines_are_answered_ok_or_with_the_error() {
        let (jobs_tx, jobs_rx) = mpsc::channel::<Job>();
        let worker = std::thread::spawn(move || {
            for job in jobs_rx {
                if let Job::Script { text, asker } = job {
                    let r = if text == "BAD" {
                        let message = "Unknown command:\"BAD\"\nmore".to_string();
                        Err(crate::printer::PrinterError::Command { message }.into())
                    } else {
                        Ok(serde_json::json!({}))
                    };
                    asker.via.expect("a channel").send(r).expect("answer");
                }
            }
        });
        let shared = Shared::new(Arc::new(AtomicBool::new(false)));
        let mut out = Vec::new();
        serve_lines(&b"G28\n\nBAD\nG1 X1\n"[..], &mut out, &jobs_tx, &shared);
        drop(jobs_tx);
        worker.join().expect("worker");
        assert_eq!(
            String::from_utf8(out).unwrap(),
            "ok\nok\n!! Unknown command:\"BAD\"\nok\nok\n"
        );
    }
}
