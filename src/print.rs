//! `cadence print`: G-code → planner → step compression → MCU (live) or a wire file (batch).

use std::collections::BTreeSet;
use std::fs::File;
use std::io::{BufReader, BufWriter};
use std::path::{Path, PathBuf};
use std::time::Instant;

use clap::Args;
use planner::gcode::{Command, GcodeReader};
use planner::machine::{Applied, PlanErrorKind};
use planner::pipeline::Pipeline;
use planner::stepgen::StepCmd;
use sysconfig::printer::PrinterConfig;

use crate::accessories::Accessories;
use crate::live::{self, Hists, RtConfig};
use crate::machine::Machine;
use crate::mcus::{ConnectOptions, Mcus};
use crate::sink::{BatchSink, Sink};
use crate::streams::{McuParams, StepStreams};

/// Arguments of `cadence print`.
#[derive(Debug, Args)]
pub struct PrintArgs {
    /// The G-code file to print.
    pub file: PathBuf,
    /// Klipper-format printer.cfg (default: the built-in simulated cartesian printer).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Simulated MCU clock runs this many times faster than the wall clock (default: the
    /// config's [simulator] time_scale, else 1).
    #[arg(long)]
    pub time_scale: Option<f64>,
    /// No MCU and no real-time waiting: write the exact wire stream to this file (another MCU
    /// with steppers gets its own file, `-NAME` inserted before the extension).
    #[arg(long)]
    pub batch: Option<PathBuf>,
    /// Data dictionary (zlib-compressed JSON as served by identify, or plain JSON as Klipper's
    /// out/klipper.dict) for --batch; default: the Cadence firmware's own.
    #[arg(long)]
    pub dictionary: Option<PathBuf>,
    /// Write the simulated MCU's step trace to this file.
    #[arg(long)]
    pub trace: Option<PathBuf>,
    /// Maximum step time error of the compression, in microseconds.
    #[arg(long, default_value_t = 25.0)]
    pub max_error_us: f64,
    /// Don't pin threads, use SCHED_FIFO or lock memory.
    #[arg(long)]
    pub no_realtime: bool,
    /// Save the print's latency histograms to this file (HdrHistogram V2 interval log).
    #[arg(long)]
    pub histograms: Option<PathBuf>,
    /// Logging and where the IO stage runs (see `live::LiveArgs`).
    #[command(flatten)]
    pub live: live::LiveArgs,
}

/// Lead every step command must have at the MCU, in print seconds.
pub(crate) const MIN_LEAD_S: f64 = 0.100;
/// Most time scale the simulator's 32-bit clock allows (it wraps every 86 s / scale at 50 MHz).
const MAX_TIME_SCALE: f64 = 50.0;

pub fn run(args: &PrintArgs) -> Result<(), String> {
    if !(args.max_error_us > 0.0 && args.max_error_us <= 1000.0) {
        return Err(format!(
            "--max-error-us {}: must be in (0, 1000]",
            args.max_error_us
        ));
    }
    if let Some(scale) = args.time_scale {
        if !(scale > 0.0 && scale <= MAX_TIME_SCALE) {
            return Err(format!("--time-scale {scale}: must be in (0, {MAX_TIME_SCALE}]"));
        }
    }
    // Open the G-code first: a missing file must not start any MCU.
    let gcode = File::open(&args.file).map_err(|e| format!("{}: {e}", args.file.display()))?;
    let cfg = crate::machine::load_config(args.config.as_deref())?;
    for w in &cfg.warnings {
        eprintln!("cadence: warning: {w}");
    }
    let machine = Machine::from_config(&cfg)?;
    match &args.batch {
        Some(out) => run_batch(args, &cfg, &machine, gcode, out),
        None => run_live(args, &cfg, &machine, gcode),
    }
}

/// Counts and reports G-code commands the planner does not implement yet, once per name.
#[derive(Debug, Default)]
struct Warnings {
    seen: BTreeSet<String>,
}

impl Warnings {
    fn unsupported(&mut self, file: &Path, line: usize, name: &str) {
        // Look up first: the name is copied (allocated) only the first time it is seen.
        if !self.seen.contains(name) && self.seen.insert(name.to_string()) {
            eprintln!(
                "cadence: warning: {}:{line}: {name} is not implemented yet and is ignored (reported once)",
                file.display()
            );
        }
    }
}

/// A G-code command that moves with the MCUs in the loop: `motion` in [`plan_file`] runs it on a
/// live print (and says so) or leaves it to the planner.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum MotionCmd<'a> {
    /// G28 with the axes to home.
    Home([bool; 3]),
    /// PROBE, PROBE_ACCURACY or QUERY_PROBE, as written.
    Probe { name: &'a str, raw: &'a str },
}

impl MotionCmd<'_> {
    /// The command's name for errors.
    fn name(&self) -> &str {
        match self {
            MotionCmd::Home(_) => "G28",
            MotionCmd::Probe { name, .. } => name,
        }
    }
}

/// Feeds the G-code through the planner, handing step commands to `emit` as they become final.
/// `pace` runs between lines (live flow control; batch passes a no-op); `motion` runs G28 and the
/// probe commands when it can (returns true) with the MCUs in the loop. Heater, fan, display and
/// M114 commands go to `accessories`.
pub(crate) fn plan_file(
    args: &PrintArgs,
    pipeline: &mut Pipeline,
    gcode: File,
    accessories: &mut Accessories,
    mut emit: impl FnMut(&mut Vec<(usize, StepCmd)>) -> Result<(), String>,
    mut pace: impl FnMut(&mut Pipeline) -> Result<(), String>,
    mut motion: impl FnMut(&mut Pipeline, &MotionCmd<'_>) -> Result<bool, String>,
) -> Result<u64, String> {
    let mut warnings = Warnings::default();
    let mut out = Vec::with_capacity(4096);
    let mut lines = 0u64;
    for line in GcodeReader::new(BufReader::with_capacity(1 << 16, gcode)) {
        let line = line.map_err(|e| format!("{}: {e}", args.file.display()))?;
        lines += 1;
        // G28 with real motion where the printer can home; otherwise the planner's own G28
        // (which sets the configured endstop positions). The probe commands likewise.
        let cmd = match &line.cmd {
            Command::Home { x, y, z } => Some(MotionCmd::Home([*x, *y, *z])),
            Command::Other { name, raw } if crate::homing::probe::is_probe_command(name) => {
                Some(MotionCmd::Probe { name, raw })
            }
            _ => None,
        };
        if let Some(cmd) = cmd {
            if motion(pipeline, &cmd)
                .map_err(|e| format!("{}:{}: {}: {e}", args.file.display(), line.line_no, cmd.name()))?
            {
                continue;
            }
        }
        let applied = pipeline.apply(&line).map_err(|e| {
            let hint = match e.kind {
                PlanErrorKind::UnknownCommand(_) => {
                    " (to skip unknown commands with a warning: `unknown_commands: warn` in [gcode] of printer.cfg)"
                }
                _ => "",
            };
            format!("{}: {e}{hint}", args.file.display())
        })?;
        if let Applied::Unsupported(name) = &applied {
            warnings.unsupported(&args.file, line.line_no, name);
        }
        if let Some(w) = accessories.record(line.line_no, &applied) {
            eprintln!("cadence: warning: {}: {w}", args.file.display());
        }
        pipeline.generate(&mut out);
        if !out.is_empty() {
            emit(&mut out)?;
            out.clear();
            pace(pipeline)?;
        }
    }
    pipeline.finish(&mut out);
    emit(&mut out)?;
    Ok(lines)
}

/// Batch mode: the wire stream of each MCU with steppers (the main one to `out`, another one
/// to `out` with `-NAME` inserted, as for traces), every MCU encoded with the one dictionary and
/// its clock counted from print time 0.
fn run_batch(
    args: &PrintArgs,
    cfg: &PrinterConfig,
    machine: &Machine,
    gcode: File,
    out: &Path,
) -> Result<(), String> {
    let started = Instant::now();
    let dict = crate::decode::load_dictionary(args.dictionary.as_deref())?;
    let clock_freq = dict.clock_freq().map_err(|e| e.to_string())?;
    let names: Vec<&str> = cfg.mcus.iter().map(|m| m.name.as_str()).collect();
    let move_count = 16384;
    let params: Vec<McuParams<'_>> = crate::streams::stream_mcus(machine, &names)
        .into_iter()
        .map(|i| McuParams {
            name: names[i],
            mcu_index: i,
            dict: &dict,
            clock_freq,
            move_count,
        })
        .collect();
    let mut sinks = Vec::with_capacity(params.len());
    let mut paths = Vec::with_capacity(params.len());
    for (k, m) in params.iter().enumerate() {
        let path = crate::mcus::trace_path(out, m.name, k == 0);
        let file = File::create(&path).map_err(|e| format!("{}: {e}", path.display()))?;
        let mut sink = BatchSink::new(BufWriter::with_capacity(1 << 16, file));
        for c in crate::mcus::config_commands(&dict, machine, m.name)
            .map_err(|e| format!("mcu '{}': {e}", m.name))?
            .0
        {
            sink.send(c)?;
        }
        sinks.push(sink);
        paths.push(path);
    }
    let mut streams = StepStreams::new(machine, &params)?;
    // Batch mode runs flat out: step generation and compression on every core.
    let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    let mut pipeline = machine.batch_pipeline(clock_freq, args.max_error_us * 1e-6, threads)?;
    let mut accessories = Accessories::new(false);
    let lines = plan_file(
        args,
        &mut pipeline,
        gcode,
        &mut accessories,
        |cmds| {
            for &(idx, cmd) in cmds.iter() {
                streams.push(idx, cmd, &mut sinks[..])?;
            }
            Ok(())
        },
        |_| Ok(()),
        |_, _| Ok(false),
    )?;
    for s in &mut sinks {
        s.finish()?;
    }
    let stats = pipeline.stats();
    let files: Vec<String> = paths.iter().map(|p| p.display().to_string()).collect();
    println!("batch: {} -> {}", args.file.display(), files.join(", "));
    println!(
        "  lines {lines}, moves {}, print time {:.3} s",
        stats.moves,
        pipeline.planned_until()
    );
    for (s, n) in machine.steppers.iter().zip(streams.steps_sent()) {
        println!("  {:<10} {n} steps", s.name);
    }
    println!(
        "  queue_step {}, blocks {}, wire bytes {}, wall {:.3} s",
        streams.queue_steps(),
        sinks.iter().map(|s| s.blocks).sum::<u64>(),
        sinks.iter().map(|s| s.bytes).sum::<u64>(),
        started.elapsed().as_secs_f64()
    );
    for line in accessories.lines() {
        println!("  {line}");
    }
    Ok(())
}

fn run_live(args: &PrintArgs, cfg: &PrinterConfig, machine: &Machine, gcode: File) -> Result<(), String> {
    if args.live.remote() {
        return crate::remote::run(args, cfg, machine, gcode);
    }
    let started = Instant::now();
    let simulated = cfg.mcus.iter().any(|m| m.is_simulated());
    if args.time_scale.is_some() && !simulated {
        return Err("--time-scale only applies to a simulated printer".to_string());
    }
    let time_scale = args.time_scale.unwrap_or(cfg.simulator.time_scale);
    let hists = Hists::new();
    let logging = live::Logging::start(args.live.log_level, args.live.log_file.clone())?;
    let rt = RtConfig::from_section(&cfg.realtime, args.no_realtime);
    let _idle_hold = rt.hold_idle_latency();
    let opts = ConnectOptions {
        time_scale,
        trace: args.trace.clone(),
        lead_hooks: Some(hists.lead_hooks(logging.handle("io-link"))),
        io_rt: Some(rt.link_spec()),
    };
    let mut mcus = Mcus::connect(cfg, machine, opts)?;
    hists.set_min_lead(&mcus);
    let log = logging.handle("main");
    let run = live::LiveRun {
        started,
        scale: time_scale,
        rt: &rt,
        hists: &hists,
        log: &log,
    };
    let result = live::print_on(args, machine, &mcus, gcode, &run);
    let stats = mcus.close();
    let mut summary = result?;
    summary.wall = started.elapsed().as_secs_f64();
    if let Some(path) = &args.histograms {
        hists.save(path, summary.wall)?;
    }
    summary.extra.push(logging.finish());
    summary.print(&stats);
    for line in rt_core::os::rt_report() {
        eprintln!("cadence: {line}");
    }
    Ok(())
}

/// What a live print reports at the end.
#[derive(Debug)]
pub(crate) struct Summary {
    pub file: PathBuf,
    pub lines: u64,
    pub moves: u64,
    pub print_time: f64,
    pub wall: f64,
    pub queue_steps: u64,
    /// (stepper, steps sent, MCU position, host position, commanded axis position)
    pub rows: Vec<(String, u64, i64, i64, f64)>,
    pub clock_freq: f64,
    /// Each streamed MCU's CLOCK_FREQ (for its lead figures; others use `clock_freq`).
    pub mcu_freqs: Vec<(String, f64)>,
    /// Further report lines (histograms, allocation counts).
    pub extra: Vec<String>,
}

impl Summary {
    pub(crate) fn print(&self, all_stats: &[(String, links::mcu::LinkStats)]) {
        println!("print: {}", self.file.display());
        println!(
            "  lines {}, moves {}, queue_step {}, print time {:.3} s, wall {:.3} s",
            self.lines, self.moves, self.queue_steps, self.print_time, self.wall
        );
        println!(
            "  {:<10} {:>10} {:>12} {:>12} {:>12}",
            "stepper", "steps", "mcu pos", "host pos", "position mm"
        );
        for (name, steps, mcu_pos, host_pos, mm) in &self.rows {
            let flag = if mcu_pos == host_pos { "" } else { "  MISMATCH" };
            println!("  {name:<10} {steps:>10} {mcu_pos:>12} {host_pos:>12} {mm:>12.4}{flag}");
        }
        for line in &self.extra {
            println!("  {line}");
        }
        for (name, stats) in all_stats {
            let freq = self
                .mcu_freqs
                .iter()
                .find(|(n, _)| n == name)
                .map_or(self.clock_freq, |&(_, f)| f);
            if let Some(margin) = stats.min_lead_margin_ticks {
                println!(
                    "  mcu '{name}': min lead margin {:.1} ms over {} clocked messages (required {:.0} ms)",
                    margin as f64 / freq * 1e3,
                    stats.clocked_msgs,
                    MIN_LEAD_S * 1e3
                );
            }
            let q = &stats.queue;
            println!(
                "  mcu '{name}': {} bytes written, {} read, {} retransmitted, {} invalid; srtt {:.3} ms, \
                 clock residual {:.1} us",
                q.bytes_write,
                q.bytes_read,
                q.bytes_retransmit,
                q.bytes_invalid,
                q.srtt * 1e3,
                stats.clock_residual_us
            );
        }
    }
}
