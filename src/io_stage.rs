//! The IO stage of one MCU: its step channel (iceoryx2 shared memory) → the 100 ms lead check
//! → the MCU link, whose own IO thread writes the bytes. Allocation-free after warm-up; the
//! batches it took are counted so the planner can drain the hand-off before homing.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc;
use std::time::Duration;

use links::dict::Cmd;
use links::mcu::McuLink;
use rt_core::alloc_count::AllocCounter;
use rt_core::logger::{Arg, Level, LoggerHandle};
use rt_core::shm::{open_node, ChannelConfig, ShmSubscriber, StepBatch};

use crate::latency::{mono_ns, Hists};
use crate::planner_thread::Ipc;
use crate::MIN_LEAD_S;

/// What the IO stage reports.
#[derive(Debug, Default)]
pub(crate) struct IoReport {
    pub batches: u64,
    pub allocations_after_warmup: Option<u64>,
    /// Batches taken after warm-up (the loop iterations `allocations_after_warmup` covers).
    pub batches_after_warmup: u64,
}

/// A stage's heap allocations after warm-up and the step batches it handled meanwhile (so a
/// 0 means something only with batches > 0). Homing and probing moves in the middle of a print
/// leave the streaming loop (the planner drains the hand-off and drives the MCUs directly,
/// building and parsing their messages): their allocations are counted apart. Displayed as
/// "`allocations` (`batches` batches)", then "; `n` more in `m` homing/probing commands".
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(crate) struct AfterWarmup {
    pub allocations: u64,
    pub batches: u64,
    /// Allocations during homing/probing commands after warm-up (not in `allocations`).
    pub motion_allocations: u64,
    /// Homing/probing commands after warm-up.
    pub motions: u64,
}

impl std::fmt::Display for AfterWarmup {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} ({} batches", self.allocations, self.batches)?;
        if self.motions > 0 {
            write!(
                f,
                "; {} more in {} homing/probing command{}",
                self.motion_allocations,
                self.motions,
                if self.motions == 1 { "" } else { "s" }
            )?;
        }
        write!(f, ")")
    }
}

/// Batches after which a stage counts as warmed up (allocation accounting starts).
pub(crate) const WARMUP_BATCHES: u64 = 64;

/// Why an IO stage stopped, or did not start.
#[derive(Debug, thiserror::Error)]
pub enum IoStageError {
    /// Its shared-memory node or step channel could not be opened.
    #[error(transparent)]
    Shm(#[from] rt_core::shm::ShmError),
    /// Receiving from the step channel failed.
    #[error("io stage: {0}")]
    Receive(#[source] rt_core::shm::ShmError),
    /// It did not start (the reason went to whoever waited for it to be ready).
    #[error("io stage: it did not start")]
    NotStarted,
    /// A step message came with less than the minimum lead.
    #[error(
        "the IO stage fell behind: a step message for clock {clock} reached it {ahead_ms:.1} ms before it is due \
         (at least {min_ms:.0} ms required); print stopped before sending it"
    )]
    FellBehind { clock: u64, ahead_ms: f64, min_ms: f64 },
    /// A message in a batch is not an encoded command.
    #[error("io stage: malformed message in a step batch")]
    Malformed,
    /// The MCU link refused the message.
    #[error(transparent)]
    Link(#[from] links::mcu::LinkError),
}

/// The IO stage: shared memory → lead check → the MCU link. Runs until `done` is set and no
/// batch is pending; `consumed` counts the batches taken.
#[allow(clippy::too_many_arguments)]
pub(crate) fn io_stage(
    link: &McuLink,
    service: &str,
    ready: mpsc::Sender<Result<(), IoStageError>>,
    done: &AtomicBool,
    consumed: &AtomicU64,
    hists: &Hists,
    clock_freq: f64,
    log: &LoggerHandle,
) -> Result<IoReport, IoStageError> {
    let setup = || -> Result<_, IoStageError> {
        let (node, _) = open_node::<Ipc>(&format!("cadence-io-{}", std::process::id()))?;
        let sub = ShmSubscriber::<Ipc, StepBatch>::open(&node, service, &ChannelConfig::steps())?;
        Ok((node, sub))
    };
    // The node stays alive as long as its port.
    let (_node, mut sub) = match setup() {
        Ok(s) => {
            let _ = ready.send(Ok(()));
            s
        }
        Err(e) => {
            let _ = ready.send(Err(e));
            return Err(IoStageError::NotStarted);
        }
    };
    log.log(Level::Info, "io stage subscribed to its step channel", []);
    let lead_ticks = MIN_LEAD_S * clock_freq;
    let idle_wait = Duration::from_millis(5);
    let mut report = IoReport::default();
    let mut warm: Option<AllocCounter> = None;
    loop {
        let was_done = done.load(Ordering::Acquire);
        let got = sub
            .recv_timeout_with(idle_wait, |b| *b)
            .map_err(IoStageError::Receive)?;
        let Some(batch) = got else {
            if was_done {
                break;
            }
            continue;
        };
        if let Ok(mut h) = hists.handoff.try_lock() {
            h.record(mono_ns().saturating_sub(batch.t_ns));
        }
        let now_clock = link.clock().clock_at(McuLink::system_now());
        for m in batch.messages() {
            if m.req_clock > 0 && (m.req_clock as f64) < now_clock + lead_ticks {
                log.log(
                    Level::Error,
                    "io stage fell behind: req_clock, ms before due",
                    [
                        Arg::U(m.req_clock),
                        Arg::F((m.req_clock as f64 - now_clock) / clock_freq * 1e3),
                    ],
                );
                return Err(IoStageError::FellBehind {
                    clock: m.req_clock,
                    ahead_ms: (m.req_clock as f64 - now_clock) / clock_freq * 1e3,
                    min_ms: MIN_LEAD_S * 1e3,
                });
            }
            let cmd = Cmd::from_bytes(m.bytes()).ok_or(IoStageError::Malformed)?;
            if m.req_clock == 0 && m.min_clock == 0 {
                link.send(cmd)?;
            } else {
                link.send_clocked(cmd, m.min_clock, m.req_clock)?;
            }
        }
        report.batches += 1;
        // Pairs with the planner's Acquire load before homing talks to the link directly.
        consumed.store(batch.seq + 1, Ordering::Release);
        if report.batches == WARMUP_BATCHES {
            warm = Some(AllocCounter::snapshot());
        }
    }
    report.allocations_after_warmup = warm.map(|w| AllocCounter::snapshot().since(w).allocations());
    report.batches_after_warmup = report.batches.saturating_sub(WARMUP_BATCHES);
    log.log(Level::Info, "io stage done: batches", [Arg::U(report.batches)]);
    Ok(report)
}
