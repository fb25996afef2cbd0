//! The live print on real-time threads:
//!
//! ```text
//! [planner] G-code → lookahead → steps → compression ──StepBatch (iceoryx2)──► [io-mcu] ──► link IO thread ──► pty/tty
//!  core 0, SCHED_FIFO                                   cadence/<instance>/mcu/mcu/steps      core 1, SCHED_FIFO
//! ```
//!
//! The planner thread runs the G-code loop with flow control (buffered print time between a
//! low and a high water mark) and publishes encoded step messages in batches over iceoryx2
//! shared memory (no loss: safe overflow off, back-pressure, sequence numbers). Each MCU with
//! steppers has its own channel (`cadence/<instance>/mcu/<mcu>/steps`) and its own IO stage
//! thread (`io-<mcu>`), whose steps the planner counts in that MCU's clock (see [`crate::step_stream`]). An
//! IO stage subscribes, checks each step message's lead (in its MCU's clock) before handing it
//! to the MCU link, and the link's own IO thread writes it. Histograms recorded on the way: lead margin of every step
//! message (in the link IO thread, when its bytes leave), hand-off latency planner → IO stage,
//! and each stage's wake-up lateness. When the OS refuses pinning or SCHED_FIFO, the threads run
//! anyway and rt-core reports once which guarantees are off.
//!
//! The planner reaches the MCUs through [`McuSide`]: in this process (the IO stage is a thread
//! here; homing works) or in a `cadence serve --role io` process (`--io-process`, see
//! [`crate::io_process`]): then the dictionary, move queue size and clock snapshots come over shared memory
//! (the main MCU's only: a printer with steppers on other MCUs is refused there).
//!
//! Logging during a print: the threads push fixed-size records to rt-core's logger thread
//! ([`crate::logging::Logging`]), the only one that formats or writes; nobody prints from a real-time thread.
//! Telemetry is published by a thread of its own ([`telemetry_thread`]), off the planner's loop.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

use links::mcu::McuLink;
use planner::pipeline::Pipeline;
use rt_core::logger::{Level, LoggerHandle};
use rt_core::os::apply_rt;
use rt_core::shm::steps_service_name;

use crate::events::SessionShared;
use crate::gcode_feed::GcodeInput;
use crate::hardware::Machine;
use crate::io_stage::{io_stage, AfterWarmup, IoReport, IoStageError, WARMUP_BATCHES};
use crate::latency::{Hists, ALL_SOURCES};
use crate::mcus::{McuConn, McuError, Mcus};
use crate::planner_thread::{planner_stage, McuSide, Planned, PlannerError, PlannerStage};
use crate::realtime::RtConfig;
use crate::step_stream::StepStreams;
use crate::summary::Summary;
use crate::telemetry::telemetry_thread;
use crate::MIN_LEAD_S;

/// How a live print runs: when it started, the simulator's time scale, thread placement and
/// where its histograms go.
#[derive(Debug, Clone, Copy)]
pub(crate) struct LiveRun<'a> {
    pub started: Instant,
    pub scale: f64,
    /// Maximum step time error of the compression (s).
    pub max_error_s: f64,
    pub rt: &'a RtConfig,
    pub hists: &'a Arc<Hists>,
    pub log: &'a LoggerHandle,
    /// A printer session's stop flag, status and events (`None`: a plain print).
    pub session: Option<&'a SessionShared>,
    /// Service instance: the step channels are `cadence/<instance>/mcu/<mcu>/steps`, the
    /// telemetry `cadence/<instance>/telemetry` (a print uses `p<pid>`).
    pub instance: &'a str,
}

/// Why a live print failed.
#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    /// A thread of the print did not start (`what`: which one).
    #[error("cannot start the {what}: {source}")]
    Spawn {
        what: String,
        #[source]
        source: std::io::Error,
    },
    /// A thread of the print panicked (`what`: which one).
    #[error("{what} panicked")]
    Panicked { what: &'static str },
    /// An MCU's IO stage did not subscribe to its step channel.
    #[error("io stage of mcu '{mcu}': {source}")]
    IoStageStart {
        mcu: String,
        #[source]
        source: IoStageError,
    },
    /// An MCU's IO stage did not report ready in time.
    #[error("io stage of mcu '{mcu}' did not start within 10 s")]
    IoStageTimeout { mcu: String },
    /// An IO stage stopped the print.
    #[error(transparent)]
    IoStage(#[from] IoStageError),
    /// The planner thread stopped the print.
    #[error(transparent)]
    Planner(Box<PlannerError>),
    /// An MCU shut down.
    #[error(transparent)]
    Mcu(#[from] McuError),
    /// An MCU's link failed while the print's end was awaited.
    #[error("mcu '{mcu}': {source}")]
    Link {
        mcu: String,
        #[source]
        source: links::mcu::LinkError,
    },
    /// An MCU's clock did not reach the print's last step.
    #[error("mcu '{mcu}': its clock did not reach the end of the print in time")]
    ClockStalled { mcu: String },
    /// A stepper's MCU is not connected.
    #[error("[{stepper}]: mcu '{mcu}' is not connected")]
    NotConnected { stepper: String, mcu: String },
    /// An MCU's dictionary cannot encode the position query.
    #[error("mcu '{mcu}': {source}")]
    Encode {
        mcu: String,
        #[source]
        source: links::dict::DictError,
    },
    /// A stepper's position could not be read back.
    #[error("mcu '{mcu}': [{stepper}] position: {source}")]
    PositionQuery {
        mcu: String,
        stepper: String,
        #[source]
        source: links::mcu::LinkError,
    },
    /// No position was read back for a stepper.
    #[error("{stepper}: no position read back from the MCU")]
    NoPosition { stepper: String },
    /// An MCU's step count differs from the host's.
    #[error("{stepper}: mcu '{mcu}' reports position {mcu_pos} steps but the host sent {host_pos}")]
    PositionMismatch {
        stepper: String,
        mcu: String,
        mcu_pos: i64,
        host_pos: i64,
    },
    /// A step command reached its MCU with less than the minimum lead.
    #[error("a step command reached mcu '{mcu}' with only {lead_ms:.1} ms lead (at least {min_ms:.0} ms required)")]
    LowLead { mcu: String, lead_ms: f64, min_ms: f64 },
}

from_boxed!(LiveError, Planner, PlannerError);

/// The older string-typed layers' view (the message as shown).
impl From<LiveError> for String {
    fn from(e: LiveError) -> String {
        e.to_string()
    }
}

/// What the print's threads share besides the run settings.
#[derive(Debug, Clone, Copy)]
struct PrintParts<'a> {
    machine: &'a Machine,
    mcus: &'a Mcus,
    /// `consumed[k]`: the batches stream k's IO stage took.
    consumed: &'a [AtomicU64],
    heaters: &'a crate::heaters::runtime::HeaterShared,
    /// Set when the planner is done (or the print fails): the IO stages drain and stop.
    done: &'a AtomicBool,
}

/// An IO stage thread.
type IoHandle<'scope> = std::thread::ScopedJoinHandle<'scope, Result<IoReport, IoStageError>>;

/// Runs the live print of `gcode` on the connected MCUs: one IO stage thread per MCU with
/// steppers (each subscribed to its own step channel), the planner thread feeding them all.
pub(crate) fn print_on(
    gcode: GcodeInput,
    machine: &Machine,
    mcus: &Mcus,
    run: &LiveRun<'_>,
) -> Result<Summary, LiveError> {
    let run = *run;
    // (MCU index, step channel) of each MCU with steppers, the main one first.
    let streams: Vec<(usize, String)> = mcus
        .stream_params(machine)
        .iter()
        .map(|m| (m.mcu_index, steps_service_name(run.instance, m.name)))
        .collect();
    let done_flag = AtomicBool::new(false);
    let consumed_counts: Vec<AtomicU64> = streams.iter().map(|_| AtomicU64::new(0)).collect();
    let heater_state = Arc::new(crate::heaters::runtime::HeaterShared::new(&machine.thermal));
    if let Some(s) = run.session {
        // A session's status reads the heaters (its first print's loop: one per session).
        let _ = s.heaters.set(heater_state.clone());
    }
    let parts = PrintParts {
        machine,
        mcus,
        consumed: &consumed_counts,
        heaters: &heater_state,
        done: &done_flag,
    };

    std::thread::scope(|scope| {
        // The heater loop runs for the whole print (every heater off when it ends).
        let heater_thread = std::thread::Builder::new()
            .name("heaters".to_string())
            .spawn_scoped(scope, move || {
                crate::heaters::runtime::run(mcus, &machine.thermal, parts.heaters)
            })
            .map_err(|source| spawn_error("heater thread", source))?;
        // Whatever way this closure returns, the heater loop ends (before the scope joins it).
        let _stop_heaters = crate::heaters::runtime::StopOnDrop(parts.heaters);
        let stop = || {
            parts.done.store(true, Ordering::Release);
            parts.heaters.stop.store(true, Ordering::Release);
        };
        let mut ios = Vec::with_capacity(streams.len());
        for ((mcu_index, service), counter) in streams.iter().zip(parts.consumed) {
            match start_io_stage(scope, &mcus.list[*mcu_index], service, counter, run, parts.done) {
                Ok(io) => ios.push(io),
                Err(e) => {
                    stop();
                    return Err(e);
                }
            }
        }
        let planner = match start_planner(scope, gcode, parts, run) {
            Ok(p) => p,
            Err(e) => {
                stop();
                return Err(e);
            }
        };
        let (instance, hists, started, done) = (run.instance, run.hists, run.started, parts.done);
        let telemetry = std::thread::Builder::new()
            .name("telemetry".to_string())
            .spawn_scoped(scope, move || {
                telemetry_thread(instance, hists, started, ALL_SOURCES, done)
            })
            .map_err(|source| spawn_error("telemetry thread", source))?;
        let planned = planner.join();
        stop();
        let heater_result = heater_thread.join();
        let planned = planned.map_err(|_| LiveError::Panicked {
            what: "the planner thread",
        })?;
        match heater_result {
            Ok(Ok(())) => {}
            Ok(Err(e)) => {
                run.log.log(Level::Warn, "heater loop failed (see stderr)", []);
                eprintln!("cadence: heaters: {e}");
            }
            Err(_) => {
                return Err(LiveError::Panicked {
                    what: "the heater thread",
                })
            }
        }
        if let Ok(Err(e)) = telemetry.join() {
            run.log.log(Level::Warn, "telemetry failed (see stderr)", []);
            eprintln!("cadence: telemetry: {e}");
        }
        conclude(planned, ios, parts, run.hists, run.scale)
    })
}

fn spawn_error(what: &str, source: std::io::Error) -> LiveError {
    LiveError::Spawn {
        what: what.to_string(),
        source,
    }
}

/// Starts the IO stage thread of MCU `conn` on step channel `service` and waits (bounded)
/// until it subscribed.
fn start_io_stage<'scope, 'env: 'scope>(
    scope: &'scope std::thread::Scope<'scope, 'env>,
    conn: &'env McuConn,
    service: &'env str,
    counter: &'env AtomicU64,
    run: LiveRun<'env>,
    done: &'env AtomicBool,
) -> Result<IoHandle<'scope>, LiveError> {
    let (link, clock_freq) = (&conn.link, conn.clock_freq);
    let (ready_tx, ready_rx) = mpsc::channel();
    let io_spec = run.rt.io_spec(&conn.name);
    let (hists, log) = (run.hists, run.log);
    let io = std::thread::Builder::new()
        .name(io_spec.name.clone())
        .spawn_scoped(scope, move || {
            apply_rt(&io_spec);
            let log = log.with_tag("io");
            io_stage(link, service, ready_tx, done, counter, hists, clock_freq, &log)
        })
        .map_err(|source| spawn_error(&format!("IO stage thread of mcu '{}'", conn.name), source))?;
    match ready_rx.recv_timeout(Duration::from_secs(10)) {
        Ok(Ok(())) => Ok(io),
        Ok(Err(source)) => Err(LiveError::IoStageStart {
            mcu: conn.name.clone(),
            source,
        }),
        Err(_) => Err(LiveError::IoStageTimeout {
            mcu: conn.name.clone(),
        }),
    }
}

/// Starts the planner thread; its end sets `done` (the IO stages drain and stop).
fn start_planner<'scope, 'env: 'scope>(
    scope: &'scope std::thread::Scope<'scope, 'env>,
    gcode: GcodeInput,
    parts: PrintParts<'env>,
    run: LiveRun<'env>,
) -> Result<std::thread::ScopedJoinHandle<'scope, Result<Planned, PlannerError>>, LiveError> {
    let planner_spec = run.rt.planner_spec();
    std::thread::Builder::new()
        .name("planner".to_string())
        .spawn_scoped(scope, move || {
            apply_rt(&planner_spec);
            let log = run.log.with_tag("planner");
            let stage = PlannerStage {
                machine: parts.machine,
                side: McuSide::Local(parts.mcus),
                scale: run.scale,
                max_error_s: run.max_error_s,
                instance: run.instance,
                consumed: parts.consumed,
                hists: run.hists,
                log: &log,
                rt: run.rt,
                session: run.session,
                heaters: Some(parts.heaters),
            };
            let r = planner_stage(gcode, &stage);
            parts.done.store(true, Ordering::Release);
            r
        })
        .map_err(|source| spawn_error("planner thread", source))
}

/// The print's end: the IO stages joined (a failed one is the root cause of a planner
/// hand-off error: reported first), the planner's result, the positions and leads checked, the
/// summary completed.
fn conclude(
    planned: Result<Planned, PlannerError>,
    ios: Vec<IoHandle<'_>>,
    parts: PrintParts<'_>,
    hists: &Hists,
    scale: f64,
) -> Result<Summary, LiveError> {
    let (io_total, io_allocs, io_error) = join_io_stages(ios);
    if let Some(e) = io_error {
        return Err(e);
    }
    let (mut summary, pipeline, streams, planner_allocs, _) = planned?;
    finish_print(
        parts.mcus,
        parts.machine,
        &pipeline,
        &streams,
        &mut summary,
        scale,
    )?;
    summary.extra.extend(hists.report(summary.clock_freq));
    summary.extra.push(allocation_line(
        planner_allocs,
        streams.mcus.len(),
        &io_total,
        io_allocs,
    ));
    Ok(summary)
}

/// Connects and configures the MCUs for a live print: each link's lead-margin hook records
/// into a new [`Hists`] (and logs a message that left late), each link's IO thread runs with
/// `rt`'s settings.
pub(crate) fn connect_mcus(
    cfg: &sysconfig::printer::PrinterConfig,
    machine: &Machine,
    time_scale: f64,
    trace: Option<std::path::PathBuf>,
    rt: &RtConfig,
    logging: &crate::logging::Logging,
) -> Result<(Arc<Hists>, Mcus), crate::mcus::McuError> {
    let hists = Hists::new();
    let opts = crate::mcus::ConnectOptions {
        time_scale,
        trace,
        lead_hooks: Some(hists.lead_hooks(logging.handle("io-link"))),
        io_rt: Some(rt.link_spec()),
    };
    let mcus = Mcus::connect(cfg, machine, opts)?;
    hists.set_min_lead(&mcus);
    Ok((hists, mcus))
}

/// Joins the IO stage threads: their batches in all, their allocations after warm-up (`None`
/// when one of them could not count) and the first error.
fn join_io_stages(ios: Vec<IoHandle<'_>>) -> (IoReport, Option<u64>, Option<LiveError>) {
    let mut io_total = IoReport::default();
    let mut io_allocs = Some(0u64);
    let mut io_error = None;
    for io in ios {
        let r = io
            .join()
            .map_err(|_| LiveError::Panicked {
                what: "an IO stage thread",
            })
            .and_then(|r| r.map_err(LiveError::from));
        match r {
            Ok(r) => {
                io_total.batches += r.batches;
                io_total.batches_after_warmup += r.batches_after_warmup;
                io_allocs = match (io_allocs, r.allocations_after_warmup) {
                    (Some(a), Some(b)) => Some(a + b),
                    // A stage that never warmed up (few batches) counts nothing.
                    (a, None) if r.batches < WARMUP_BATCHES => a,
                    _ => None,
                };
            }
            Err(e) => io_error = io_error.or(Some(e)),
        }
    }
    (io_total, io_allocs, io_error)
}

/// The summary's `allocations after warm-up` line.
fn allocation_line(
    planner_allocs: Option<AfterWarmup>,
    streams: usize,
    io_total: &IoReport,
    io_allocs: Option<u64>,
) -> String {
    format!(
        "allocations after warm-up: planner {}, io stage{} {}; {} batches in all",
        planner_allocs.map_or("n/a".to_string(), |n| n.to_string()),
        if streams > 1 { "s" } else { "" },
        io_allocs
            .filter(|_| io_total.batches >= WARMUP_BATCHES)
            .map_or("n/a".to_string(), |n| {
                AfterWarmup {
                    allocations: n,
                    batches: io_total.batches_after_warmup,
                    ..AfterWarmup::default()
                }
                .to_string()
            }),
        io_total.batches
    )
}

/// Times the final positions are read again while they differ from the host's: a simulated
/// MCU that the machine stalled answers the query waiting in its input before the step timers
/// that fell due meanwhile (seen once: 183 steps short, its steps up to 1.3 s of MCU time
/// late), and has caught up a moment later; steps really lost differ every time.
const POSITION_REREADS: usize = 3;
/// Wall time between two reads of [`POSITION_REREADS`].
const POSITION_REREAD_GAP: Duration = Duration::from_millis(200);

/// Waits for every MCU to execute its last step, reads the positions back and checks them,
/// and checks every MCU's lead.
fn finish_print(
    mcus: &Mcus,
    machine: &Machine,
    pipeline: &Pipeline,
    streams: &StepStreams,
    summary: &mut Summary,
    scale: f64,
) -> Result<(), LiveError> {
    let ends = streams.end_clocks();
    let mcu_positions = reread_while_different(
        &pipeline.stepper_positions(),
        POSITION_REREADS,
        POSITION_REREAD_GAP,
        || read_final_positions(mcus, machine, &ends, scale),
    )?;
    check_positions(machine, pipeline, &streams.steps_sent(), &mcu_positions, summary)?;
    for m in &mcus.list {
        check_min_lead(&m.name, m.link.stats().min_lead_margin_ticks, m.clock_freq)?;
    }
    Ok(())
}

/// `read()`, and again up to `rereads` times `gap` apart while it differs from `host`: the
/// last reading.
fn reread_while_different<E>(
    host: &[i64],
    rereads: usize,
    gap: Duration,
    mut read: impl FnMut() -> Result<Vec<i64>, E>,
) -> Result<Vec<i64>, E> {
    let mut positions = read()?;
    for _ in 0..rereads {
        if positions == host {
            break;
        }
        std::thread::sleep(gap);
        positions = read()?;
    }
    Ok(positions)
}

/// Waits (bounded) until each MCU of `ends` (MCU index, last step clock in its own clock)
/// executed everything, then reads each stepper's position back from its MCU, in machine
/// order, in the host's sign convention (dir pin inversion undone).
pub(crate) fn read_final_positions(
    mcus: &Mcus,
    machine: &Machine,
    ends: &[(usize, u64)],
    scale: f64,
) -> Result<Vec<i64>, LiveError> {
    for &(i, end_clock) in ends {
        let Some(m) = mcus.list.get(i) else {
            continue;
        };
        let link = &m.link;
        let clock_freq = m.clock_freq;
        let now_s = || link.clock().clock_at(McuLink::system_now()) / clock_freq;
        let wait_s = (end_clock as f64 / clock_freq - now_s()).max(0.0) / scale + 5.0;
        let deadline = Instant::now() + Duration::from_secs_f64(wait_s);
        link.wait_idle(Duration::from_secs_f64(wait_s))
            .map_err(|source| LiveError::Link {
                mcu: m.name.clone(),
                source,
            })?;
        while now_s() * clock_freq < end_clock as f64 + 0.01 * clock_freq {
            mcus.check()?;
            if Instant::now() > deadline {
                return Err(LiveError::ClockStalled { mcu: m.name.clone() });
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }
    mcus.check()?;
    let mut out = Vec::with_capacity(machine.steppers.len());
    for s in &machine.steppers {
        let m = mcus.get(&s.mcu).ok_or_else(|| LiveError::NotConnected {
            stepper: s.name.clone(),
            mcu: s.mcu.clone(),
        })?;
        let link = &m.link;
        let q = link
            .dictionary()
            .encode("stepper_get_position", &[s.oid as i64])
            .map_err(|source| LiveError::Encode {
                mcu: m.name.clone(),
                source,
            })?;
        // Retried: an answer lost on a noisy line is not retransmitted (the query is idempotent).
        let ask = || {
            link.query(
                q,
                "stepper_position",
                Some(("oid", s.oid as i64)),
                Duration::from_secs(1),
            )
        };
        let mut reply = ask();
        for _ in 0..3 {
            if reply.is_ok() || link.error().is_some() {
                break;
            }
            reply = ask();
        }
        let reply = reply.map_err(|source| LiveError::PositionQuery {
            mcu: m.name.clone(),
            stepper: s.name.clone(),
            source,
        })?;
        let raw = reply.get("pos").unwrap_or(0);
        out.push(if s.dir_pin.invert { -raw } else { raw });
    }
    Ok(out)
}

/// Fills the summary's rows and fails if an MCU position differs from the host's.
/// `steps_sent` is per stepper in machine order.
pub(crate) fn check_positions(
    machine: &Machine,
    pipeline: &Pipeline,
    steps_sent: &[u64],
    mcu_positions: &[i64],
    summary: &mut Summary,
) -> Result<(), LiveError> {
    let host_positions = pipeline.stepper_positions();
    let commanded = pipeline.position();
    for (i, s) in machine.steppers.iter().enumerate() {
        let Some(&mcu_pos) = mcu_positions.get(i) else {
            return Err(LiveError::NoPosition {
                stepper: s.name.clone(),
            });
        };
        let host_pos = host_positions.get(i).copied().unwrap_or(0);
        summary.rows.push((
            s.name.clone(),
            steps_sent.get(i).copied().unwrap_or(0),
            mcu_pos,
            host_pos,
            commanded.get(s.axis).copied().unwrap_or(0.0),
        ));
    }
    if let Some((name, _, m, h, _)) = summary.rows.iter().find(|r| r.2 != r.3) {
        let mcu = machine
            .steppers
            .iter()
            .find(|s| &s.name == name)
            .map_or("?", |s| s.mcu.as_str());
        return Err(LiveError::PositionMismatch {
            stepper: name.clone(),
            mcu: mcu.to_string(),
            mcu_pos: *m,
            host_pos: *h,
        });
    }
    Ok(())
}

/// Fails if a step command reached MCU `mcu` (clock `clock_freq`) with less than the
/// required lead.
pub(crate) fn check_min_lead(
    mcu: &str,
    min_margin_ticks: Option<i64>,
    clock_freq: f64,
) -> Result<(), LiveError> {
    if let Some(margin) = min_margin_ticks {
        if (margin as f64) < MIN_LEAD_S * clock_freq {
            return Err(LiveError::LowLead {
                mcu: mcu.to_string(),
                lead_ms: margin as f64 / clock_freq * 1e3,
                min_ms: MIN_LEAD_S * 1e3,
            });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn final_positions_are_read_again_until_the_mcu_caught_up() {
        // A stalled MCU answers first with steps still owed, then with all of them.
        let mut readings = vec![vec![-1497, 10], vec![-1680, 10]].into_iter();
        let mut reads = 0;
        let got = reread_while_different(&[-1680, 10], 3, Duration::ZERO, || {
            reads += 1;
            readings.next().ok_or("no more readings")
        });
        assert_eq!(got, Ok(vec![-1680, 10]));
        assert_eq!(reads, 2);
        // Steps really lost: the same difference every time, reported after the rereads.
        let mut reads = 0;
        let got = reread_while_different(&[-1680], 3, Duration::ZERO, || {
            reads += 1;
            Ok::<_, ()>(vec![-1497])
        });
        assert_eq!(got, Ok(vec![-1497]));
        assert_eq!(reads, 4);
        // Equal at once: read once.
        let mut reads = 0;
        let _ = reread_while_different(&[5], 3, Duration::ZERO, || {
            reads += 1;
            Ok::<_, ()>(vec![5])
        });
        assert_eq!(reads, 1);
    }
}
