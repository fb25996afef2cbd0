//! `cadence print --io-process` / `--io-attach NAME`: the planner in this process, the IO stage
//! (the MCU connections) in a `cadence serve --role io` process.
//!
//! This side starts the IO process (or attaches to a running one), waits for its `READY`,
//! reads the main MCU's [`McuInfo`] (data dictionary, `CLOCK_FREQ`, move queue size, and the
//! configuration CRC, which must equal the one this process computes from its own printer.cfg),
//! then runs the same planner thread as an in-process print against the clock snapshots the IO
//! process publishes. A relay thread (not real-time) copies the newest snapshot into a seqlock
//! ([`links::clocksync::ClockShared`]) and watches the IO process's status, so the planner
//! thread reads its clock lock-free and without touching iceoryx2. At the end it sends
//! `FINISH`, waits for `DONE` with the MCU's stepper positions and checks them against its own.
//! The handshake and payloads are documented in [`super::payloads`].
//!
//! Homing needs the trigger relay and the step queue of the MCU link in the planner's process:
//! a G28 on a printer with endstops is refused in this mode with a clear error.

use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use links::clocksync::{ClockEstimate, ClockShared};
use links::dict::Dictionary;
use links::mcu::McuLink;
use rt_core::logger::{Arg, Level};
use rt_core::os::apply_rt;
use rt_core::shm::{open_node, ChannelConfig, ShmError, ShmPublisher, ShmSubscriber};
use sysconfig::printer::PrinterConfig;

use super::payloads::{
    clock_service_name, control_kind, control_service_name, info_service_name, io_state, status_service_name,
    ClockSnapshot, IoControl, IoStatus, McuInfo,
};
use super::{IoProcessError, OffMainMcu};
use crate::events::Latch;
use crate::gcode_feed::GcodeInput;
use crate::hardware::Machine;
use crate::job::{LiveOutcome, PrintJob};
use crate::latency::{Hists, PLANNER_SOURCES};
use crate::live;
use crate::logging::Logging;
use crate::planner_thread::{McuSide, Planned, PlannerError, PlannerStage};
use crate::realtime::RtConfig;

type Ipc = iceoryx2::prelude::ipc::Service;

/// Longest wait for the IO process to connect its MCUs and report `READY`.
const READY_TIMEOUT: Duration = Duration::from_secs(60);
/// How often the relay thread looks for new clock snapshots and status.
const RELAY_PERIOD: Duration = Duration::from_millis(5);

/// CRC-32 of the configuration commands for MCU `mcu` (the `finalize_config` value): both
/// processes compute it, so a planner and an IO process with different printer configs (other
/// oids or pins) refuse to work together.
pub(crate) fn config_crc(dict: &Dictionary, machine: &Machine, mcu: &str) -> Result<u32, IoProcessError> {
    let (_, _, crc) =
        crate::mcus::config_commands(dict, machine, mcu).map_err(|source| IoProcessError::Configure {
            mcu: mcu.to_string(),
            source: Box::new(source),
        })?;
    Ok(crc)
}

/// Refuses a printer with steppers on other MCUs than the main one: the IO process serves the
/// main MCU's step stream only.
pub(crate) fn check_single_mcu(machine: &Machine) -> Result<(), OffMainMcu> {
    match machine
        .steppers
        .iter()
        .find(|s| s.mcu != sysconfig::printer::MAIN_MCU)
    {
        Some(s) => Err(OffMainMcu {
            stepper: s.name.clone(),
            mcu: s.mcu.clone(),
        }),
        None => Ok(()),
    }
}

/// The main MCU as the planner sees it when the IO stage runs in another process.
#[derive(Debug)]
pub(crate) struct RemoteMcu {
    pub name: String,
    pub dict: Dictionary,
    pub clock_freq: f64,
    pub move_count: usize,
    clock: ClockShared,
    failed: Latch,
    /// The newest status of the IO process.
    status: Mutex<IoStatus>,
    /// Set once a valid clock snapshot was stored.
    clock_valid: AtomicBool,
}

impl RemoteMcu {
    /// The newest clock fit (lock-free seqlock read).
    pub fn clock(&self) -> ClockEstimate {
        self.clock.load()
    }

    /// The IO process's failure reason, once it failed.
    pub fn failure(&self) -> Option<String> {
        self.failed.reason("the IO process failed")
    }

    /// The IO process's failure, as an error.
    fn failed(&self) -> Result<(), IoProcessError> {
        match self.failure() {
            Some(reason) => Err(IoProcessError::Failed { reason }),
            None => Ok(()),
        }
    }

    fn fail(&self, msg: String) {
        self.failed.set(msg);
    }

    /// Waits (bounded) until the relay stored a valid clock snapshot.
    fn wait_clock(&self) -> Result<(), IoProcessError> {
        let deadline = Instant::now() + Duration::from_secs(10);
        // Acquire pairs with the relay's Release store after the snapshot.
        while !self.clock_valid.load(Ordering::Acquire) {
            self.failed()?;
            if Instant::now() > deadline {
                return Err(IoProcessError::NoClock);
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        Ok(())
    }

    fn status(&self) -> IoStatus {
        self.status.lock().map(|s| *s).unwrap_or_default()
    }
}

/// The IO process this print started (killed if still running when dropped).
#[derive(Debug)]
struct IoChild(Mutex<Option<Child>>);

impl IoChild {
    /// `Some(description)` once the child exited.
    fn exited(&self) -> Option<String> {
        let mut guard = self.0.lock().ok()?;
        let child = guard.as_mut()?;
        match child.try_wait() {
            Ok(Some(status)) => Some(format!("the IO process exited ({status})")),
            Ok(None) => None,
            Err(e) => Some(format!("the IO process cannot be waited for: {e}")),
        }
    }

    /// Waits (bounded) for the child to exit; kills it after `timeout`.
    fn finish(&self, timeout: Duration) -> Option<std::process::ExitStatus> {
        let mut guard = self.0.lock().ok()?;
        let mut child = guard.take()?;
        let deadline = Instant::now() + timeout;
        loop {
            match child.try_wait() {
                Ok(Some(s)) => return Some(s),
                Ok(None) if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(10)),
                _ => {
                    let _ = child.kill();
                    return child.wait().ok();
                }
            }
        }
    }
}

impl Drop for IoChild {
    fn drop(&mut self) {
        if let Ok(mut g) = self.0.lock() {
            if let Some(mut c) = g.take() {
                if matches!(c.try_wait(), Ok(None)) {
                    let _ = c.kill();
                }
                let _ = c.wait();
            }
        }
    }
}

/// Starts `cadence serve --role io` for this print, with this print's settings.
fn spawn_io(args: &PrintJob, instance: &str, time_scale: f64) -> Result<Child, IoProcessError> {
    let exe = std::env::current_exe().map_err(IoProcessError::Executable)?;
    let mut cmd = Command::new(exe);
    cmd.args(["serve", "--role", "io", "--instance", instance]);
    cmd.arg("--parent-pid").arg(std::process::id().to_string());
    if let Some(c) = &args.config {
        cmd.arg("--config").arg(c);
    }
    if args.time_scale.is_some() {
        cmd.arg("--time-scale").arg(time_scale.to_string());
    }
    if let Some(t) = &args.trace {
        cmd.arg("--trace").arg(t);
    }
    if args.no_realtime {
        cmd.arg("--no-realtime");
    }
    if let Some(f) = &args.live.log_file {
        cmd.arg("--log-file").arg(f);
    }
    cmd.arg("--log-level").arg(args.live.log_level.name());
    cmd.stdin(Stdio::null())
        .stdout(Stdio::inherit())
        .stderr(Stdio::inherit());
    cmd.spawn().map_err(IoProcessError::Spawn)
}

/// Runs a live print with the IO stage in another process; prints the summary.
pub(crate) fn run(
    args: &PrintJob,
    cfg: &PrinterConfig,
    machine: &Machine,
    gcode: GcodeInput,
) -> Result<LiveOutcome, IoProcessError> {
    let started = Instant::now();
    check_single_mcu(machine)?;
    let simulated = cfg.mcus.iter().any(|m| m.is_simulated());
    if args.time_scale.is_some() && !simulated {
        return Err(IoProcessError::TimeScaleNotSimulated);
    }
    let time_scale = args.time_scale.unwrap_or(cfg.simulator.time_scale);
    let logging = Logging::start(args.live.log_level, args.live.log_file.clone())?;
    let log = logging.handle("main");
    let hists = Hists::new();
    let rt = RtConfig::from_section(&cfg.realtime, args.no_realtime);
    let _idle_hold = rt.hold_idle_latency();
    let (instance, child) = match &args.live.io_attach {
        Some(name) => (name.clone(), IoChild(Mutex::new(None))),
        None => {
            let instance = format!("p{}", std::process::id());
            let child = spawn_io(args, &instance, time_scale)?;
            (instance, IoChild(Mutex::new(Some(child))))
        }
    };
    let main_name = cfg
        .mcus
        .first()
        .map(|m| m.name.clone())
        .ok_or(IoProcessError::NoMcu)?;
    let (node, _) = open_node::<Ipc>(&format!("cadence-print-{}", std::process::id()))?;
    let mut control = ShmPublisher::<Ipc, IoControl>::open(
        &node,
        &control_service_name(&instance),
        &ChannelConfig::control(),
    )?;
    log.log(Level::Info, "waiting for the IO process", []);
    let remote = attach(&node, &instance, &child, machine, &main_name)?;
    let run = RemoteRun {
        machine,
        remote: &remote,
        child: &child,
        instance: &instance,
        rt: &rt,
        hists: &hists,
        log: &log,
        time_scale,
        max_error_s: args.max_error_us * 1e-6,
        started,
    };
    let result = print_remote(&run, gcode, &mut control);
    let exit = child.finish(Duration::from_secs(30));
    let summary = result?;
    if let Some(status) = exit {
        if !status.success() {
            return Err(IoProcessError::Exited(status));
        }
    }
    crate::job::live_outcome(
        summary,
        started,
        args.histograms.as_deref(),
        &hists,
        logging,
        Vec::new(),
    )
    .map_err(IoProcessError::from)
}

/// What the print against an IO process works with.
#[derive(Debug, Clone, Copy)]
struct RemoteRun<'a> {
    machine: &'a Machine,
    remote: &'a RemoteMcu,
    child: &'a IoChild,
    instance: &'a str,
    rt: &'a RtConfig,
    hists: &'a Hists,
    log: &'a rt_core::logger::LoggerHandle,
    time_scale: f64,
    /// Maximum step time error of the compression (s).
    max_error_s: f64,
    started: Instant,
}

/// The print proper: the relay thread, the planner thread against the IO process's clock and
/// telemetry, then the FINISH/DONE hand-shake and the checks of what the IO process read back.
fn print_remote(
    r: &RemoteRun<'_>,
    gcode: GcodeInput,
    control: &mut ShmPublisher<Ipc, IoControl>,
) -> Result<crate::summary::Summary, IoProcessError> {
    let stop_relay = AtomicBool::new(false);
    let telemetry_stop = AtomicBool::new(false);
    // The planner watches what the IO process took only before homing, which is refused here.
    let consumed = [AtomicU64::new(0)];
    let r = *r;
    std::thread::scope(|scope| {
        let (remote, instance, child) = (r.remote, r.instance, r.child);
        let stop_flag = &stop_relay;
        let relay = std::thread::Builder::new()
            .name("io-relay".to_string())
            .spawn_scoped(scope, move || relay(remote, instance, child, stop_flag))
            .map_err(|source| IoProcessError::Thread {
                what: "relay thread",
                source,
            })?;
        let stop = || {
            stop_relay.store(true, Ordering::Release);
            let _ = relay.join();
        };
        if let Err(e) = remote.wait_clock() {
            stop();
            return Err(e);
        }
        let planner = spawn_planner(scope, r, gcode, &consumed);
        let telemetry_stop = &telemetry_stop;
        let (hists, started) = (r.hists, r.started);
        let telemetry = std::thread::Builder::new()
            .name("telemetry".to_string())
            .spawn_scoped(scope, move || {
                crate::telemetry::telemetry_thread(instance, hists, started, PLANNER_SOURCES, telemetry_stop)
            });
        let planned = planner.and_then(|p| match p.join() {
            Ok(result) => result.map_err(IoProcessError::from),
            Err(_) => Err(IoProcessError::Panicked {
                what: "planner thread",
            }),
        });
        telemetry_stop.store(true, Ordering::Release);
        if let Ok(t) = telemetry {
            if let Ok(Err(e)) = t.join() {
                eprintln!("cadence: telemetry: {e}");
            }
        }
        let (mut summary, pipeline, streams, allocs, batches) = match planned {
            Ok(p) => p,
            Err(e) => {
                let _ = control.send_with(|c| c.kind = control_kind::ABORT);
                stop();
                // The IO process's own failure explains a failed hand-off best.
                return Err(remote.failed().err().unwrap_or(e));
            }
        };
        let batches = batches.first().copied().unwrap_or(0);
        let done = finish_handshake(control, remote, &streams, batches, r.time_scale, r.log);
        stop();
        let done = done?;
        let _ = control.send_with(|c| c.kind = control_kind::DONE_SEEN);
        check_done(r.machine, &pipeline, &streams, &done, remote, &mut summary)?;
        summary.extra.extend(hists.report(remote.clock_freq));
        summary.extra.push(format!(
            "allocations after warm-up: planner {}; io stage in process {} ({} batches)",
            allocs.map_or("n/a".to_string(), |n| n.to_string()),
            done.pid,
            done.batches
        ));
        Ok(summary)
    })
}

/// Starts the planner thread against the IO process's MCU.
fn spawn_planner<'scope, 'env: 'scope>(
    scope: &'scope std::thread::Scope<'scope, 'env>,
    r: RemoteRun<'env>,
    gcode: GcodeInput,
    consumed: &'env [AtomicU64],
) -> Result<std::thread::ScopedJoinHandle<'scope, Result<Planned, PlannerError>>, IoProcessError> {
    let planner_spec = r.rt.planner_spec();
    let planner_log = r.log.with_tag("planner");
    std::thread::Builder::new()
        .name("planner".to_string())
        .spawn_scoped(scope, move || {
            apply_rt(&planner_spec);
            let stage = PlannerStage {
                machine: r.machine,
                side: McuSide::Remote(r.remote),
                scale: r.time_scale,
                max_error_s: r.max_error_s,
                instance: r.instance,
                consumed,
                hists: r.hists,
                log: &planner_log,
                rt: r.rt,
                session: None,
                heaters: None,
            };
            crate::planner_thread::planner_stage(gcode, &stage)
        })
        .map_err(|source| IoProcessError::Thread {
            what: "planner thread",
            source,
        })
}

/// Waits for the IO process's `READY` and its main MCU's info, and checks that it configured
/// the MCU as this printer config says (the configuration CRC).
fn attach(
    node: &iceoryx2::node::Node<Ipc>,
    instance: &str,
    child: &IoChild,
    machine: &Machine,
    main_name: &str,
) -> Result<RemoteMcu, IoProcessError> {
    wait_ready(node, instance, child)?;
    let info = wait_info(node, instance, main_name, child)?;
    let dict = Dictionary::from_compressed(info.dict()).map_err(|source| IoProcessError::BadDictionary {
        mcu: main_name.to_string(),
        source,
    })?;
    let ours = config_crc(&dict, machine, main_name)?;
    if ours != info.config_crc {
        return Err(IoProcessError::ConfigMismatch {
            mcu: main_name.to_string(),
            theirs: info.config_crc,
            ours,
        });
    }
    Ok(RemoteMcu {
        name: main_name.to_string(),
        dict,
        clock_freq: info.clock_freq,
        move_count: info.move_count as usize,
        clock: ClockShared::new(ClockEstimate::INVALID),
        failed: Latch::default(),
        status: Mutex::new(IoStatus::default()),
        clock_valid: AtomicBool::new(false),
    })
}

/// Sends `FINISH` (the batches published and the last step clock) and waits for `DONE`.
fn finish_handshake(
    control: &mut ShmPublisher<Ipc, IoControl>,
    remote: &RemoteMcu,
    streams: &crate::step_stream::StepStreams,
    batches: u64,
    time_scale: f64,
    log: &rt_core::logger::LoggerHandle,
) -> Result<IoStatus, IoProcessError> {
    let end_clock = streams.mcus.first().map_or(0, |m| m.streamer.last_step_clock);
    control
        .send_with(|c| {
            c.kind = control_kind::FINISH;
            c.batches = batches;
            c.end_clock = end_clock;
        })
        .map_err(IoProcessError::Control)?;
    log.log(
        Level::Info,
        "sent FINISH: batches, end clock",
        [Arg::U(batches), Arg::U(end_clock)],
    );
    wait_done(remote, end_clock, time_scale)
}

/// Waits (bounded: the rest of the print at the simulator's speed, plus slack) for the IO
/// process's `DONE`, which carries the stepper positions it read back.
fn wait_done(remote: &RemoteMcu, end_clock: u64, time_scale: f64) -> Result<IoStatus, IoProcessError> {
    let clock_freq = remote.clock_freq;
    let now_s = remote.clock().clock_at(McuLink::system_now()) / clock_freq;
    let wait = (end_clock as f64 / clock_freq - now_s).max(0.0) / time_scale + 30.0;
    let deadline = Instant::now() + Duration::from_secs_f64(wait);
    loop {
        let s = remote.status();
        if s.state == io_state::DONE {
            return Ok(s);
        }
        remote.failed()?;
        if Instant::now() > deadline {
            return Err(IoProcessError::NotFinished { secs: wait });
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Checks the positions and the lead the IO process reported against this side's, adding its
/// lead line to the summary.
fn check_done(
    machine: &Machine,
    pipeline: &planner::pipeline::Pipeline,
    streams: &crate::step_stream::StepStreams,
    done: &IoStatus,
    remote: &RemoteMcu,
    summary: &mut crate::summary::Summary,
) -> Result<(), IoProcessError> {
    let clock_freq = remote.clock_freq;
    live::check_positions(
        machine,
        pipeline,
        &streams.steps_sent(),
        done.positions(),
        summary,
    )?;
    let min_lead = (done.min_lead_margin_ticks != i64::MIN).then_some(done.min_lead_margin_ticks);
    if let Some(m) = min_lead {
        summary.extra.push(format!(
            "mcu '{}' (in IO process {}): min lead margin {:.1} ms over {} clocked messages (required {:.0} ms)",
            remote.name,
            done.pid,
            m as f64 / clock_freq * 1e3,
            done.clocked_msgs,
            crate::MIN_LEAD_S * 1e3
        ));
    }
    Ok(live::check_min_lead(&remote.name, min_lead, clock_freq)?)
}

/// Waits (bounded) for the IO process's `READY`.
fn wait_ready(
    node: &iceoryx2::node::Node<Ipc>,
    instance: &str,
    child: &IoChild,
) -> Result<(), IoProcessError> {
    let mut status =
        ShmSubscriber::<Ipc, IoStatus>::open(node, &status_service_name(instance), &ChannelConfig::latest())?
            .accept_any_start();
    let deadline = Instant::now() + READY_TIMEOUT;
    loop {
        if let Some(s) = status.latest()? {
            match s.state {
                io_state::READY => return Ok(()),
                io_state::FAILED => {
                    return Err(IoProcessError::FailedAtStart {
                        reason: s.msg().to_string(),
                    })
                }
                _ => {}
            }
        }
        if let Some(reason) = child.exited() {
            return Err(IoProcessError::Failed { reason });
        }
        if Instant::now() > deadline {
            return Err(IoProcessError::NotReady {
                secs: READY_TIMEOUT.as_secs(),
            });
        }
        let _ = status.wait(Duration::from_millis(20));
    }
}

/// Reads (bounded wait) the info the IO process published for MCU `mcu`.
fn wait_info(
    node: &iceoryx2::node::Node<Ipc>,
    instance: &str,
    mcu: &str,
    child: &IoChild,
) -> Result<Box<McuInfo>, IoProcessError> {
    let mut sub =
        ShmSubscriber::<Ipc, McuInfo>::open(node, &info_service_name(instance, mcu), &ChannelConfig::info())?
            .accept_any_start();
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        if let Some(info) = sub.latest()? {
            return Ok(Box::new(info));
        }
        if let Some(reason) = child.exited() {
            return Err(IoProcessError::Failed { reason });
        }
        if Instant::now() > deadline {
            return Err(IoProcessError::NoInfo { mcu: mcu.to_string() });
        }
        let _ = sub.wait(Duration::from_millis(20));
    }
}

/// The relay thread: newest clock snapshot → seqlock, newest status → `remote`, IO process
/// failure or exit → `remote.fail`.
fn relay(remote: &RemoteMcu, instance: &str, child: &IoChild, stop: &AtomicBool) {
    let setup = || -> Result<_, ShmError> {
        let (node, _) = open_node::<Ipc>(&format!("cadence-relay-{}", std::process::id()))?;
        let clock = ShmSubscriber::<Ipc, ClockSnapshot>::open(
            &node,
            &clock_service_name(instance, &remote.name),
            &ChannelConfig::latest(),
        )?
        .accept_any_start();
        let status = ShmSubscriber::<Ipc, IoStatus>::open(
            &node,
            &status_service_name(instance),
            &ChannelConfig::latest(),
        )?
        .accept_any_start();
        Ok((node, clock, status))
    };
    let (_node, mut clock, mut status) = match setup() {
        Ok(s) => s,
        Err(e) => return remote.fail(format!("clock relay: {e}")),
    };
    // Acquire pairs with the Release store of the thread that stops the relay.
    while !stop.load(Ordering::Acquire) {
        match clock.latest() {
            Ok(Some(c)) if c.valid != 0 => {
                remote
                    .clock
                    .store(ClockEstimate::new(c.ref_time, c.ref_clock, c.freq));
                remote.clock_valid.store(true, Ordering::Release);
            }
            Ok(_) => {}
            Err(e) => remote.fail(format!("clock relay: {e}")),
        }
        match status.latest() {
            Ok(Some(s)) => {
                if s.state == io_state::FAILED {
                    remote.fail(format!("the IO process failed: {}", s.msg()));
                }
                if let Ok(mut g) = remote.status.lock() {
                    *g = s;
                }
            }
            Ok(None) => {}
            Err(e) => remote.fail(format!("io status: {e}")),
        }
        if let Some(e) = child.exited() {
            if remote.status().state != io_state::DONE {
                remote.fail(e);
            }
        }
        std::thread::sleep(RELAY_PERIOD);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn machine(cfg_text: &str) -> Machine {
        let cfg = sysconfig::parse_str(cfg_text, std::path::Path::new("printer.cfg")).unwrap();
        Machine::from_config(&cfg).unwrap()
    }

    #[test]
    fn config_crc_tells_printer_configs_apart() {
        let text = include_str!("../../examples/simulated-cartesian.cfg");
        let dict = crate::wire_check::load_dictionary(None).unwrap();
        let a = config_crc(&dict, &machine(text), "mcu").unwrap();
        assert_eq!(a, config_crc(&dict, &machine(text), "mcu").unwrap());
        let moved = text.replace("step_pin: PA0", "step_pin: PA4");
        assert_ne!(a, config_crc(&dict, &machine(&moved), "mcu").unwrap());
    }

    #[test]
    fn steppers_on_another_mcu_are_refused_by_the_io_process() {
        let m = machine(include_str!("../../examples/simulated-toolboard.cfg"));
        let err = check_single_mcu(&m).unwrap_err().to_string();
        assert!(err.contains("[stepper_z] is driven by mcu 'toolboard'"), "{err}");
        let m = machine(include_str!("../../examples/simulated-multi-mcu.cfg"));
        assert!(check_single_mcu(&m).is_ok());
    }
}
