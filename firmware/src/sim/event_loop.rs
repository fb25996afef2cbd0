//! The simulator's main loop: sleep until the next timer or input, feed bytes, run timers,
//! write responses.
//!
//! One iteration: (freeze if `--freeze-after-ms` has come); run due timers at the current
//! clock; pass pending output through the fault stage ([`TxFaults`]) to the pty; check the
//! parent process (at most every [`PARENT_POLL`]); then wait for the next timer as the
//! [`SpinPolicy`] says (`--spin-us`, default [`DEFAULT_SPIN`]):
//! - sleep: publish the world's positions and `ppoll` the pty master and the signalfd until the
//!   spin window before the timer (or, once the spin streak is used up, until the timer itself),
//!   capped at [`PARENT_POLL`] and at the next release of delayed output;
//! - spin (within the window, for at most the window in a row): do not sleep; loop reading the
//!   (vDSO) clock and run the timers the moment they are due, checking input and signals with a
//!   zero-timeout poll at most every [`INPUT_POLL`], and yielding the CPU on every turn (so a
//!   runnable host thread on the same core is not kept waiting). The bounded streak keeps
//!   dense steps from turning into an endless busy loop that starves the host on a small
//!   machine.
//!
//! Each chunk the host sent is fed to the core at the clock of its arrival. When the loop comes
//! back after more than [`INPUT_POLL`] away from the pty (preempted, or stalled by the machine),
//! it takes the waiting input before the timers that fell due meanwhile: a board's UART
//! receives while its timers wait, so a `trsync_set_timeout` the host sent in time renews the
//! trsync before the expiry it was sent to prevent, and a `queue_step` joins its stepper's
//! queue before the stepper runs dry (it was refused as "Timer too close" after a 166 ms stall
//! of a cadence-mcu under Klipper's host).
//!
//! Hang-up: the master reports POLLHUP once the host has opened and closed the slave — but also
//! if anything else opened and closed it before the host came. So a hang-up counts only after
//! the host has sent at least one byte; before that the loop stops polling the master (POLLHUP
//! would make poll return at once), sleeps at most [`HANGUP_RETRY`], and checks again. Output
//! produced before the host's first byte (periodic stats) is discarded rather than left in the
//! pty buffer for the host to read as stale blocks. With `--keep-open` a hang-up after the
//! host spoke does not end the loop: it goes back to waiting for a host, as at start-up (the
//! MCU state is kept, as on a board whose host restarted).

use super::board::SimBoard;
use super::clock::SimClock;
use super::faults::TxFaults;
use super::pty::{Io, Pty};
pub use super::spin::DEFAULT_SPIN;
use super::spin::{SpinPolicy, Wait};
use super::{SimError, SimMcu};
use nix::errno::Errno;
use nix::poll::{poll, ppoll, PollFd, PollFlags, PollTimeout};
use nix::sys::signal::Signal;
use nix::sys::signalfd::SignalFd;
use nix::sys::time::TimeSpec;
use nix::unistd::{getppid, Pid};
use rt_core::{McuClock, WireClock};
use std::os::fd::AsFd;
use std::time::{Duration, Instant};

/// Longest sleep between parent-process checks (and the period of those checks).
pub const PARENT_POLL: Duration = Duration::from_millis(100);
/// Sleep between checks while the pty shows a hang-up before the host's first byte.
pub const HANGUP_RETRY: Duration = Duration::from_millis(20);
/// Longest time between two input checks while spinning.
pub const INPUT_POLL: Duration = Duration::from_micros(100);
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
    /// A hang-up after the host spoke waits for the next host instead of ending the loop.
    keep_open: bool,
    faults: TxFaults,
    /// Output released by the fault stage, not yet written.
    staged: Vec<u8>,
    /// `(start, length)` of the freeze still to come.
    freeze: Option<(Instant, Duration)>,
    last_parent_check: Instant,
    last_input_poll: Instant,
    spin: SpinPolicy,
}

impl<'a> EventLoop<'a> {
    /// A loop over `pty` and `sigfd`, exiting if the parent is no longer `parent`.
    pub fn new(pty: &'a Pty, sigfd: &'a SignalFd, clock: SimClock, parent: Pid) -> Self {
        let now = Instant::now();
        EventLoop {
            pty,
            sigfd,
            clock,
            parent,
            host_seen: false,
            hangup_wait: false,
            keep_open: false,
            faults: TxFaults::new(0.0, Duration::ZERO, 1),
            staged: Vec::new(),
            freeze: None,
            last_parent_check: now,
            last_input_poll: now,
            spin: SpinPolicy::new(DEFAULT_SPIN),
        }
    }

    /// Passes output through `faults` (`--drop-tx`, `--tx-delay-ms`).
    pub fn with_faults(mut self, faults: TxFaults) -> Self {
        self.faults = faults;
        self
    }

    /// Busy-waits at most `window` before a timer and at most `window` in a row (`--spin-us`;
    /// zero: never busy-wait).
    pub fn with_spin(mut self, window: Duration) -> Self {
        self.spin = SpinPolicy::new(window);
        self
    }

    /// On a hang-up after the host spoke, wait for the next host (`--keep-open`).
    pub fn with_keep_open(mut self, keep_open: bool) -> Self {
        self.keep_open = keep_open;
        self
    }

    /// The host hung up after speaking: true if the loop ends; with `keep_open`, forget the
    /// host and its pending output and wait for the next one.
    fn host_closed(&mut self) -> bool {
        if !self.keep_open {
            return true;
        }
        self.host_seen = false;
        self.hangup_wait = true;
        self.staged.clear();
        false
    }

    /// Freezes for `length`, `after` from now (`--freeze-after-ms`, `--freeze-ms`).
    pub fn with_freeze(mut self, after: Duration, length: Duration) -> Self {
        self.freeze = Some((Instant::now() + after, length));
        self
    }

    /// Runs until the host hangs up, a signal arrives or the parent dies.
    pub fn run(&mut self, mcu: &mut SimMcu) -> Result<Exit, SimError> {
        let mut buf = [0u8; READ_CHUNK];
        let mut busy_since = self.clock.now();
        loop {
            if let Some((at, length)) = self.freeze {
                if Instant::now() >= at {
                    std::thread::sleep(length);
                    self.freeze = None;
                }
            }
            if self.last_input_poll.elapsed() >= INPUT_POLL && !self.hangup_wait {
                // The loop was away longer than an input check's period (the process was
                // preempted or stalled, e.g. while spinning): what the host sent meanwhile is
                // taken before the timers that fell due, as a board's UART would have received
                // it while they waited (a trsync renewal before its expiry, a queue_step before
                // its stepper's queue ran dry).
                if self.take_waiting_input(mcu, &mut buf)? {
                    if self.host_seen && self.host_closed() {
                        return Ok(Exit::HostClosed);
                    }
                    self.hangup_wait = true;
                }
            }
            let now = self.clock.now();
            mcu.board_mut().now = now;
            mcu.run_timers(WireClock(now as u32));
            if self.pump_output(mcu.board_mut())? && self.host_seen && self.host_closed() {
                return Ok(Exit::HostClosed);
            }
            if self.last_parent_check.elapsed() >= PARENT_POLL {
                self.last_parent_check = Instant::now();
                if getppid() != self.parent {
                    return Ok(Exit::ParentDied);
                }
            }
            let now = self.clock.now();
            let wake = McuClock(now).extend(mcu.next_wake()).0;
            let until_wake = self.clock.wall_until(now, wake);
            let wait = match self.spin.decide(until_wake, Instant::now()) {
                // While waiting out an early hang-up the master is not polled: never spin.
                Wait::Spin if self.hangup_wait => Wait::Sleep(until_wake.saturating_sub(self.spin.window())),
                w => w,
            };
            let timeout = match wait {
                Wait::Spin => {
                    if self.last_input_poll.elapsed() < INPUT_POLL {
                        mcu.board_mut().world.flush_due();
                        // A polite spin: another runnable thread of this core (the host) gets
                        // the CPU at once; with none, this returns at once.
                        std::thread::yield_now();
                        continue;
                    }
                    Duration::ZERO
                }
                Wait::Sleep(sleep) => {
                    mcu.board_mut().export_heaters(now);
                    mcu.board_mut().world.flush();
                    mcu.record_loop(u32::try_from(now.saturating_sub(busy_since)).unwrap_or(u32::MAX));
                    self.sleep_for(sleep)
                }
            };
            let want_write = !mcu.board().out.is_empty() || !self.staged.is_empty();
            let (sig_ready, master) = self.wait(timeout, want_write)?;
            self.last_input_poll = Instant::now();
            if !timeout.is_zero() {
                busy_since = self.clock.now();
            }
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
                if self.host_seen && self.host_closed() {
                    return Ok(Exit::HostClosed);
                }
                self.hangup_wait = true;
            }
        }
    }

    /// How long to sleep when the policy asks for `sleep`: capped by the periodic checks and
    /// the next output release or freeze.
    fn sleep_for(&self, sleep: Duration) -> Duration {
        let mut timeout = sleep.min(PARENT_POLL);
        if self.hangup_wait {
            timeout = timeout.min(HANGUP_RETRY);
        }
        let now = Instant::now();
        for at in [self.faults.next_release(), self.freeze.map(|f| f.0)]
            .into_iter()
            .flatten()
        {
            timeout = timeout.min(at.saturating_duration_since(now));
        }
        timeout
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

    /// Checks the pty without waiting and feeds what is there to the core; returns true on a
    /// hang-up.
    fn take_waiting_input(&mut self, mcu: &mut SimMcu, buf: &mut [u8]) -> Result<bool, SimError> {
        let mut fds = [PollFd::new(self.pty.fd(), PollFlags::POLLIN)];
        match poll(&mut fds, PollTimeout::ZERO) {
            Ok(_) | Err(Errno::EINTR) => {}
            Err(e) => return Err(super::sys("poll")(e)),
        }
        self.last_input_poll = Instant::now();
        let r = fds[0].revents().unwrap_or(PollFlags::empty());
        let hung_up = r.intersects(PollFlags::POLLHUP | PollFlags::POLLERR);
        if r.contains(PollFlags::POLLIN) || hung_up {
            return Ok(self.read_input(mcu, buf)? | hung_up);
        }
        Ok(false)
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

    /// Writes pending output (through the fault stage); returns true on a hang-up. Before the
    /// host's first byte the output is discarded.
    fn pump_output(&mut self, board: &mut SimBoard) -> Result<bool, SimError> {
        if !self.host_seen {
            board.out.clear();
            return Ok(false);
        }
        if self.faults.is_transparent() && self.staged.is_empty() {
            return self.write_out(&mut board.out);
        }
        if !board.out.is_empty() {
            self.faults.push(&board.out, Instant::now());
            board.out.clear();
        }
        self.faults.ready(Instant::now(), &mut self.staged);
        let mut staged = std::mem::take(&mut self.staged);
        let hung_up = self.write_out(&mut staged);
        self.staged = staged;
        hung_up
    }

    /// Writes as much of `out` as the pty takes and removes it from `out`.
    fn write_out(&mut self, out: &mut Vec<u8>) -> Result<bool, SimError> {
        let mut written = 0;
        let mut hung_up = false;
        while written < out.len() {
            match self.pty.write(&out[written..]).map_err(super::sys("write pty"))? {
                Io::Done(n) => written += n,
                Io::WouldBlock => break,
                Io::HangUp => {
                    hung_up = true;
                    break;
                }
            }
        }
        out.drain(..written);
        Ok(hung_up)
    }

    /// Bytes dropped by `--drop-tx` so far.
    pub fn dropped_tx(&self) -> u64 {
        self.faults.dropped
    }
}
