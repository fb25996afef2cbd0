//! A tty or pseudo-terminal opened by path (the simulator's pty slave, or any tty whose speed is
//! already set), in raw mode, with non-blocking reads bounded by `ppoll`.
//!
//! Hang-up: when the other side of a pty closes, `ppoll` reports `POLLHUP` and `read` fails with
//! `EIO`; both become `UnexpectedEof`. A write that would block is retried after `ppoll` for
//! `POLLOUT`, for at most [`WRITE_TIMEOUT`] in total.

use std::io;
use std::os::fd::{AsFd, OwnedFd};
use std::path::Path;
use std::time::{Duration, Instant};

use nix::errno::Errno;
use nix::fcntl::{fcntl, FcntlArg, OFlag};
use nix::poll::{ppoll, PollFd, PollFlags};
use nix::sys::stat::Mode;
use nix::sys::termios::{cfmakeraw, tcgetattr, tcsetattr, SetArg};
use nix::sys::time::TimeSpec;

use super::{Transport, Wake};

/// Longest a `write_all` waits for the peer to drain its input.
pub const WRITE_TIMEOUT: Duration = Duration::from_secs(1);

/// A raw-mode tty/pty file descriptor.
#[derive(Debug)]
pub struct PtyTransport {
    fd: OwnedFd,
    name: String,
}

impl PtyTransport {
    /// Opens `path` (e.g. the simulator's `/dev/pts/N`) read-write, raw, non-blocking.
    pub fn open(path: impl AsRef<Path>) -> io::Result<PtyTransport> {
        let path = path.as_ref();
        let fd = nix::fcntl::open(
            path,
            OFlag::O_RDWR | OFlag::O_NOCTTY | OFlag::O_NONBLOCK | OFlag::O_CLOEXEC,
            Mode::empty(),
        )
        .map_err(|e| io::Error::new(io::Error::from(e).kind(), format!("open {}: {e}", path.display())))?;
        PtyTransport::from_fd(fd, &format!("pty {}", path.display()))
    }

    /// Wraps an open tty descriptor (e.g. a pty master in a test), making it raw and
    /// non-blocking; `name` is what [`Transport::describe`] reports.
    pub fn from_fd(fd: OwnedFd, name: &str) -> io::Result<PtyTransport> {
        let flags = OFlag::from_bits_truncate(fcntl(&fd, FcntlArg::F_GETFL)?);
        fcntl(&fd, FcntlArg::F_SETFL(flags | OFlag::O_NONBLOCK))?;
        let mut tio = tcgetattr(&fd)?;
        cfmakeraw(&mut tio);
        tcsetattr(&fd, SetArg::TCSANOW, &tio)?;
        Ok(PtyTransport {
            fd,
            name: name.to_owned(),
        })
    }

    /// Waits up to `timeout` for `events`; returns the reported events (empty on timeout).
    fn wait(&self, events: PollFlags, timeout: Duration) -> io::Result<PollFlags> {
        self.wait_or_wake(events, timeout, None)
    }

    /// Like `wait`, but also returns (with empty events) once `wake` is readable; drains it.
    fn wait_or_wake(
        &self,
        events: PollFlags,
        timeout: Duration,
        wake: Option<&Wake>,
    ) -> io::Result<PollFlags> {
        let tty = PollFd::new(self.fd.as_fd(), events);
        let ts = TimeSpec::from_duration(timeout);
        let (n, tty_ev, woke) = match wake {
            None => {
                let mut fds = [tty];
                let n = ppoll(&mut fds, Some(ts), None);
                (n, fds[0].revents(), false)
            }
            Some(w) => {
                let mut fds = [tty, PollFd::new(w.fd(), PollFlags::POLLIN)];
                let n = ppoll(&mut fds, Some(ts), None);
                let woke = fds[1].revents().is_some_and(|e| !e.is_empty());
                (n, fds[0].revents(), woke)
            }
        };
        if woke {
            if let Some(w) = wake {
                w.drain();
            }
        }
        match n {
            Ok(0) | Err(Errno::EINTR) => Ok(PollFlags::empty()),
            Ok(_) => Ok(tty_ev.unwrap_or(PollFlags::empty())),
            Err(e) => Err(e.into()),
        }
    }

    fn read_impl(&mut self, buf: &mut [u8], timeout: Duration, wake: Option<&Wake>) -> io::Result<usize> {
        if buf.is_empty() {
            return Ok(0);
        }
        let mut polled = false;
        loop {
            match nix::unistd::read(&self.fd, buf) {
                Ok(0) => return Err(hang_up("end of file on tty")),
                Ok(n) => return Ok(n),
                Err(Errno::EAGAIN) | Err(Errno::EINTR) if polled => return Ok(0),
                Err(Errno::EAGAIN) | Err(Errno::EINTR) => {}
                Err(Errno::EIO) => return Err(hang_up("tty hung up (EIO)")),
                Err(e) => return Err(e.into()),
            }
            let ev = self.wait_or_wake(PollFlags::POLLIN, timeout, wake)?;
            if ev.is_empty() {
                return Ok(0);
            }
            if !ev.contains(PollFlags::POLLIN)
                && ev.intersects(PollFlags::POLLHUP | PollFlags::POLLERR | PollFlags::POLLNVAL)
            {
                return Err(hang_up("tty hung up"));
            }
            polled = true;
        }
    }
}

fn hang_up(what: &str) -> io::Error {
    io::Error::new(io::ErrorKind::UnexpectedEof, what.to_owned())
}

impl Transport for PtyTransport {
    fn read(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        self.read_impl(buf, timeout, None)
    }

    fn read_wake(&mut self, buf: &mut [u8], timeout: Duration, wake: &Wake) -> io::Result<usize> {
        self.read_impl(buf, timeout, Some(wake))
    }

    fn supports_wake(&self) -> bool {
        true
    }

    fn write_all(&mut self, data: &[u8]) -> io::Result<()> {
        let start = Instant::now();
        let mut rest = data;
        while !rest.is_empty() {
            match nix::unistd::write(&self.fd, rest) {
                Ok(n) => rest = &rest[n..],
                Err(Errno::EINTR) => {}
                Err(Errno::EAGAIN) => {
                    let left = WRITE_TIMEOUT.checked_sub(start.elapsed()).ok_or_else(|| {
                        io::Error::new(io::ErrorKind::TimedOut, "tty write blocked for 1 s")
                    })?;
                    let ev = self.wait(PollFlags::POLLOUT, left)?;
                    if ev.intersects(PollFlags::POLLHUP | PollFlags::POLLERR | PollFlags::POLLNVAL) {
                        return Err(io::Error::new(io::ErrorKind::BrokenPipe, "tty hung up"));
                    }
                }
                Err(Errno::EIO) => {
                    return Err(io::Error::new(io::ErrorKind::BrokenPipe, "tty hung up (EIO)"))
                }
                Err(e) => return Err(e.into()),
            }
        }
        Ok(())
    }

    fn describe(&self) -> String {
        self.name.clone()
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::transport::conformance;
    use nix::pty::{grantpt, posix_openpt, ptsname_r, unlockpt};

    /// A pty pair: (master, slave path).
    pub(crate) fn pty_pair() -> (PtyTransport, String) {
        let master = posix_openpt(OFlag::O_RDWR | OFlag::O_NOCTTY).unwrap();
        grantpt(&master).unwrap();
        unlockpt(&master).unwrap();
        let path = ptsname_r(&master).unwrap();
        (
            PtyTransport::from_fd(OwnedFd::from(master), "pty master").unwrap(),
            path,
        )
    }

    #[test]
    fn conformance_host_side_hangup() {
        let (master, path) = pty_pair();
        let slave = PtyTransport::open(&path).unwrap();
        assert_eq!(slave.describe(), format!("pty {path}"));
        // The MCU (master) goes away: the host (slave) sees a hang-up.
        conformance::run(Box::new(master), Box::new(slave));
    }

    #[test]
    fn conformance_mcu_side_hangup() {
        let (master, path) = pty_pair();
        let slave = PtyTransport::open(&path).unwrap();
        conformance::run(Box::new(slave), Box::new(master));
    }

    #[test]
    fn open_missing_path_fails() {
        let e = PtyTransport::open("/nonexistent/pty").unwrap_err();
        assert!(e.to_string().contains("/nonexistent/pty"));
    }
}
