//! The live print on real-time threads:
//!
//! ```text
//! [planner] G-code → lookahead → steps → compression ──StepBatch (iceoryx2)──► [io-mcu] ──► link IO thread ──► pty/tty
//!  core 0, SCHED_FIFO                                   cadence/<instance>/mcu/mcu/steps      core 1, SCHED_FIFO
//! ```
//!
//! The planner thread runs the G-code loop with flow control (buffered print time between a
//! low and a high water mark) and publishes encoded step messages in batches over iceoryx2
//! shared memory (no loss: safe overflow off, back-pressure, sequence numbers). The IO stage
//! subscribes, checks each step message's lead before handing it to the MCU link, and the
//! link's own IO thread writes it. Histograms recorded on the way: lead margin of every step
//! message (in the link IO thread, when its bytes leave), hand-off latency planner → IO stage,
//! and each stage's wake-up lateness. When the OS refuses pinning or SCHED_FIFO, the threads run
//! anyway and rt-core reports once which guarantees are off.

use std::cell::RefCell;
use std::fs::File;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};

use links::dict::Cmd;
use links::mcu::McuLink;
use planner::pipeline::Pipeline;
use planner::stepgen::StepCmd;
use rt_core::alloc_count::AllocCounter;
use rt_core::hist::LatencyHist;
use rt_core::os::{apply_rt, RtSpec};
use rt_core::shm::{
    open_node, steps_service_name, telemetry_kind, telemetry_service_name, ChannelConfig, ShmPublisher,
    ShmSubscriber, StepBatch, Telemetry, WireMsg,
};

use crate::homing::{home_axes, HomingCtx};
use crate::machine::Machine;
use crate::mcus::Mcus;
use crate::print::{plan_file, PrintArgs, Summary, MIN_LEAD_S};
use crate::sink::{LinkSink, Sink, StepStreamer};

type Ipc = iceoryx2::prelude::ipc::Service;

/// Thread placement and priorities of a live print (from printer.cfg's `[realtime]`).
#[derive(Debug, Clone)]
pub struct RtConfig {
    /// Apply pinning / SCHED_FIFO / mlockall at all.
    pub enabled: bool,
    pub planner_core: usize,
    pub io_core: usize,
    pub planner_priority: i32,
    pub io_priority: i32,
    pub lock_memory: bool,
}

impl RtConfig {
    /// Settings of the MCU links' own IO threads: on the IO core, above the IO stage (they
    /// write the bytes and relay homing triggers).
    pub fn link_spec(&self) -> RtSpec {
        self.spec("io-link", self.io_core, self.io_priority + 5)
    }

    fn spec(&self, name: &str, core: usize, priority: i32) -> RtSpec {
        let mut spec = RtSpec::new(name);
        if self.enabled {
            spec.core = Some(core % available_cores());
            spec.fifo_priority = Some(priority);
            spec.lock_memory = self.lock_memory;
        }
        spec
    }
}

fn available_cores() -> usize {
    std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
}

/// Latency histograms recorded during a live print.
#[derive(Debug)]
pub struct Hists {
    /// Lead margin of each step message when its bytes left (MCU ticks).
    pub lead: Mutex<LatencyHist>,
    /// Planner → IO stage hand-off (ns).
    pub handoff: Mutex<LatencyHist>,
    /// Planner thread wake-up lateness after a flow-control sleep (ns).
    pub wake_planner: Mutex<LatencyHist>,
}

impl Hists {
    pub fn new() -> Arc<Hists> {
        let ticks = || LatencyHist::with_bounds(1, 1 << 42, 3, 1.0).unwrap_or_else(|_| LatencyHist::new());
        Arc::new(Hists {
            lead: Mutex::new(ticks()),
            handoff: Mutex::new(LatencyHist::new()),
            wake_planner: Mutex::new(LatencyHist::new()),
        })
    }

    /// A link margin hook recording into `lead` (runs in the link's IO thread; a `try_lock`
    /// so the IO thread never waits on a reader).
    pub fn lead_hook(self: &Arc<Self>) -> links::serialqueue::MarginHook {
        let h = Arc::clone(self);
        Box::new(move |_req, margin| {
            if let Ok(mut hist) = h.lead.try_lock() {
                hist.record_signed(margin);
            }
        })
    }

    /// Report lines (margins in ms of print time).
    pub fn report(&self, clock_freq: f64) -> Vec<String> {
        let mut out = Vec::new();
        if let Ok(h) = self.lead.lock() {
            let s = h.summary();
            if s.count > 0 {
                let ms = |t: u64| t as f64 / clock_freq * 1e3;
                out.push(format!(
                    "lead margin (ms): min {:.1} p0.1 {:.1} p1 {:.1} p50 {:.1} over {} step messages{}",
                    ms(s.min),
                    ms(s.p0_1),
                    ms(s.p1),
                    ms(s.p50),
                    s.count,
                    if s.negative > 0 {
                        format!(", {} LATE", s.negative)
                    } else {
                        String::new()
                    }
                ));
            }
        }
        for (name, m) in [
            ("hand-off planner→io", &self.handoff),
            ("wake-up lateness planner", &self.wake_planner),
        ] {
            if let Ok(h) = m.lock() {
                let s = h.summary();
                if s.count > 0 {
                    out.push(format!("{name}: {} ({} samples)", s.format_latency(), s.count));
                }
            }
        }
        out
    }

    /// Publishes a summary of each histogram on the telemetry service (see the module docs):
    /// kind `HIST_SUMMARY`, values = [count, negative, min, p0.1, p1, p50, p99, p99.9, max,
    /// mean, ns_per_unit], source 0 = lead margin (MCU ticks), 1 = hand-off (ns), 2 = planner
    /// wake-up lateness (ns). Monitors never stall the printer (safe overflow on).
    fn publish(&self, publisher: &mut ShmPublisher<Ipc, Telemetry>, t_ns: u64) {
        for (source, m) in [(0u32, &self.lead), (1, &self.handoff), (2, &self.wake_planner)] {
            let Ok(h) = m.try_lock() else { continue };
            let x = h.summary();
            drop(h);
            let values = [
                x.count as f64,
                x.negative as f64,
                x.min as f64,
                x.p0_1 as f64,
                x.p1 as f64,
                x.p50 as f64,
                x.p99 as f64,
                x.p999 as f64,
                x.max as f64,
                x.mean,
                x.ns_per_unit,
            ];
            let _ = publisher.send_with(|t| {
                t.kind = telemetry_kind::HIST_SUMMARY;
                t.source = source;
                t.t_ns = t_ns;
                t.count = values.len() as u32;
                t.values[..values.len()].copy_from_slice(&values);
            });
        }
    }

    /// Saves every histogram as an HdrHistogram V2 interval log.
    pub fn save(&self, path: &std::path::Path, wall_s: f64) -> Result<(), String> {
        let file = File::create(path).map_err(|e| format!("{}: {e}", path.display()))?;
        let err = |e: rt_core::hist::HistError| format!("{}: {e}", path.display());
        let mut log = rt_core::hist::IntervalLog::begin(
            std::io::BufWriter::new(file),
            "cadence print latency histograms",
        )
        .map_err(err)?;
        for (tag, m) in [
            ("lead_margin_ticks", &self.lead),
            ("handoff_ns", &self.handoff),
            ("wake_planner_ns", &self.wake_planner),
        ] {
            if let Ok(h) = m.lock() {
                log.write(tag, &h, Duration::ZERO, Duration::from_secs_f64(wall_s.max(0.0)))
                    .map_err(err)?;
            }
        }
        log.finish().map_err(err)?;
        Ok(())
    }
}

fn mono_ns() -> u64 {
    (McuLink::system_now() * 1e9) as u64
}

/// The planner side of the shared-memory hand-off: packs messages into batches.
struct ShmSink {
    publisher: ShmPublisher<Ipc, StepBatch>,
    batch: StepBatch,
}

impl ShmSink {
    fn push(&mut self, m: WireMsg) -> Result<(), String> {
        if !self.batch.push(m) {
            self.flush()?;
            self.batch.push(m);
        }
        Ok(())
    }

    /// Publishes the pending batch (if any).
    fn flush(&mut self) -> Result<(), String> {
        if self.batch.count == 0 {
            return Ok(());
        }
        let batch = self.batch;
        self.publisher
            .send_with(|b| {
                *b = batch;
                b.t_ns = mono_ns();
            })
            .map_err(|e| format!("planner → io hand-off: {e}"))?;
        self.batch.count = 0;
        Ok(())
    }
}

impl Sink for ShmSink {
    fn send(&mut self, cmd: Cmd) -> Result<(), String> {
        self.push(WireMsg::new(0, 0, cmd.as_bytes()).unwrap_or_default())
    }
    fn send_clocked(&mut self, cmd: Cmd, min_clock: u64, req_clock: u64) -> Result<(), String> {
        self.push(WireMsg::new(min_clock, req_clock, cmd.as_bytes()).unwrap_or_default())
    }
}

/// What the IO stage reports.
#[derive(Debug, Default)]
struct IoReport {
    batches: u64,
    allocations_after_warmup: Option<u64>,
}

/// Batches after which a stage counts as warmed up (allocation accounting starts).
const WARMUP_BATCHES: u64 = 64;

/// The IO stage: shared memory → lead check → the MCU link.
fn io_stage(
    link: &McuLink,
    service: &str,
    ready: mpsc::Sender<Result<(), String>>,
    done: &AtomicBool,
    consumed: &AtomicU64,
    hists: &Hists,
    clock_freq: f64,
) -> Result<IoReport, String> {
    let setup = || -> Result<_, String> {
        let (node, _) =
            open_node::<Ipc>(&format!("cadence-io-{}", std::process::id())).map_err(|e| e.to_string())?;
        let sub = ShmSubscriber::<Ipc, StepBatch>::open(&node, service, &ChannelConfig::steps())
            .map_err(|e| e.to_string())?;
        Ok((node, sub))
    };
    // The node stays alive as long as its port.
    let (_node, mut sub) = match setup() {
        Ok(s) => {
            let _ = ready.send(Ok(()));
            s
        }
        Err(e) => {
            let _ = ready.send(Err(e.clone()));
            return Err(e);
        }
    };
    let lead_ticks = MIN_LEAD_S * clock_freq;
    let idle_wait = Duration::from_millis(5);
    let mut report = IoReport::default();
    let mut warm: Option<AllocCounter> = None;
    loop {
        let was_done = done.load(Ordering::Acquire);
        let got = sub
            .recv_timeout_with(idle_wait, |b| *b)
            .map_err(|e| format!("io stage: {e}"))?;
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
                return Err(format!(
                    "the IO stage fell behind: a step message for clock {} reached it {:.1} ms before it is due \
                     (at least {:.0} ms required); print stopped before sending it",
                    m.req_clock,
                    (m.req_clock as f64 - now_clock) / clock_freq * 1e3,
                    MIN_LEAD_S * 1e3
                ));
            }
            let cmd = Cmd::from_bytes(m.bytes()).ok_or("io stage: malformed message in a step batch")?;
            if m.req_clock == 0 && m.min_clock == 0 {
                link.send(cmd).map_err(|e| e.to_string())?;
            } else {
                link.send_clocked(cmd, m.min_clock, m.req_clock)
                    .map_err(|e| e.to_string())?;
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
    Ok(report)
}

/// How a live print runs: when it started, the simulator's time scale, thread placement and
/// where its histograms go.
#[derive(Debug)]
pub struct LiveRun<'a> {
    pub started: Instant,
    pub scale: f64,
    pub rt: &'a RtConfig,
    pub hists: &'a Arc<Hists>,
}

/// Runs the live print of `gcode` on the connected MCUs.
pub fn print_on(
    args: &PrintArgs,
    machine: &Machine,
    mcus: &Mcus,
    gcode: File,
    run: &LiveRun<'_>,
) -> Result<Summary, String> {
    let LiveRun {
        started,
        scale,
        rt,
        hists,
    } = *run;
    let main = mcus.main();
    let link = &main.link;
    let clock_freq = main.clock_freq;
    let instance = format!("p{}", std::process::id());
    let service = steps_service_name(&instance, &main.name);
    let done_flag = AtomicBool::new(false);
    let done = &done_flag;
    let consumed_count = AtomicU64::new(0);
    let consumed = &consumed_count;
    let service = service.as_str();

    std::thread::scope(|scope| {
        let (ready_tx, ready_rx) = mpsc::channel();
        let io_spec = rt.spec(&format!("io-{}", main.name), rt.io_core, rt.io_priority);
        let io = std::thread::Builder::new()
            .name(io_spec.name.clone())
            .spawn_scoped(scope, move || {
                apply_rt(&io_spec);
                io_stage(link, service, ready_tx, done, consumed, hists, clock_freq)
            })
            .map_err(|e| format!("cannot start the IO stage thread: {e}"))?;
        match ready_rx.recv_timeout(Duration::from_secs(10)) {
            Ok(Ok(())) => {}
            Ok(Err(e)) => return Err(format!("io stage: {e}")),
            Err(_) => return Err("io stage did not start within 10 s".to_string()),
        }
        let planner_spec = rt.spec("planner", rt.planner_core, rt.planner_priority);
        let planner = std::thread::Builder::new()
            .name("planner".to_string())
            .spawn_scoped(scope, move || {
                apply_rt(&planner_spec);
                let r = planner_stage(
                    args, machine, mcus, gcode, started, scale, service, consumed, hists,
                );
                done.store(true, Ordering::Release);
                r
            })
            .map_err(|e| format!("cannot start the planner thread: {e}"))?;
        let planned = planner
            .join()
            .map_err(|_| "the planner thread panicked".to_string())?;
        done.store(true, Ordering::Release);
        let io_report = io
            .join()
            .map_err(|_| "the IO stage thread panicked".to_string())?;
        // A failed IO stage is the root cause of a planner hand-off error: report it first.
        let io_report = io_report?;
        let (mut summary, pipeline, streamer, planner_allocs) = planned?;
        finish_print(mcus, machine, &pipeline, &streamer, &mut summary, scale)?;
        summary.extra.extend(hists.report(clock_freq));
        summary.extra.push(format!(
            "allocations after warm-up: planner {}, io stage {} ({} batches)",
            planner_allocs.map_or("n/a".to_string(), |n| n.to_string()),
            io_report
                .allocations_after_warmup
                .map_or("n/a".to_string(), |n| n.to_string()),
            io_report.batches
        ));
        Ok(summary)
    })
}

type Planned = (Summary, Pipeline, StepStreamer, Option<u64>);

/// The planner thread: G-code → pipeline → step messages into shared memory, paced.
#[allow(clippy::too_many_arguments)]
fn planner_stage(
    args: &PrintArgs,
    machine: &Machine,
    mcus: &Mcus,
    gcode: File,
    started: Instant,
    scale: f64,
    service: &str,
    consumed: &AtomicU64,
    hists: &Hists,
) -> Result<Planned, String> {
    let main = mcus.main();
    let link = &main.link;
    let dict = link.dictionary();
    let clock_freq = main.clock_freq;
    let (node, _) =
        open_node::<Ipc>(&format!("cadence-planner-{}", std::process::id())).map_err(|e| e.to_string())?;
    let publisher = ShmPublisher::<Ipc, StepBatch>::open(&node, service, &ChannelConfig::steps())
        .map_err(|e| format!("planner → io hand-off: {e}"))?;
    let deadline = Instant::now() + Duration::from_secs(5);
    while publisher.connect().map_err(|e| e.to_string())? < 1 {
        if Instant::now() > deadline {
            return Err("planner → io hand-off: the IO stage never subscribed".to_string());
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    let mut telemetry = ShmPublisher::<Ipc, Telemetry>::open(
        &node,
        &telemetry_service_name(&format!("p{}", std::process::id())),
        &ChannelConfig::telemetry(),
    )
    .map_err(|e| format!("telemetry: {e}"))?;
    let mut last_telemetry = Instant::now();
    let sink = RefCell::new(ShmSink {
        publisher,
        batch: StepBatch::default(),
    });

    let print_now = || link.clock().clock_at(McuLink::system_now()) / clock_freq;
    // Start far enough ahead that the first batch is planned long before it is due.
    let start = print_now() + (0.5f64).max(0.25 * scale);
    // Buffering window in print time: 2 s, or 1 s of wall time when the clock runs faster.
    let high_water = (2.0f64).max(1.0 * scale);
    let low_water = high_water / 2.0;
    let lead_ticks = (MIN_LEAD_S * clock_freq) as u64;
    let pace = Duration::from_millis(5);

    let mut pipeline = Pipeline::with_options(
        machine.pipeline_config(clock_freq, args.max_error_us * 1e-6),
        start,
        machine.options,
    )
    .map_err(|e| e.to_string())?;
    let streamer = RefCell::new(StepStreamer::new(dict, &machine.steppers, main.move_count)?);
    let mut warm: Option<AllocCounter> = None;
    let lines = plan_file(
        args,
        &mut pipeline,
        gcode,
        |cmds| {
            let mut streamer = streamer.borrow_mut();
            let mut sink = sink.borrow_mut();
            let now_clock = (print_now() * clock_freq) as u64;
            for &(idx, cmd) in cmds.iter() {
                if let StepCmd::QueueStep { first_clock, .. } = cmd {
                    if first_clock < now_clock + lead_ticks {
                        return Err(format!(
                            "the planner fell behind: a step for {} at print time {:.3} s was ready only {:.1} ms \
                             before it is due (at least {:.0} ms required); print stopped before sending it",
                            machine.steppers[idx].name,
                            first_clock as f64 / clock_freq,
                            (first_clock as f64 - now_clock as f64) / clock_freq * 1e3,
                            MIN_LEAD_S * 1e3
                        ));
                    }
                }
                streamer.push(idx, cmd, &mut *sink)?;
            }
            sink.flush()
        },
        |p| {
            // Flow control: keep between the low and high water marks of buffered print time.
            if p.planned_until() - print_now() > high_water {
                if warm.is_none() {
                    warm = Some(AllocCounter::snapshot());
                }
                while p.planned_until() - print_now() > low_water {
                    if last_telemetry.elapsed() >= Duration::from_secs(1) {
                        last_telemetry = Instant::now();
                        hists.publish(&mut telemetry, started.elapsed().as_nanos() as u64);
                    }
                    mcus.check()?;
                    let t = Instant::now();
                    std::thread::sleep(pace);
                    if let Ok(mut h) = hists.wake_planner.try_lock() {
                        h.record(t.elapsed().saturating_sub(pace).as_nanos() as u64);
                    }
                }
            }
            mcus.check()
        },
        |pipeline, axes| {
            if machine.endstops.is_empty() {
                return Ok(false);
            }
            // Drain the shared-memory hand-off: everything planned so far must be in the link
            // before homing talks to the MCUs directly.
            let published = {
                let mut sink = sink.borrow_mut();
                sink.flush()?;
                sink.publisher.next_seq()
            };
            let deadline = Instant::now() + Duration::from_secs(10);
            while consumed.load(Ordering::Acquire) < published {
                if Instant::now() > deadline {
                    return Err("the IO stage did not take the planned steps before homing".to_string());
                }
                mcus.check()?;
                std::thread::sleep(Duration::from_millis(1));
            }
            let mut streamer = streamer.borrow_mut();
            let mut direct = LinkSink { link };
            let mut ctx = HomingCtx {
                mcus,
                machine,
                pipeline,
                streamer: &mut streamer,
                sink: &mut direct,
                lead: MIN_LEAD_S,
                time_scale: scale,
            };
            let report = home_axes(&mut ctx, axes)?;
            println!("{report}");
            Ok(true)
        },
    )?;
    hists.publish(&mut telemetry, started.elapsed().as_nanos() as u64);
    let mut sink = sink.into_inner();
    let streamer = streamer.into_inner();
    sink.flush()?;
    let allocs = warm.map(|w| AllocCounter::snapshot().since(w).allocations());
    let stats = pipeline.stats();
    let summary = Summary {
        file: args.file.clone(),
        lines,
        moves: stats.moves,
        print_time: pipeline.planned_until() - start,
        wall: 0.0,
        queue_steps: streamer.queue_steps(),
        rows: Vec::new(),
        clock_freq,
        extra: Vec::new(),
    };
    Ok((summary, pipeline, streamer, allocs))
}

/// Waits for the MCU to execute the last step, reads the positions back and checks them.
fn finish_print(
    mcus: &Mcus,
    machine: &Machine,
    pipeline: &Pipeline,
    streamer: &StepStreamer,
    summary: &mut Summary,
    scale: f64,
) -> Result<(), String> {
    let main = mcus.main();
    let link = &main.link;
    let dict = link.dictionary();
    let clock_freq = main.clock_freq;
    let print_now = || link.clock().clock_at(McuLink::system_now()) / clock_freq;
    let end_clock = streamer.last_step_clock;
    let wait_s = (end_clock as f64 / clock_freq - print_now()).max(0.0) / scale + 5.0;
    let deadline = Instant::now() + Duration::from_secs_f64(wait_s);
    link.wait_idle(Duration::from_secs_f64(wait_s))
        .map_err(|e| e.to_string())?;
    while print_now() * clock_freq < end_clock as f64 + 0.01 * clock_freq {
        mcus.check()?;
        if Instant::now() > deadline {
            return Err("the MCU clock did not reach the end of the print in time".to_string());
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    mcus.check()?;
    let host_positions = pipeline.stepper_positions();
    let commanded = pipeline.position();
    let steps_sent = streamer.steps_sent();
    for (i, s) in machine.steppers.iter().enumerate() {
        let q = dict
            .encode("stepper_get_position", &[s.oid as i64])
            .map_err(|e| e.to_string())?;
        // Retried: an answer lost on a noisy line is not retransmitted (the query is idempotent).
        let mut reply = link.query(
            q,
            "stepper_position",
            Some(("oid", s.oid as i64)),
            Duration::from_secs(1),
        );
        for _ in 0..3 {
            if reply.is_ok() || link.error().is_some() {
                break;
            }
            reply = link.query(
                q,
                "stepper_position",
                Some(("oid", s.oid as i64)),
                Duration::from_secs(1),
            );
        }
        let reply = reply.map_err(|e| e.to_string())?;
        let raw = reply.get("pos").unwrap_or(0);
        let mcu_pos = if s.dir_pin.invert { -raw } else { raw };
        let host_pos = host_positions.get(i).copied().unwrap_or(0);
        summary.rows.push((
            s.name.clone(),
            steps_sent[i],
            mcu_pos,
            host_pos,
            commanded[s.axis],
        ));
    }
    if let Some((name, _, m, h, _)) = summary.rows.iter().find(|r| r.2 != r.3) {
        return Err(format!(
            "{name}: the MCU reports position {m} steps but the host sent {h}"
        ));
    }
    if let Some(margin) = link.stats().min_lead_margin_ticks {
        if (margin as f64) < MIN_LEAD_S * clock_freq {
            return Err(format!(
                "a step command reached the MCU with only {:.1} ms lead (at least {:.0} ms required)",
                margin as f64 / clock_freq * 1e3,
                MIN_LEAD_S * 1e3
            ));
        }
    }
    Ok(())
}
