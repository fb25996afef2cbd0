//! A real serial port (USB CDC or UART) through the `serialport` crate: it sets the baud rate,
//! raw mode and exclusive access. Reads map its "timed out" error to `Ok(0)`; a hang-up (USB
//! unplugged) comes back as `BrokenPipe`.

use std::io::{self, Read, Write};
use std::time::Duration;

use serialport::SerialPort;

use super::pty::WRITE_TIMEOUT;
use super::Transport;

/// An open serial port.
#[derive(Debug)]
pub struct SerialTransport {
    port: serialport::TTYPort,
    path: String,
    baud: u32,
}

impl SerialTransport {
    /// Opens `path` at `baud` (8N1, no flow control, exclusive).
    pub fn open(path: &str, baud: u32) -> io::Result<SerialTransport> {
        let port = serialport::new(path, baud)
            .timeout(WRITE_TIMEOUT)
            .open_native()
            .map_err(|e| io::Error::new(io::Error::from(e.clone()).kind(), format!("open {path}: {e}")))?;
        Ok(SerialTransport {
            port,
            path: path.to_owned(),
            baud,
        })
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
    fn open_missing_port_fails() {
        assert!(SerialTransport::open("/nonexistent/ttyUSB9", 250_000).is_err());
    }
}
