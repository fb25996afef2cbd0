//! The simulator's main loop: sleep until the next timer or input, feed bytes, run timers,
//! write responses.
//!
//! One iteration: run due timers at the current clock; write pending output; check the parent;
//! then `ppoll` the pty master and the signalfd with the exact time left until the core's next
//! wake (capped at [`PARENT_POLL`] so a dead parent is noticed); then read everything the host
//! sent, feeding each chunk to the core at the clock of its arrival.
//!
//! Hang-up: the master reports POLLHUP once the host has opened and closed the slave — but also
//! if anything else opened and closed it before the host came. So a hang-up counts only after
//! the host has sent at least one byte; before that the loop stops polling the master (POLLHUP
//! would make poll return at once), sleeps at most [`HANGUP_RETRY`], and checks again. Output
//! produced before the host's first byte (periodic stats) is discarded rather than left in the
//! pty buffer for the host to read as stale blocks.

use super::board::SimBoard;
use super::clock::SimClock;
use super::pty::{Io, Pty};
use super::{SimError, SimMcu};
use nix::errno::Errno;
use nix::poll::{poll, ppoll, PollFd, PollFlags, PollTimeout};
use nix::sys::signal::Signal;
use nix::sys::signalfd::SignalFd;
use nix::sys::time::TimeSpec;
use nix::unistd::{getppid, Pid};
use rt_core::{McuClock, WireClock};
use std::os::fd::AsFd;
use std::time::Duration;

/// Longest sleep between parent-process checks.
pub const PARENT_POLL: Duration = Duration::from_millis(100);
/// Sleep between checks while the pty shows a hang-up before the host's first byte.
pub const HANGUP_RETRY: Duration = Duration::from_millis(20);
const READ_CHUNK: usize = 4096;

/// Why the loop ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Exit {
    /// The host closed the pty slave.
    HostClosed,
    /// SIGTERM, SIGINT or SIGHUP.
    Signal(Signal),
    /// The parent process exited.
    ParentDied,
}

/// The event loop's state.
#[derive(Debug)]
pub struct EventLoop<'a> {
    pty: &'a Pty,
    sigfd: &'a SignalFd,
    clock: SimClock,
    parent: Pid,
    /// The host has sent at least one byte.
    host_seen: bool,
    /// The master shows a hang-up although the host never spoke: do not poll it.
    hangup_wait: bool,
}

impl<'a> EventLoop<'a> {
    /// A loop over `pty` and `sigfd`, exiting if the parent is no longer `parent`.
    pub fn new(pty: &'a Pty, sigfd: &'a SignalFd, clock: SimClock, parent: Pid) -> Self {
        EventLoop {
            pty,
            sigfd,
            clock,
            parent,
            host_seen: false,
            hangup_wait: false,
        }
    }

    /// Runs until the host hangs up, a signal arrives or the parent dies.
    pub fn run(&mut self, mcu: &mut SimMcu) -> Result<Exit, SimError> {
        let mut buf = [0u8; READ_CHUNK];
        let mut busy_since = self.clock.now();
        loop {
            let now = self.clock.now();
            mcu.board_mut().now = now;
            mcu.run_timers(WireClock(now as u32));
            if self.pump_output(mcu.board_mut())? && self.host_seen {
                return Ok(Exit::HostClosed);
            }
            if getppid() != self.parent {
                return Ok(Exit::ParentDied);
            }
            let now = self.clock.now();
            mcu.record_loop(u32::try_from(now.saturating_sub(busy_since)).unwrap_or(u32::MAX));
            let wake = McuClock(now).extend(mcu.next_wake()).0;
            let mut timeout = self.clock.wall_until(now, wake).min(PARENT_POLL);
            if self.hangup_wait {
                timeout = timeout.min(HANGUP_RETRY);
            }

            let (sig_ready, master) = self.wait(timeout, !mcu.board().out.is_empty())?;
            busy_since = self.clock.now();
            if sig_ready {
                if let Some(info) = self.sigfd.read_signal().map_err(super::sys("read signalfd"))? {
                    let sig = Signal::try_from(info.ssi_signo as i32).unwrap_or(Signal::SIGTERM);
                    return Ok(Exit::Signal(sig));
                }
            }
            let master = match master {
                Some(m) => m,
                None if self.hangup_wait => self.probe_master()?,
                None => PollFlags::empty(),
            };
            let mut hung_up = master.intersects(PollFlags::POLLHUP | PollFlags::POLLERR);
            if master.contains(PollFlags::POLLIN) || hung_up {
                hung_up |= self.read_input(mcu, &mut buf)?;
            }
            if hung_up {
                if self.host_seen {
                    return Ok(Exit::HostClosed);
                }
                self.hangup_wait = true;
            }
        }
    }

    /// Sleeps in `ppoll` for at most `timeout`; returns (signal ready, master revents if polled).
    fn wait(&self, timeout: Duration, want_write: bool) -> Result<(bool, Option<PollFlags>), SimError> {
        let mut master_events = PollFlags::POLLIN;
        if want_write {
            master_events |= PollFlags::POLLOUT;
        }
        let mut fds = [
            PollFd::new(self.sigfd.as_fd(), PollFlags::POLLIN),
            PollFd::new(self.pty.fd(), master_events),
        ];
        let n = if self.hangup_wait { 1 } else { 2 };
        match ppoll(&mut fds[..n], Some(TimeSpec::from(timeout)), None) {
            Ok(_) | Err(Errno::EINTR) => {}
            Err(e) => return Err(super::sys("ppoll")(e)),
        }
        let sig = fds[0].revents().is_some_and(|r| r.contains(PollFlags::POLLIN));
        let master = (n == 2).then(|| fds[1].revents().unwrap_or(PollFlags::empty()));
        Ok((sig, master))
    }

    /// While waiting out an early hang-up: has the host opened the slave since?
    fn probe_master(&mut self) -> Result<PollFlags, SimError> {
        let mut fds = [PollFd::new(self.pty.fd(), PollFlags::POLLIN)];
        match poll(&mut fds, PollTimeout::ZERO) {
            Ok(_) | Err(Errno::EINTR) => {}
            Err(e) => return Err(super::sys("poll")(e)),
        }
        let r = fds[0].revents().unwrap_or(PollFlags::empty());
        if !r.contains(PollFlags::POLLHUP) {
            self.hangup_wait = false;
        }
        Ok(r)
    }

    /// Reads everything available and feeds it to the core; returns true on a hang-up.
    fn read_input(&mut self, mcu: &mut SimMcu, buf: &mut [u8]) -> Result<bool, SimError> {
        loop {
            match self.pty.read(buf).map_err(super::sys("read pty"))? {
                Io::Done(n) => {
                    let now = self.clock.now();
                    mcu.board_mut().now = now;
                    mcu.receive(WireClock(now as u32), &buf[..n]);
                    self.host_seen = true;
                    self.hangup_wait = false;
                }
                Io::WouldBlock => return Ok(false),
                Io::HangUp => return Ok(true),
            }
        }
    }

    /// Writes pending output; returns true on a hang-up. Before the host's first byte the
    /// output is discarded.
    fn pump_output(&mut self, board: &mut SimBoard) -> Result<bool, SimError> {
        if !self.host_seen {
            board.out.clear();
            return Ok(false);
        }
        let mut written = 0;
        let mut hung_up = false;
        while written < board.out.len() {
            match self
                .pty
                .write(&board.out[written..])
                .map_err(super::sys("write pty"))?
            {
                Io::Done(n) => written += n,
                Io::WouldBlock => break,
                Io::HangUp => {
                    hung_up = true;
                    break;
                }
            }
        }
        board.out.drain(..written);
        Ok(hung_up)
    }
}
