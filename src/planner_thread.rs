//! The planner thread: G-code → lookahead → steps → compression → encoded step messages,
//! published in batches over iceoryx2 shared memory (one lossless channel per MCU with
//! steppers, `cadence/<instance>/mcu/<mcu>/steps`), paced between a low and a high water mark
//! of buffered print time. A step that would reach its MCU with less than [`MIN_LEAD_S`] of
//! lead stops the print before it is sent. G28 and the probe commands leave the streaming loop:
//! the hand-off is drained and [`crate::homing`] drives the MCUs directly.
//!
//! The planner reaches the MCUs through [`McuSide`]: in this process (the IO stage is a thread
//! here; homing works) or in a `cadence serve --role io` process (see [`crate::io_process`]):
//! then the dictionary, move queue size and clock snapshots come over shared memory.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use links::clocksync::ClockEstimate;
use links::dict::Cmd;
use links::mcu::McuLink;
use planner::pipeline::Pipeline;
use planner::stepgen::StepCmd;
use rt_core::alloc_count::AllocCounter;
use rt_core::logger::{Arg, Level, LoggerHandle};
use rt_core::shm::{open_node, steps_service_name, ChannelConfig, ShmPublisher, StepBatch, WireMsg};

use crate::accessories::Accessories;
use crate::events::{Event, MotionStatus, PrinterState, SessionShared};
use crate::gcode_feed::{plan_file, FeedError, FeedTarget, GcodeInput, MotionCmd};
use crate::hardware::Machine;
use crate::homing::{run_motion, HomingCtx};
use crate::io_stage::AfterWarmup;
use crate::latency::{mono_ns, Hists};
use crate::mcus::Mcus;
use crate::realtime::RtConfig;
use crate::step_stream::sink::Sink;
use crate::step_stream::{McuParams, StepStreams, StreamError};
use crate::summary::Summary;
use crate::MIN_LEAD_S;

/// Why the planner thread stopped, or could not start.
#[derive(Debug, thiserror::Error)]
pub enum PlannerError {
    /// printer.cfg has no `[mcu]`.
    #[error("the printer has no MCU")]
    NoMcu,
    /// Fewer or more IO stages than step streams (a bug).
    #[error("internal error: {stages} IO stages for {streams} step streams")]
    StageCount { stages: usize, streams: usize },
    /// The shared-memory node or a channel port failed.
    #[error(transparent)]
    Shm(#[from] rt_core::shm::ShmError),
    /// The step channel to an MCU's IO stage could not be opened.
    #[error("planner → io hand-off of mcu '{mcu}': {source}")]
    Channel {
        mcu: String,
        #[source]
        source: rt_core::shm::ShmError,
    },
    /// An IO stage did not subscribe to its step channel in time.
    #[error("planner → io hand-off: the IO stage of mcu '{mcu}' never subscribed")]
    NeverSubscribed { mcu: String },
    /// The IO stages did not take the planned steps before homing.
    #[error("the IO stages did not take the planned steps before homing")]
    HandoffNotDrained,
    /// The step streams could not be set up or fed.
    #[error(transparent)]
    Stream(#[from] StreamError),
    /// The planner could not be set up or refused a time.
    #[error(transparent)]
    Plan(#[from] planner::machine::PlanError),
    /// The printer's `[gcode_macro]`s or `[save_variables]` file.
    #[error(transparent)]
    Macros(#[from] crate::hardware::MacrosError),
    /// An MCU shut down or its link failed.
    #[error(transparent)]
    Mcu(#[from] crate::mcus::McuError),
    /// The IO process refuses this printer (steppers off the main MCU).
    #[error(transparent)]
    OffMainMcu(#[from] crate::io_process::OffMainMcu),
    /// The IO process failed or exited (its reason).
    #[error("{reason}")]
    IoProcess { reason: String },
    /// The session was stopped (its reason).
    #[error("{reason}")]
    Stopped { reason: String },
    /// A heater fault shut the printer down (its reason).
    #[error("{reason}")]
    ThermalFault { reason: String },
    /// The G-code feed stopped: a line refused, a failed homing, a shutdown (located at its
    /// file and line by the feed).
    #[error(transparent)]
    Feed(Box<FeedError<PlannerError>>),
    /// G28, a probe or a TMC command with the MCUs in the loop failed.
    #[error(transparent)]
    Homing(Box<crate::homing::HomingError>),
    /// A heater or fan command was refused.
    #[error(transparent)]
    Heat(#[from] crate::heaters::feed::HeatError),
    /// A heater or fan to drive while the IO stage is in another process.
    #[error(
        "heaters and fans are driven only with the IO stage in this process (the heater loop \
         reads and drives their MCU objects over the MCU link): print without \
         --io-process/--io-attach"
    )]
    HeatersNeedLocalIo,
    /// A step command would have reached its MCU with less than the minimum lead.
    #[error(
        "the planner fell behind: a step for {stepper} on mcu '{mcu}' at its clock {clock} was \
         ready only {ahead_ms:.1} ms before it is due (at least {min_ms:.0} ms required); print \
         stopped before sending it"
    )]
    FellBehind {
        stepper: String,
        mcu: String,
        clock: u64,
        ahead_ms: f64,
        min_ms: f64,
    },
    /// Homing or probing on a print whose IO stage is in another process.
    #[error(
        "{what} the in-process IO stage (triggers are relayed through the MCU link): \
         print without --io-process/--io-attach"
    )]
    MotionNeedsLocalIo { what: &'static str },
    /// M112.
    #[error("Shutdown due to M112 command")]
    EmergencyStop,
    /// PID_CALIBRATE ended without a result.
    #[error("pid_calibrate interrupted")]
    CalibrationInterrupted,
    /// PID_CALIBRATE WRITE_FILE=1 could not write its samples.
    #[error("PID_CALIBRATE: {path}: {source}")]
    CalibrationFile {
        path: &'static str,
        #[source]
        source: std::io::Error,
    },
    /// SAVE_CONFIG on the built-in printer.
    #[error(
        "SAVE_CONFIG: the built-in simulated printer has no config file to save to (give a printer.cfg)"
    )]
    NoConfigFile,
    /// SAVE_CONFIG could not write printer.cfg.
    #[error(transparent)]
    Save(#[from] sysconfig::autosave::SaveError),
}

from_boxed!(PlannerError, Feed, FeedError<PlannerError>);
from_boxed!(PlannerError, Homing, crate::homing::HomingError);

/// `ipc::Service` with pooled per-loan state: a loan allocates nothing after warm-up (see
/// rt-core's `shm::pooled`); it talks to `ipc::Service` ports of other processes unchanged.
pub(crate) type Ipc = rt_core::shm::pooled::Ipc;

/// Where the planner thread's MCU-side needs come from.
#[derive(Debug, Clone, Copy)]
pub(crate) enum McuSide<'a> {
    /// The MCUs are connected in this process (the IO stage is a thread here).
    Local(&'a Mcus),
    /// The MCUs live in a `cadence serve --role io` process.
    Remote(&'a crate::io_process::planner_side::RemoteMcu),
}

impl<'a> McuSide<'a> {
    /// What the step streams need of each MCU that gets one (the main MCU first).
    fn stream_params(&self, machine: &Machine) -> Result<Vec<McuParams<'a>>, PlannerError> {
        match *self {
            McuSide::Local(m) => Ok(m.stream_params(machine)),
            McuSide::Remote(r) => {
                crate::io_process::planner_side::check_single_mcu(machine)?;
                Ok(vec![McuParams {
                    name: &r.name,
                    mcu_index: 0,
                    dict: &r.dict,
                    clock_freq: r.clock_freq,
                    move_count: r.move_count,
                }])
            }
        }
    }

    /// The clock fit of MCU `mcu_index` (in `[mcu]` order; lock-free).
    fn clock(&self, mcu_index: usize) -> ClockEstimate {
        match self {
            McuSide::Local(m) => m
                .list
                .get(mcu_index)
                .map_or(ClockEstimate::INVALID, |c| c.link.clock()),
            McuSide::Remote(r) => r.clock(),
        }
    }

    /// An MCU shutdown or a failed IO process, as an error.
    fn check(&self) -> Result<(), PlannerError> {
        match self {
            McuSide::Local(m) => Ok(m.check()?),
            McuSide::Remote(r) => match r.failure() {
                Some(reason) => Err(PlannerError::IoProcess { reason }),
                None => Ok(()),
            },
        }
    }
}

/// The planner side of the shared-memory hand-off: packs messages into batches.
pub(crate) struct ShmSink {
    publisher: ShmPublisher<Ipc, StepBatch>,
    batch: StepBatch,
}

impl ShmSink {
    fn push(&mut self, m: WireMsg) -> Result<(), StreamError> {
        if !self.batch.push(m) {
            self.flush()?;
            self.batch.push(m);
        }
        Ok(())
    }

    /// Publishes the pending batch (if any).
    fn flush(&mut self) -> Result<(), StreamError> {
        if self.batch.count == 0 {
            return Ok(());
        }
        let batch = self.batch;
        self.publisher
            .send_with(|b| {
                *b = batch;
                b.t_ns = mono_ns();
            })
            .map_err(StreamError::Handoff)?;
        self.batch.count = 0;
        Ok(())
    }
}

impl Sink for ShmSink {
    fn send(&mut self, cmd: Cmd) -> Result<(), StreamError> {
        self.push(WireMsg::new(0, 0, cmd.as_bytes()).unwrap_or_default())
    }
    fn send_clocked(&mut self, cmd: Cmd, min_clock: u64, req_clock: u64) -> Result<(), StreamError> {
        self.push(WireMsg::new(min_clock, req_clock, cmd.as_bytes()).unwrap_or_default())
    }
}

/// What the planner thread hands back: the summary so far, the pipeline and step streams
/// (final positions, last step clocks), its allocations after warm-up and the number of step
/// batches published per stream.
pub(crate) type Planned = (Summary, Pipeline, StepStreams, Option<AfterWarmup>, Vec<u64>);

/// True when `cmd` would turn a heater or fan on or wait on a temperature (where no heater
/// loop runs, it cannot be carried out; turning things off and reports can).
fn drives_output(cmd: &crate::heaters::gcode::HeatCmd) -> bool {
    use crate::heaters::gcode::HeatCmd;
    match cmd {
        HeatCmd::Set { target, .. } => *target > 0.0,
        HeatCmd::Fan { speed } | HeatCmd::FanSpeed { speed, .. } => *speed > 0.0,
        HeatCmd::Wait { .. } | HeatCmd::PidCalibrate { .. } | HeatCmd::TemperatureFanTarget { .. } => true,
        _ => false,
    }
}

/// What the planner thread works with besides its G-code.
#[derive(Debug, Clone, Copy)]
pub(crate) struct PlannerStage<'a> {
    pub machine: &'a Machine,
    pub side: McuSide<'a>,
    /// MCU seconds per wall second (the simulator's time scale).
    pub scale: f64,
    /// Maximum step time error of the compression (s).
    pub max_error_s: f64,
    /// Service instance of the step channels (`cadence/<instance>/mcu/<mcu>/steps`).
    pub instance: &'a str,
    /// `consumed[k]`: the batches stream k's IO stage took.
    pub consumed: &'a [AtomicU64],
    pub hists: &'a Hists,
    pub log: &'a LoggerHandle,
    pub rt: &'a RtConfig,
    /// A printer session's stop flag, status and events (`None`: a plain print).
    pub session: Option<&'a SessionShared>,
    /// The heater thread's state (`None`: no heater loop, heater commands are only recorded).
    pub heaters: Option<&'a crate::heaters::runtime::HeaterShared>,
}

/// The planner thread: G-code → pipeline → step messages into shared memory (one channel per
/// MCU with steppers: `cadence/<instance>/mcu/<mcu>/steps`), paced.
pub(crate) fn planner_stage(gcode: GcodeInput, st: &PlannerStage<'_>) -> Result<Planned, PlannerError> {
    let params = st.side.stream_params(st.machine)?;
    let Some(main) = params.first().copied() else {
        return Err(PlannerError::NoMcu);
    };
    if st.consumed.len() != params.len() {
        return Err(PlannerError::StageCount {
            stages: st.consumed.len(),
            streams: params.len(),
        });
    }
    let (node, _) = open_node::<Ipc>(&format!("cadence-planner-{}", std::process::id()))?;
    let sinks = open_sinks(&node, st.instance, &params)?;
    let clock_freq = main.clock_freq;
    let side = st.side;
    let print_now = || side.clock(main.mcu_index).clock_at(McuLink::system_now()) / clock_freq;
    // Start far enough ahead that the first batch is planned long before it is due.
    let start = print_now() + (0.5f64).max(0.25 * st.scale);
    let streams = StepStreams::new(st.machine, &params)?;
    let maps = streams.clock_maps(|i| side.clock(i))?;
    let mut pipeline = Pipeline::with_clocks(
        st.machine.pipeline_config(clock_freq, st.max_error_s),
        start,
        st.machine.options,
        &maps,
    )?;
    let mut run = PlannerRun::new(st, main, sinks, streams, params.len());
    if let Some(h) = st.heaters {
        // A print's steppers are on from its start ([controller_fan]); a session says when
        // it goes idle.
        h.motors_on.store(true, std::sync::atomic::Ordering::Release);
    }
    st.log.log(
        Level::Info,
        "planner started: start print time s, high water s, step streams",
        [Arg::F(start), Arg::F(run.high_water), Arg::U(params.len() as u64)],
    );
    // With the heater loop running, heat asked of a real board is real: no warning.
    let mut accessories = Accessories::new(st.machine.real_board && st.heaters.is_none());
    let file = gcode.name.clone();
    let mut macros = st.machine.macros(start)?;
    let lines = plan_file(
        gcode,
        &mut pipeline,
        &mut accessories,
        &mut macros,
        &st.machine.homing,
        &mut run,
    )?;
    run.sinks.iter_mut().try_for_each(ShmSink::flush)?;
    let total = run.published();
    // Counted before anything below allocates (the report's own vectors).
    let (motion_allocations, motion_count) = run.motions;
    let allocs = run.warm.map(|(w, seq)| AfterWarmup {
        allocations: AllocCounter::snapshot()
            .since(w)
            .allocations()
            .saturating_sub(motion_allocations),
        batches: total - seq,
        motion_allocations,
        motions: motion_count,
    });
    crate::allocsites::finish_if_requested("planner");
    let mut summary_extra = accessories.lines();
    summary_extra.append(&mut run.homing_reports);
    summary_extra.append(&mut run.heat.lines(st.heaters));
    let batches: Vec<u64> = run.sinks.iter().map(|s| s.publisher.next_seq()).collect();
    let stats = pipeline.stats();
    let summary = Summary {
        file,
        lines,
        moves: stats.moves,
        print_time: pipeline.planned_until() - start,
        wall: 0.0,
        queue_steps: run.streams.queue_steps(),
        rows: Vec::new(),
        clock_freq,
        mcu_freqs: params
            .iter()
            .map(|m| (m.name.to_string(), m.clock_freq))
            .collect(),
        extra: summary_extra,
    };
    st.log.log(
        Level::Info,
        "planner done: lines, moves, queue_steps, batches",
        [
            Arg::U(lines),
            Arg::U(stats.moves),
            Arg::U(summary.queue_steps),
            Arg::U(total),
        ],
    );
    Ok((summary, pipeline, run.streams, allocs, batches))
}

/// One publisher per step stream, each waited for (bounded) until its IO stage subscribed.
fn open_sinks(
    node: &iceoryx2::node::Node<Ipc>,
    instance: &str,
    params: &[McuParams<'_>],
) -> Result<Vec<ShmSink>, PlannerError> {
    let mut sinks = Vec::with_capacity(params.len());
    for m in params {
        let service = steps_service_name(instance, m.name);
        let publisher = ShmPublisher::<Ipc, StepBatch>::open(node, &service, &ChannelConfig::steps())
            .map_err(|source| PlannerError::Channel {
                mcu: m.name.to_string(),
                source,
            })?;
        let deadline = Instant::now() + Duration::from_secs(5);
        while publisher.connect()? < 1 {
            if Instant::now() > deadline {
                return Err(PlannerError::NeverSubscribed {
                    mcu: m.name.to_string(),
                });
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        sinks.push(ShmSink {
            publisher,
            batch: StepBatch::default(),
        });
    }
    Ok(sinks)
}

/// The planner thread's end of the G-code loop: lead checks, the hand-off, flow control and
/// homing with the MCUs in the loop.
struct PlannerRun<'a, 'p> {
    st: &'a PlannerStage<'p>,
    main: McuParams<'p>,
    sinks: Vec<ShmSink>,
    streams: StepStreams,
    /// Each stream's MCU clock now (reused: no allocation per batch).
    now_clocks: Vec<f64>,
    /// Buffering window in print time (see [`buffer_window`]).
    high_water: f64,
    low_water: f64,
    /// Allocation counter and batches published when the pipeline first reached high water
    /// (warm-up: every buffer has seen a full window).
    warm: Option<(AllocCounter, u64)>,
    /// Allocations of homing/probing commands after warm-up (counted apart) and their count.
    motions: (u64, u64),
    /// Report lines of homing and probing, printed with the summary.
    homing_reports: Vec<String>,
    /// Planning G-code (false while a session's feed is idle).
    busy: bool,
    /// Heater commands' waits, for the summary.
    heat: crate::heaters::feed::HeatLog,
    /// Calibration results waiting for SAVE_CONFIG.
    autosave: sysconfig::autosave::Changes,
}

/// Sleep between flow-control checks.
const PACE: Duration = Duration::from_millis(5);

/// Share of half the MCUs' 32-bit clock range the buffered print time may span: a step
/// command is sent up to the buffered time (plus the move being planned) before it is due,
/// and an MCU compares 32-bit clocks, so a command due more than 2^31 ticks ahead reads as
/// one in the past ("Timer too close"). 0.3 leaves room for a long move beyond the window.
const WRAP_SHARE: f64 = 0.3;

/// The high water mark of buffered print time (s): 2 s, or 1 s of wall time when the clock
/// runs `scale` times faster, but never more than [`WRAP_SHARE`] of 2^31 ticks of the fastest
/// MCU clock (12.9 s at 50 MHz: from `--time-scale` 13 on, the wall-time buffer shrinks to
/// 12.9 s / scale, 258 ms at 50×).
pub(crate) fn buffer_window(scale: f64, fastest_clock_freq: f64) -> f64 {
    let wrap_limit = WRAP_SHARE * 2f64.powi(31) / fastest_clock_freq;
    (2.0f64).max(scale).min(wrap_limit)
}

impl<'a, 'p> PlannerRun<'a, 'p> {
    fn new(
        st: &'a PlannerStage<'p>,
        main: McuParams<'p>,
        sinks: Vec<ShmSink>,
        streams: StepStreams,
        n: usize,
    ) -> Self {
        let fastest = streams
            .mcus
            .iter()
            .map(|m| m.clock_freq)
            .fold(main.clock_freq, f64::max);
        let high_water = buffer_window(st.scale, fastest);
        PlannerRun {
            st,
            main,
            sinks,
            streams,
            now_clocks: vec![0.0f64; n],
            high_water,
            low_water: high_water / 2.0,
            warm: None,
            motions: (0, 0),
            homing_reports: Vec::new(),
            busy: true,
            heat: crate::heaters::feed::HeatLog::default(),
            autosave: sysconfig::autosave::Changes::default(),
        }
    }

    /// The main MCU's print time now.
    fn print_now(&self) -> f64 {
        self.st
            .side
            .clock(self.main.mcu_index)
            .clock_at(McuLink::system_now())
            / self.main.clock_freq
    }

    fn published(&self) -> u64 {
        self.sinks.iter().map(|s| s.publisher.next_seq()).sum()
    }

    /// An MCU shutdown, a failed IO process or a stop request, as an error.
    fn check(&self) -> Result<(), PlannerError> {
        // A stop first: an emergency stop also shuts the MCUs down, and is the cause.
        if let Some(s) = self.st.session {
            if let Some(reason) = s.stop_reason() {
                return Err(PlannerError::Stopped { reason });
            }
        }
        // A thermal runaway also shuts the MCUs down, and is the cause.
        if let Some(reason) = self.st.heaters.and_then(|h| h.fault()) {
            return Err(PlannerError::ThermalFault { reason });
        }
        // An SPI temperature chip's faulty reads shut its MCU down: the error names the fault.
        self.st
            .side
            .check()
            .map_err(|e| match (&e, self.st.heaters.and_then(|h| h.chip_fault())) {
                (PlannerError::Mcu(crate::mcus::McuError::Shutdown { reason, .. }), Some(fault))
                    if reason == firmware::core::reason::THERMOCOUPLE_FAULT =>
                {
                    PlannerError::ThermalFault {
                        reason: format!("{e} ({fault})"),
                    }
                }
                _ => e,
            })
    }

    /// Refuses a step command that would reach its MCU with less than [`MIN_LEAD_S`].
    fn check_lead(&self, idx: usize, cmd: &StepCmd) -> Result<(), PlannerError> {
        let StepCmd::QueueStep { first_clock, .. } = *cmd else {
            return Ok(());
        };
        let k = self.streams.stream_of(idx).unwrap_or(0);
        let freq = self.streams.mcus[k].clock_freq;
        let now_clock = self.now_clocks[k];
        if (first_clock as f64) >= now_clock + MIN_LEAD_S * freq {
            return Ok(());
        }
        let ahead_ms = (first_clock as f64 - now_clock) / freq * 1e3;
        self.st.log.log(
            Level::Error,
            "planner fell behind: stepper index, ms before due",
            [Arg::U(idx as u64), Arg::F(ahead_ms)],
        );
        Err(PlannerError::FellBehind {
            stepper: self.st.machine.steppers[idx].name.clone(),
            mcu: self.streams.mcus[k].name.clone(),
            clock: first_clock,
            ahead_ms,
            min_ms: MIN_LEAD_S * 1e3,
        })
    }

    /// Publishes the motion status of a session (no allocation).
    fn publish_status(&self, pipeline: &Pipeline) {
        if let Some(s) = self.st.session {
            s.publish_motion(MotionStatus {
                position: pipeline.position(),
                homed: pipeline.gcode_state().homed(),
                planned_until: pipeline.planned_until(),
                busy: self.busy,
            });
        }
    }

    /// Drains the shared-memory hand-offs: everything planned so far must be in the links
    /// before homing talks to the MCUs directly.
    fn drain_handoff(&mut self, mcus: &Mcus) -> Result<(), PlannerError> {
        self.sinks.iter_mut().try_for_each(ShmSink::flush)?;
        let targets: Vec<u64> = self.sinks.iter().map(|s| s.publisher.next_seq()).collect();
        let deadline = Instant::now() + Duration::from_secs(10);
        while self
            .st
            .consumed
            .iter()
            .zip(&targets)
            .any(|(c, &t)| c.load(Ordering::Acquire) < t)
        {
            if Instant::now() > deadline {
                return Err(PlannerError::HandoffNotDrained);
            }
            mcus.check()?;
            std::thread::sleep(Duration::from_millis(1));
        }
        Ok(())
    }
}

impl FeedTarget for PlannerRun<'_, '_> {
    type Error = PlannerError;

    fn emit(&mut self, cmds: &mut Vec<(usize, StepCmd)>) -> Result<(), PlannerError> {
        if !cmds.is_empty() {
            self.drivers_to_run_current()?;
        }
        let now = McuLink::system_now();
        for (c, m) in self.now_clocks.iter_mut().zip(&self.streams.mcus) {
            *c = self.st.side.clock(m.mcu_index).clock_at(now);
        }
        for &(idx, cmd) in cmds.iter() {
            self.check_lead(idx, &cmd)?;
            self.streams.push(idx, cmd, &mut self.sinks[..])?;
        }
        Ok(self.sinks.iter_mut().try_for_each(ShmSink::flush)?)
    }

    fn pace(&mut self, p: &mut Pipeline) -> Result<(), PlannerError> {
        let side = self.st.side;
        if let (false, McuSide::Local(mcus)) = (self.busy, side) {
            // Quiet: a TMC2660 gets its idle current once the toolhead has been still a while.
            let now = McuLink::system_now();
            let still = self
                .streams
                .mcus
                .iter()
                .map(|m| {
                    (side.clock(m.mcu_index).clock_at(now) - m.streamer.last_step_clock as f64) / m.clock_freq
                })
                .fold(f64::INFINITY, f64::min);
            crate::tmc::idle::on_quiet(mcus, &self.st.machine.tmc, still).map_err(tmc_error)?;
        }
        // The next batch is planned with the MCUs' latest clock fits.
        self.streams.refresh_clocks(p, |i| side.clock(i))?;
        self.publish_status(p);
        // Flow control: keep between the low and high water marks of buffered print time.
        if p.planned_until() - self.print_now() > self.high_water {
            if self.warm.is_none() {
                self.warm = Some((AllocCounter::snapshot(), self.published()));
                crate::allocsites::start_if_requested();
            }
            self.st.log.log(
                Level::Debug,
                "flow control: buffered print time s, waiting down to s",
                [
                    Arg::F(p.planned_until() - self.print_now()),
                    Arg::F(self.low_water),
                ],
            );
            while p.planned_until() - self.print_now() > self.low_water {
                self.check()?;
                let t = Instant::now();
                std::thread::sleep(PACE);
                if let Ok(mut h) = self.st.hists.wake_planner.try_lock() {
                    h.record(t.elapsed().saturating_sub(PACE).as_nanos() as u64);
                }
            }
        }
        self.check()
    }

    fn motion(&mut self, pipeline: &mut Pipeline, cmd: &MotionCmd<'_>) -> Result<bool, PlannerError> {
        let st = self.st;
        if st.machine.endstops.is_empty() && st.machine.probe.is_none() && st.machine.tmc.is_empty() {
            return Ok(false);
        }
        if let MotionCmd::Probe { name, .. } = cmd {
            if !crate::homing::probe::is_configured(st.machine, name) {
                return Ok(false);
            }
        }
        let McuSide::Local(mcus) = st.side else {
            let what = match cmd {
                MotionCmd::Home(_) => "homing needs",
                MotionCmd::Probe { .. } => "probing needs",
                MotionCmd::Tmc { .. } => "TMC driver commands need",
            };
            return Err(PlannerError::MotionNeedsLocalIo { what });
        };
        let motion_start = AllocCounter::snapshot();
        self.drain_handoff(mcus)?;
        if !matches!(cmd, MotionCmd::Tmc { .. }) {
            self.drivers_to_run_current()?;
        }
        if let MotionCmd::Home(axes) = cmd {
            st.log.log(
                Level::Info,
                "homing axes x, y, z",
                [
                    Arg::U(axes[0] as u64),
                    Arg::U(axes[1] as u64),
                    Arg::U(axes[2] as u64),
                ],
            );
        }
        let mut direct = crate::homing::direct_sinks(&self.streams, mcus);
        let mut ctx = HomingCtx::new(
            mcus,
            st.machine,
            pipeline,
            &mut self.streams,
            &mut direct,
            st.scale,
            st.rt,
        );
        // Formatted text is printed by the main thread with the summary.
        let mut out = Vec::new();
        let result = run_motion(&mut ctx, cmd, &mut out);
        let timeout_detail = match (&result, ctx.comm_timeout_detail.take()) {
            (Err(_), Some(detail)) => Some(format!("homing: communication timeout: {detail}")),
            _ => None,
        };
        if let Some(line) = &timeout_detail {
            out.push(line.clone());
        }
        if let Some(session) = st.session {
            match &result {
                Ok(Some(report)) => {
                    if let Ok(mut last) = session.last_homing.lock() {
                        *last = Some(report.clone());
                    }
                    session.emit(Event::Homed(report.clone()));
                }
                _ => out.iter().for_each(|l| session.emit(Event::Response(l.clone()))),
            }
        }
        self.homing_reports.extend(out);
        // A BED_MESH_CALIBRATE or BED_MESH_PROFILE SAVE/REMOVE is pending for SAVE_CONFIG from
        // now on, as Klipper's `configfile.save_config_pending` shows it.
        if let Some(bm) = &self.st.machine.bed_mesh {
            let pending = bm.take_pending();
            if !pending.is_empty() {
                self.autosave.merge(pending);
                self.publish_save_pending();
            }
        }
        if let Some(line) = timeout_detail {
            // Which member fell silent, or whose expiry passed: printed with the error, since a
            // failed print has no summary to carry it.
            self.warn(line);
        }
        result?;
        if matches!(cmd, MotionCmd::Home(_)) {
            st.log.log(Level::Info, "homing done", []);
        }
        self.publish_status(pipeline);
        if self.warm.is_some() {
            let (allocs, n) = self.motions;
            let more = AllocCounter::snapshot().since(motion_start).allocations();
            self.motions = (allocs + more, n + 1);
        }
        Ok(true)
    }

    fn resume_at(&self) -> f64 {
        // As far ahead as the print's own start: the first batch is planned long before due.
        self.print_now() + (0.5f64).max(0.25 * self.st.scale)
    }

    fn warn(&mut self, text: String) {
        // A plain print's session has nobody listening for events: the warning goes to stderr.
        match self.st.session {
            Some(s) if s.listening() => s.emit(Event::Warning(text)),
            _ => eprintln!("cadence: warning: {text}"),
        }
    }

    fn heat(
        &mut self,
        pipeline: &mut Pipeline,
        cmd: &crate::heaters::gcode::HeatCmd,
    ) -> Result<(), PlannerError> {
        if *cmd == crate::heaters::gcode::HeatCmd::SaveConfig {
            return self.save_config();
        }
        let Some(shared) = self.st.heaters else {
            if matches!(self.st.side, McuSide::Remote(..)) && drives_output(cmd) {
                return Err(PlannerError::HeatersNeedLocalIo);
            }
            return Ok(());
        };
        let thermal = &self.st.machine.thermal;
        let Some(wait) = crate::heaters::feed::apply(thermal, shared, cmd)? else {
            if *cmd == crate::heaters::gcode::HeatCmd::EmergencyStop {
                // As Klipper's M112: every MCU shuts down now (outputs off, motion stopped).
                if let McuSide::Local(mcus) = self.st.side {
                    for m in &mcus.list {
                        if let Ok(stop) = m.link.dictionary().encode("emergency_stop", &[]) {
                            let _ = m.link.send(stop);
                        }
                    }
                }
                return Err(PlannerError::EmergencyStop);
            }
            if *cmd == crate::heaters::gcode::HeatCmd::Report {
                let text = crate::heaters::runtime::m105_text(shared);
                if let Some(s) = self.st.session {
                    s.emit(Event::Response(text.clone()));
                }
                self.heat.report(text);
            }
            return Ok(());
        };
        // Klipper's M109/M190/TEMPERATURE_WAIT: the moves before it run, the G-code waits.
        let mut out = Vec::new();
        pipeline.flush_lookahead();
        pipeline.generate(&mut out);
        self.emit(&mut out)?;
        let started = shared.heaters.get(wait.heater).map(|h| h.time.get());
        let wall = Instant::now();
        let mut interrupted = false;
        while !wait.done(shared) {
            self.check()?;
            if self.st.session.is_some_and(SessionShared::interrupted) {
                self.respond(format!("{} interrupted: the wait ends here", wait.what));
                interrupted = true;
                break;
            }
            self.publish_status(pipeline);
            std::thread::sleep(PACE);
        }
        let ended = shared.heaters.get(wait.heater).map(|h| h.time.get());
        self.heat
            .record(&wait, started, ended, wall.elapsed().as_secs_f64());
        match cmd {
            crate::heaters::gcode::HeatCmd::PidCalibrate { write_file, .. } if !interrupted => {
                self.calibrated(shared, *write_file)?;
            }
            _ => {}
        }
        pipeline
            .raise_print_time(self.resume_at())
            .map_err(PlannerError::from)?;
        Ok(())
    }

    fn motors_off(&mut self, pipeline: &mut Pipeline) -> Result<(), PlannerError> {
        let mut out = Vec::new();
        pipeline.flush_lookahead();
        pipeline.generate(&mut out);
        self.emit(&mut out)?;
        // Not before a move planned now could start (the lead a message sent now needs).
        let ahead = self.resume_at() - self.print_now();
        let floors: Vec<u64> = (self.now_clocks.iter().zip(&self.streams.mcus))
            .map(|(c, m)| (c + ahead * m.clock_freq) as u64)
            .collect();
        self.streams.motors_off(&floors, &mut self.sinks[..])?;
        Ok(self.sinks.iter_mut().try_for_each(ShmSink::flush)?)
    }

    fn can_extrude(&self, extruder: &str) -> Result<(), PlannerError> {
        match self.st.heaters {
            Some(shared) => Ok(crate::heaters::feed::can_extrude(
                &self.st.machine.thermal,
                shared,
                extruder,
            )?),
            None => Ok(()),
        }
    }

    fn idle(&mut self, idle: bool, pipeline: &Pipeline) {
        self.busy = !idle;
        if let Some(h) = self.st.heaters {
            h.motors_on.store(!idle, std::sync::atomic::Ordering::Release);
        }
        self.publish_status(pipeline);
        if let Some(s) = self.st.session {
            let state = if idle {
                PrinterState::Ready
            } else {
                PrinterState::Printing
            };
            s.emit(Event::State(state));
        }
    }
}

/// A TMC driver's register traffic outside a G-code command failed.
fn tmc_error(e: crate::tmc::TmcError) -> PlannerError {
    PlannerError::Homing(Box::new(e.into()))
}

impl PlannerRun<'_, '_> {
    /// Motion comes: TMC2660s in their idle current get their run current back first.
    fn drivers_to_run_current(&self) -> Result<(), PlannerError> {
        if let McuSide::Local(mcus) = self.st.side {
            crate::tmc::idle::on_motion(mcus, &self.st.machine.tmc).map_err(tmc_error)?;
        }
        Ok(())
    }
    /// A G-code answer: the session's response event, or stderr and the summary of a print.
    fn respond(&mut self, text: String) {
        match self.st.session {
            Some(s) if s.listening() => s.emit(Event::Response(text.clone())),
            _ => eprintln!("cadence: {}", text.replace('\n', " ")),
        }
        self.heat.note(text.replace('\n', " "));
    }

    /// PID_CALIBRATE's end: Klipper's report, the gains pending for SAVE_CONFIG, the samples
    /// in `/tmp/heattest.txt` with WRITE_FILE=1.
    fn calibrated(
        &mut self,
        shared: &crate::heaters::runtime::HeaterShared,
        write_file: bool,
    ) -> Result<(), PlannerError> {
        use crate::heaters::runtime::Calibration;
        let Some(Calibration::Done {
            heater,
            gains,
            pwm,
            temps,
        }) = shared.take_calibration()
        else {
            return Err(PlannerError::CalibrationInterrupted);
        };
        if write_file {
            let mut text: Vec<String> = pwm.iter().map(|(t, p)| format!("pwm: {t:.3} {p:.3}")).collect();
            text.extend(temps.iter().map(|(t, c)| format!("{t:.3} {c:.3}")));
            std::fs::write(crate::heaters::calibrate::WRITE_FILE, text.join("\n")).map_err(|source| {
                PlannerError::CalibrationFile {
                    path: crate::heaters::calibrate::WRITE_FILE,
                    source,
                }
            })?;
        }
        let gains = gains.ok_or(PlannerError::CalibrationInterrupted)?;
        let name = shared
            .heaters
            .get(heater)
            .map_or("?", |h| h.name.as_str())
            .to_string();
        self.respond(crate::heaters::calibrate::report(&gains));
        crate::heaters::calibrate::save_changes(&mut self.autosave, &name, &gains);
        self.publish_save_pending();
        Ok(())
    }

    /// Makes the pending SAVE_CONFIG changes visible (the `configfile` status object).
    fn publish_save_pending(&self) {
        if let Some(s) = self.st.session {
            s.publish_save_pending(&self.autosave);
        }
    }

    /// SAVE_CONFIG: the pending results written into the printer's config file (the service
    /// restarts the printer after it; a print reports the file and goes on).
    fn save_config(&mut self) -> Result<(), PlannerError> {
        let path = self.st.machine.config_path.clone();
        if path.starts_with("<builtin>") {
            return Err(PlannerError::NoConfigFile);
        }
        if let Some(bm) = &self.st.machine.bed_mesh {
            self.autosave.merge(bm.take_pending());
        }
        match sysconfig::autosave::save(&path, &self.autosave)? {
            Some(saved) => {
                self.autosave = sysconfig::autosave::Changes::default();
                self.publish_save_pending();
                self.respond(format!(
                    "SAVE_CONFIG: wrote {} (previous version kept as {})",
                    saved.path.display(),
                    saved.backup.display()
                ));
            }
            None => self.respond("SAVE_CONFIG: nothing to save".to_string()),
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::buffer_window;

    #[test]
    fn buffer_window_stays_inside_half_the_clock_range() {
        assert_eq!(buffer_window(1.0, 50e6), 2.0);
        assert_eq!(buffer_window(10.0, 50e6), 10.0);
        // At 50× a 50 s window would put commands more than 2^31 ticks (42.9 s) ahead.
        let w = buffer_window(50.0, 50e6);
        assert!((w - 0.3 * 2f64.powi(31) / 50e6).abs() < 1e-9, "{w}");
        assert!(w * 50e6 < 0.5 * 2f64.powi(31));
        // A slow clock wraps later: the window is not cut.
        assert!((buffer_window(50.0, 16e6) - 0.3 * 2f64.powi(31) / 16e6).abs() < 1e-9);
    }
}
