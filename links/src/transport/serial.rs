//! A real serial port (USB CDC or UART) through the `serialport` crate: it sets the baud rate,
//! raw mode and exclusive access. Reads map its "timed out" error to `Ok(0)`; a hang-up (USB
//! unplugged) comes back as `BrokenPipe`.
//!
//! **Wake-ups.** The port's own descriptor is not reachable without `unsafe`, so a second,
//! non-blocking descriptor of the same device is opened (exclusivity is lifted for that one
//! `open`) and only polled: [`Transport::read_wake`] `ppoll`s it together with the IO thread's
//! [`Wake`] eventfd, then reads through the port. Without it the IO thread could only notice a
//! hand-off at the end of its read slice (up to 5 ms on every command sent to a real MCU).
//! If the second open fails the port still works, without wake support.

use std::io::{self, Read, Write};
use std::os::fd::{AsFd, OwnedFd};
use std::time::Duration;

use nix::errno::Errno;
use nix::fcntl::OFlag;
use nix::poll::{ppoll, PollFd, PollFlags};
use nix::sys::stat::Mode;
use nix::sys::time::TimeSpec;
use serialport::SerialPort;

use super::pty::WRITE_TIMEOUT;
use super::{Transport, Wake};

/// An open serial port.
#[derive(Debug)]
pub struct SerialTransport {
    port: serialport::TTYPort,
    path: String,
    baud: u32,
    /// A second descriptor of the device, only polled (see the module doc).
    poll_fd: Option<OwnedFd>,
}

impl SerialTransport {
    /// Opens `path` at `baud` (8N1, no flow control, exclusive).
    pub fn open(path: &str, baud: u32) -> io::Result<SerialTransport> {
        let mut port = serialport::new(path, baud)
            .timeout(WRITE_TIMEOUT)
            .open_native()
            .map_err(|e| io::Error::new(io::Error::from(e.clone()).kind(), format!("open {path}: {e}")))?;
        let poll_fd = open_poll_fd(&mut port, path);
        Ok(SerialTransport {
            port,
            path: path.to_owned(),
            baud,
            poll_fd,
        })
    }

    /// Waits up to `timeout` until the port is readable (or hung up) or `wake` fires.
    /// Returns true when the port has something to read.
    fn wait_readable(fd: &OwnedFd, timeout: Duration, wake: &Wake) -> io::Result<bool> {
        let mut fds = [
            PollFd::new(fd.as_fd(), PollFlags::POLLIN),
            PollFd::new(wake.fd(), PollFlags::POLLIN),
        ];
        match ppoll(&mut fds, Some(TimeSpec::from_duration(timeout)), None) {
            Ok(_) | Err(Errno::EINTR) => {}
            Err(e) => return Err(e.into()),
        }
        if fds[1].revents().is_some_and(|e| !e.is_empty()) {
            wake.drain();
        }
        Ok(fds[0].revents().is_some_and(|e| !e.is_empty()))
    }
}

/// Opens the second, poll-only descriptor of `path` while `port` briefly allows it.
fn open_poll_fd(port: &mut serialport::TTYPort, path: &str) -> Option<OwnedFd> {
    port.set_exclusive(false).ok()?;
    let fd = nix::fcntl::open(
        path,
        OFlag::O_RDWR | OFlag::O_NOCTTY | OFlag::O_NONBLOCK | OFlag::O_CLOEXEC,
        Mode::empty(),
    );
    // Exclusive again whatever happened: other programs must not open the port.
    let relocked = port.set_exclusive(true).is_ok();
    match fd {
        Ok(fd) if relocked => Some(fd),
        _ => None,
    }
}

impl Transport for SerialTransport {
    fn read(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        self.port.set_timeout(timeout).map_err(io::Error::from)?;
        match self.port.read(buf) {
            Ok(0) if !buf.is_empty() => {
                Err(io::Error::new(io::ErrorKind::UnexpectedEof, "serial port closed"))
            }
            Ok(n) => Ok(n),
            Err(e) if matches!(e.kind(), io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock) => Ok(0),
            Err(e) if e.kind() == io::ErrorKind::Interrupted => Ok(0),
            Err(e) if e.raw_os_error() == Some(libc::EIO) => Err(io::Error::new(
                io::ErrorKind::UnexpectedEof,
                "serial port hung up (EIO)",
            )),
            Err(e) => Err(e),
        }
    }

    fn read_wake(&mut self, buf: &mut [u8], timeout: Duration, wake: &Wake) -> io::Result<usize> {
        let readable = match &self.poll_fd {
            Some(fd) => Self::wait_readable(fd, timeout, wake)?,
            None => return self.read(buf, timeout),
        };
        if readable {
            self.read(buf, Duration::ZERO)
        } else {
            Ok(0)
        }
    }

    fn supports_wake(&self) -> bool {
        self.poll_fd.is_some()
    }

    fn write_all(&mut self, data: &[u8]) -> io::Result<()> {
        self.port.set_timeout(WRITE_TIMEOUT).map_err(io::Error::from)?;
        self.port.write_all(data).map_err(|e| match e.raw_os_error() {
            Some(libc::EIO) => io::Error::new(io::ErrorKind::BrokenPipe, "serial port hung up (EIO)"),
            _ => e,
        })
    }

    fn describe(&self) -> String {
        format!("serial {}@{}", self.path, self.baud)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transport::conformance;
    use crate::transport::pty::tests::pty_pair;

    #[test]
    fn conformance_over_a_pty() {
        // A pty slave stands in for a USB serial device.
        let (master, path) = pty_pair();
        let port = SerialTransport::open(&path, 250_000).unwrap();
        assert_eq!(port.describe(), format!("serial {path}@250000"));
        conformance::run(Box::new(master), Box::new(port));
    }

    #[test]
    fn read_wake_returns_on_wake_and_reads_data() {
        let (mut master, path) = pty_pair();
        let mut port = SerialTransport::open(&path, 250_000).unwrap();
        assert!(port.supports_wake());
        // Still exclusive after the poll descriptor was opened.
        assert!(SerialTransport::open(&path, 250_000).is_err());
        let wake = Wake::new().unwrap();
        let mut buf = [0u8; 16];
        // A pending wake ends the wait (a transport ignoring it would block for the minute)
        // and is consumed: the eventfd is drained.
        wake.sleeping();
        wake.wake();
        assert_eq!(
            port.read_wake(&mut buf, Duration::from_secs(60), &wake).unwrap(),
            0
        );
        let mut fds = [nix::poll::PollFd::new(wake.fd(), PollFlags::POLLIN)];
        assert_eq!(
            nix::poll::poll(&mut fds, nix::poll::PollTimeout::ZERO).unwrap(),
            0
        );
        // Data waiting on the port is returned.
        master.write_all(&[0x7E, 1, 2]).unwrap();
        let mut got = Vec::new();
        while got.len() < 3 {
            let n = port.read_wake(&mut buf, Duration::from_secs(60), &wake).unwrap();
            got.extend_from_slice(&buf[..n]);
        }
        assert_eq!(got, [0x7E, 1, 2]);
    }

    #[test]
    fn open_missing_port_fails() {
        assert!(SerialTransport::open("/nonexistent/ttyUSB9", 250_000).is_err());
    }
}
