//! The pseudo-terminal the host talks through: we keep the master, the host opens the slave.
//!
//! The line is made raw through the master (Linux applies termios set on a pty master to its
//! slave), so the host sees bytes unmodified without us ever opening the slave. That matters
//! for hang-up detection: a master reports POLLHUP (and reads fail with EIO) only once a slave
//! was opened and then closed by everyone, so opening the slave ourselves would either hide the
//! host's close (kept open) or fake one (closed again).

use nix::errno::Errno;
use nix::fcntl::OFlag;
use nix::pty::{grantpt, posix_openpt, ptsname_r, unlockpt, PtyMaster};
use nix::sys::termios::{cfmakeraw, tcgetattr, tcsetattr, SetArg};
use std::os::fd::{AsFd, BorrowedFd};
use std::path::{Path, PathBuf};

/// An open pty master and its slave's path.
#[derive(Debug)]
pub struct Pty {
    master: PtyMaster,
    slave_path: PathBuf,
}

/// What a non-blocking read or write on the master did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Io {
    /// This many bytes moved.
    Done(usize),
    /// Nothing to do now (EAGAIN).
    WouldBlock,
    /// No slave is open (EIO): the host hung up, or never opened it.
    HangUp,
}

impl Pty {
    /// Opens a non-blocking master in raw mode.
    pub fn open() -> nix::Result<Pty> {
        let master = posix_openpt(OFlag::O_RDWR | OFlag::O_NOCTTY | OFlag::O_NONBLOCK | OFlag::O_CLOEXEC)?;
        grantpt(&master)?;
        unlockpt(&master)?;
        let slave_path = PathBuf::from(ptsname_r(&master)?);
        let mut t = tcgetattr(&master)?;
        cfmakeraw(&mut t);
        tcsetattr(&master, SetArg::TCSANOW, &t)?;
        Ok(Pty { master, slave_path })
    }

    /// The path the host opens.
    pub fn slave_path(&self) -> &Path {
        &self.slave_path
    }

    /// The master, for poll.
    pub fn fd(&self) -> BorrowedFd<'_> {
        self.master.as_fd()
    }

    /// Reads what the host sent.
    pub fn read(&self, buf: &mut [u8]) -> nix::Result<Io> {
        loop {
            return match nix::unistd::read(self.master.as_fd(), buf) {
                Ok(0) => Ok(Io::HangUp),
                Ok(n) => Ok(Io::Done(n)),
                Err(Errno::EAGAIN) => Ok(Io::WouldBlock),
                Err(Errno::EIO) => Ok(Io::HangUp),
                Err(Errno::EINTR) => continue,
                Err(e) => Err(e),
            };
        }
    }

    /// Writes toward the host.
    pub fn write(&self, buf: &[u8]) -> nix::Result<Io> {
        loop {
            return match nix::unistd::write(self.master.as_fd(), buf) {
                Ok(n) => Ok(Io::Done(n)),
                Err(Errno::EAGAIN) => Ok(Io::WouldBlock),
                Err(Errno::EIO) => Ok(Io::HangUp),
                Err(Errno::EINTR) => continue,
                Err(e) => Err(e),
            };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
    use std::fs::OpenOptions;
    use std::io::{Read, Write};

    #[test]
    fn raw_bytes_both_ways_and_hangup_after_close() {
        let pty = Pty::open().unwrap();
        let mut buf = [0u8; 64];
        // Never opened: no data, and not a hang-up yet.
        assert_eq!(pty.read(&mut buf).unwrap(), Io::WouldBlock);
        let mut slave = OpenOptions::new()
            .read(true)
            .write(true)
            .open(pty.slave_path())
            .unwrap();
        let bytes = [0x7E, b'\r', b'\n', 0x03, 0x11, 0x13, 0xFF];
        slave.write_all(&bytes).unwrap();
        let mut got = Vec::new();
        for _ in 0..100 {
            let mut fds = [PollFd::new(pty.fd(), PollFlags::POLLIN)];
            poll(&mut fds, PollTimeout::from(100u16)).unwrap();
            if let Io::Done(n) = pty.read(&mut buf).unwrap() {
                got.extend_from_slice(&buf[..n]);
            }
            if got.len() >= bytes.len() {
                break;
            }
        }
        assert_eq!(got, bytes);
        assert_eq!(pty.write(&bytes).unwrap(), Io::Done(bytes.len()));
        let mut back = [0u8; 7];
        slave.read_exact(&mut back).unwrap();
        assert_eq!(back, bytes);
        drop(slave);
        assert_eq!(pty.read(&mut buf).unwrap(), Io::HangUp);
    }
}
