//! Planner throughput benchmark: G-code file → planned moves → compressed step commands, in batch
//! mode (no MCU), with the figures issue 3 asks for: moves/s, steps/s, `queue_step` commands,
//! wire bytes, wall time and peak RSS.
//!
//! Wire bytes are computed exactly as the batch sink would write them: every command's encoded
//! length is counted (`vlq::encoded_len` of the message id and parameters, with the ids of a
//! data dictionary when one is given, else one-byte ids as in Klipper's firmware) and packed in
//! order into blocks of at most
//! `MESSAGE_PAYLOAD_MAX` payload bytes plus `MESSAGE_MIN` bytes of framing.
//! Peak RSS is the process's `VmHWM` (Linux), so it covers everything the process did so far.

use std::fs::File;
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::time::Instant;

use links::proto::{vlq, MESSAGE_MIN, MESSAGE_PAYLOAD_MAX};
use planner::compress::SearchTuning;
use planner::gcode::GcodeReader;
use planner::kinematics::Kinematics;
use planner::machine::Applied;
use planner::pipeline::{Pipeline, PipelineConfig, PipelineOptions};
use planner::stepgen::StepCmd;
use sysconfig::printer::PrinterConfig;

/// What to run.
#[derive(Debug, Clone)]
pub struct PlanOptions {
    /// Largest step time error (s); Klipper's 25 µs by default.
    pub max_error_s: f64,
    /// MCU clock (Hz).
    pub clock_freq: f64,
    /// Worker threads for step generation + compression (0 = everything on the caller's thread).
    pub threads: usize,
    /// Stop after this many G-code lines (`None`: the whole file).
    pub max_lines: Option<usize>,
    /// Message ids of `queue_step`, `set_next_step_dir`, `reset_step_clock`.
    pub msg_ids: [u32; 3],
    /// Every command from the per-step search, none from a cruise line's formula (the
    /// reference the line commands are measured against).
    pub per_step: bool,
    /// How the commands off the cruise lines are found ([`Pipeline::set_tuning`]; ignored with
    /// `per_step`, which is [`SearchTuning::SEARCH`] without line commands).
    pub tuning: SearchTuning,
    /// Steps the compression's lookahead may end a command early
    /// ([`Pipeline::set_lookahead_backoff`]; `None`: the compressor's default).
    pub lookahead: Option<usize>,
}

impl Default for PlanOptions {
    fn default() -> Self {
        PlanOptions {
            max_error_s: 25e-6,
            clock_freq: 50e6,
            threads: 2,
            max_lines: None,
            msg_ids: [20, 21, 22],
            per_step: false,
            tuning: SearchTuning::default(),
            lookahead: None,
        }
    }
}

impl PlanOptions {
    /// Takes the message ids from a data dictionary.
    pub fn with_dictionary(mut self, dict: &links::dict::Dictionary) -> Result<Self, String> {
        let id = |n: &str| dict.encoder(n).map(|e| e.id()).map_err(|e| e.to_string());
        self.msg_ids = [
            id("queue_step")?,
            id("set_next_step_dir")?,
            id("reset_step_clock")?,
        ];
        self.clock_freq = dict.clock_freq().map_err(|e| e.to_string())?;
        Ok(self)
    }
}

/// Figures of one run.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PlanReport {
    pub lines: u64,
    pub moves: u64,
    pub steps: u64,
    pub queue_steps: u64,
    /// All step commands (queue_step, set_next_step_dir, reset_step_clock).
    pub commands: u64,
    pub wire_bytes: u64,
    pub wall_s: f64,
    /// Peak resident set of the process (bytes), 0 when unknown.
    pub peak_rss_bytes: u64,
    /// Print time covered (s).
    pub print_time_s: f64,
    /// Unknown G-code commands skipped (`[gcode] unknown_commands: warn`, the default; else they are errors).
    pub skipped_unknown: u64,
    /// The step commands of each stepper, by the planner's stepper index (the printer's
    /// steppers in config order; `step_pin` unset).
    pub per_stepper: Vec<crate::stream::StepperCounts>,
}

impl PlanReport {
    pub fn moves_per_s(&self) -> f64 {
        self.moves as f64 / self.wall_s.max(1e-9)
    }
    pub fn steps_per_s(&self) -> f64 {
        self.steps as f64 / self.wall_s.max(1e-9)
    }
}

impl std::fmt::Display for PlanReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "lines {}, moves {}, steps {}, queue_step {} (+ {} set_next_step_dir/reset_step_clock), \
             wire bytes {}, wall {:.4} s, {:.0} moves/s, {:.0} steps/s, peak RSS {:.1} MB, \
             print time {:.1} s",
            self.lines,
            self.moves,
            self.steps,
            self.queue_steps,
            self.commands - self.queue_steps,
            self.wire_bytes,
            self.wall_s,
            self.moves_per_s(),
            self.steps_per_s(),
            self.peak_rss_bytes as f64 / 1e6,
            self.print_time_s
        )?;
        if self.skipped_unknown > 0 {
            write!(f, ", {} unknown commands skipped", self.skipped_unknown)?;
        }
        Ok(())
    }
}

/// The planner configuration of a validated printer config (see [`sysconfig::planning`]).
pub fn pipeline_config(
    cfg: &PrinterConfig,
    opts: &PlanOptions,
) -> Result<(PipelineConfig, Kinematics), String> {
    sysconfig::planning::pipeline_config(cfg, opts.clock_freq, opts.max_error_s)
}

/// Packs encoded messages into blocks and counts the bytes.
#[derive(Debug, Default)]
pub(crate) struct WireCounter {
    payload: usize,
    pub(crate) bytes: u64,
}

impl WireCounter {
    /// One message of these fields (the message id first).
    pub(crate) fn msg(&mut self, fields: &[u32]) {
        let len: usize = fields.iter().map(|&v| vlq::encoded_len(v)).sum();
        if self.payload + len > MESSAGE_PAYLOAD_MAX {
            self.flush();
        }
        self.payload += len;
    }
    /// Closes the last block.
    pub(crate) fn flush(&mut self) {
        if self.payload > 0 {
            self.bytes += (self.payload + MESSAGE_MIN) as u64;
            self.payload = 0;
        }
    }
}

/// Plans a G-code file for a printer config; see the module docs.
pub fn plan_file(gcode: &Path, cfg: &PrinterConfig, opts: &PlanOptions) -> Result<PlanReport, String> {
    let file = File::open(gcode).map_err(|e| format!("{}: {e}", gcode.display()))?;
    plan_reader(BufReader::with_capacity(1 << 16, file), cfg, opts)
        .map_err(|e| format!("{}: {e}", gcode.display()))
}

/// [`plan_file`] over any reader.
pub fn plan_reader(src: impl BufRead, cfg: &PrinterConfig, opts: &PlanOptions) -> Result<PlanReport, String> {
    let started = Instant::now();
    let (pc, kin) = pipeline_config(cfg, opts)?;
    let steppers = pc.steppers.len();
    let popts = PipelineOptions {
        threads: opts.threads,
        ..sysconfig::planning::pipeline_options(cfg, kin)
    };
    let mut p = Pipeline::with_options(pc, 0.25, popts).map_err(|e| e.to_string())?;
    p.set_line_fit(!opts.per_step);
    p.set_tuning(if opts.per_step {
        SearchTuning::SEARCH
    } else {
        opts.tuning
    });
    if let Some(n) = opts.lookahead {
        p.set_lookahead_backoff(n);
    }
    let mut wire = WireCounter::default();
    let mut rep = PlanReport::default();
    let mut out = Vec::with_capacity(1 << 14);
    let [q_id, d_id, r_id] = opts.msg_ids;
    rep.per_stepper = vec![crate::stream::StepperCounts::default(); steppers];
    let mut count = |out: &mut Vec<(usize, StepCmd)>, rep: &mut PlanReport| {
        for &(idx, c) in out.iter() {
            let oid = idx as u32;
            rep.commands += 1;
            let mut scratch = crate::stream::StepperCounts::default();
            let tally = rep.per_stepper.get_mut(idx).unwrap_or(&mut scratch);
            match c {
                StepCmd::QueueStep {
                    interval, count, add, ..
                } => {
                    rep.queue_steps += 1;
                    rep.steps += count as u64;
                    tally.queue_steps += 1;
                    tally.steps += count as u64;
                    wire.msg(&[q_id, oid, interval, count as u32, add as i32 as u32]);
                }
                StepCmd::SetDir { dir } => {
                    tally.set_dirs += 1;
                    wire.msg(&[d_id, oid, dir as u32])
                }
                StepCmd::ResetClock { clock } => {
                    tally.resets += 1;
                    wire.msg(&[r_id, oid, clock as u32])
                }
            }
        }
        out.clear();
    };
    for line in GcodeReader::new(src) {
        if opts.max_lines.is_some_and(|m| rep.lines as usize >= m) {
            break;
        }
        let line = line.map_err(|e| e.to_string())?;
        rep.lines += 1;
        // Heaters and fans do not affect planning; unknown commands are skipped and counted
        // (`unknown_commands: warn`, the default), or errors.
        if let Applied::Unsupported(_) = p.apply(&line).map_err(|e| e.to_string())? {
            rep.skipped_unknown += 1;
        }
        p.generate(&mut out);
        if !out.is_empty() {
            count(&mut out, &mut rep);
        }
    }
    p.finish(&mut out);
    count(&mut out, &mut rep);
    wire.flush();
    let st = p.stats();
    rep.moves = st.moves;
    rep.print_time_s = st.print_time_end;
    rep.wire_bytes = wire.bytes;
    rep.wall_s = started.elapsed().as_secs_f64();
    rep.peak_rss_bytes = peak_rss_bytes();
    Ok(rep)
}

/// The process's peak resident set (`VmHWM` from /proc/self/status), 0 when unavailable.
pub fn peak_rss_bytes() -> u64 {
    let Ok(s) = std::fs::read_to_string("/proc/self/status") else {
        return 0;
    };
    s.lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        .map_or(0, |kb| kb * 1024)
}

#[cfg(test)]
mod tests {
    use super::*;

    const CFG: &str = "[mcu]\nserial: /dev/null\n[printer]\nkinematics: cartesian\nmax_velocity: 300\n\
        max_accel: 3000\n[stepper_x]\nstep_pin: PA0\ndir_pin: PA1\nmicrosteps: 16\nrotation_distance: 40\n\
        endstop_pin: PA2\nposition_endstop: 0\nposition_max: 200\n[stepper_y]\nstep_pin: PA3\ndir_pin: PA4\n\
        microsteps: 16\nrotation_distance: 40\nendstop_pin: PA5\nposition_endstop: 0\nposition_max: 200\n\
        [stepper_z]\nstep_pin: PA6\ndir_pin: PA7\nmicrosteps: 16\nrotation_distance: 8\nendstop_pin: PB0\n\
        position_endstop: 0\nposition_max: 200\n";

    #[test]
    fn plans_a_square_in_both_modes() {
        let cfg = sysconfig::parse_str(CFG, Path::new("t.cfg")).unwrap();
        let g = "G28\nG1 X10 Y10 F6000\nG1 X50\nG1 Y50\nG1 X10\nG1 Y10\n";
        let mut reports = Vec::new();
        for threads in [0, 2] {
            let opts = PlanOptions {
                threads,
                ..PlanOptions::default()
            };
            reports.push(plan_reader(g.as_bytes(), &cfg, &opts).unwrap());
        }
        let r = &reports[0];
        assert_eq!(r.steps, 2 * 800 + 4 * 3200);
        assert_eq!(r.moves, 5);
        assert!(r.queue_steps > 0 && r.wire_bytes > r.queue_steps * 5);
        assert_eq!(reports[1].queue_steps, r.queue_steps);
        assert_eq!(reports[1].wire_bytes, r.wire_bytes);
    }

    /// Plans a few accelerating moves on [`CFG`] on the caller's thread with `opts` as given.
    fn plan_accelerations(opts: PlanOptions) -> PlanReport {
        let cfg = sysconfig::parse_str(CFG, Path::new("t.cfg")).unwrap();
        let g = "G28\nG1 X10 Y10 F6000\nG1 X150 Y40 F18000\nG1 X20 Y160\nG1 X10 Y10 F3000\n";
        let opts = PlanOptions { threads: 0, ..opts };
        plan_reader(g.as_bytes(), &cfg, &opts).unwrap()
    }

    #[test]
    fn every_tuning_takes_the_searchs_steps_in_about_its_commands() {
        let plan = |tuning| {
            plan_accelerations(PlanOptions {
                tuning,
                ..PlanOptions::default()
            })
        };
        let search = plan(SearchTuning::SEARCH);
        let formula = SearchTuning {
            curve_commands: true,
            ..SearchTuning::default()
        };
        for tuning in [SearchTuning::default(), formula] {
            let r = plan(tuning);
            assert_eq!(r.steps, search.steps);
            // Klipper takes about 4 % more than the search on the benchy.
            assert!(
                r.queue_steps * 100 <= search.queue_steps * 105,
                "{tuning:?}: {} vs {}",
                r.queue_steps,
                search.queue_steps
            );
        }
    }

    #[test]
    fn the_lookahead_changes_commands_not_steps() {
        let plan = |lookahead| {
            plan_accelerations(PlanOptions {
                lookahead,
                ..PlanOptions::default()
            })
        };
        let (default, greedy, one) = (plan(None), plan(Some(0)), plan(Some(1)));
        assert_eq!((greedy.steps, one.steps), (default.steps, default.steps));
        // The default is lookahead 1; without it the commands differ on these accelerations.
        assert_eq!(one.queue_steps, default.queue_steps);
        assert_ne!(greedy.queue_steps, default.queue_steps);
    }

    #[test]
    fn unknown_commands_are_errors_or_counted_skips() {
        let g = "G28\nM73 P5\nG1 X10 F6000\nM73 P50\n";
        let strict = format!("{CFG}[gcode]\nunknown_commands: error\n");
        let cfg = sysconfig::parse_str(&strict, Path::new("t.cfg")).unwrap();
        let e = plan_reader(g.as_bytes(), &cfg, &PlanOptions::default()).unwrap_err();
        assert!(e.contains("line 2") && e.contains("M73"), "{e}");
        let cfg = sysconfig::parse_str(CFG, Path::new("t.cfg")).unwrap();
        let r = plan_reader(g.as_bytes(), &cfg, &PlanOptions::default()).unwrap();
        assert_eq!((r.moves, r.skipped_unknown), (1, 2));
        assert!(r.to_string().ends_with(", 2 unknown commands skipped"), "{r}");
    }

    #[test]
    fn arc_resolution_and_retraction_come_from_the_config() {
        let plan = |extra: &str, g: &str| {
            let text = format!("{}\n{extra}\n", sysconfig::printer::SIMULATED_PRINTER_CFG);
            let cfg = sysconfig::parse_str(&text, Path::new("t.cfg")).unwrap();
            plan_reader(g.as_bytes(), &cfg, &PlanOptions::default()).unwrap()
        };
        // A full circle of radius 10 (62.8 mm): 62 chords of the default 1 mm, 125 of 0.5 mm.
        let arc = "G28\nG1 X50 Y50 F6000\nG2 X50 Y50 I10 J0\n";
        assert_eq!(plan("", arc).moves, 1 + 62);
        assert_eq!(plan("[gcode_arcs]\nresolution: 0.5", arc).moves, 1 + 125);
        // G10/G11: no retraction by default (length 0); 2 mm each way with the section.
        let retract = "G28\nG1 X10 F6000\nG10\nG11\n";
        let plain = plan("", retract);
        let with = plan("[firmware_retraction]\nretract_length: 2", retract);
        assert_eq!((plain.moves, with.moves), (1, 3));
        let e_steps_per_mm: f64 = 3200.0 / 33.5;
        assert_eq!(
            with.steps - plain.steps,
            (2.0 * 2.0 * e_steps_per_mm).round() as u64
        );
    }

    #[test]
    fn wire_counter_packs_blocks() {
        let mut w = WireCounter::default();
        for _ in 0..20 {
            w.msg(&[1, 2, 3]); // 3 bytes each: 19 fit in 59
        }
        w.flush();
        assert_eq!(w.bytes, (57 + 5) + (3 + 5));
    }

    #[test]
    fn plans_on_a_delta() {
        let cfg = "[mcu]\nserial: /dev/null\n[printer]\nkinematics: delta\nmax_velocity: 300\nmax_accel: 3000\n\
            delta_radius: 140\n[stepper_a]\nstep_pin: PA0\ndir_pin: PA1\nmicrosteps: 16\nrotation_distance: 40\n\
            endstop_pin: PA2\nposition_endstop: 250\narm_length: 270\n[stepper_b]\nstep_pin: PA3\ndir_pin: PA4\n\
            microsteps: 16\nrotation_distance: 40\nendstop_pin: PA5\nposition_endstop: 250\n[stepper_c]\n\
            step_pin: PA6\ndir_pin: PA7\nmicrosteps: 16\nrotation_distance: 40\nendstop_pin: PB0\n\
            position_endstop: 250\n";
        let cfg = sysconfig::parse_str(cfg, Path::new("delta.cfg")).unwrap();
        let g = "G28\nG1 Z10 F6000\nG1 X50 Y20\nG1 X-50\nG1 X0 Y0 Z250\n";
        let a = plan_reader(
            g.as_bytes(),
            &cfg,
            &PlanOptions {
                threads: 0,
                ..PlanOptions::default()
            },
        )
        .unwrap();
        let b = plan_reader(g.as_bytes(), &cfg, &PlanOptions::default()).unwrap();
        assert_eq!(a.moves, 4);
        assert!(a.steps > 3 * 2 * 240 * 80, "{a}");
        assert_eq!(a.steps, b.steps);
        let far = "G28\nG1 X139 Y0 Z10\n";
        assert!(plan_reader(far.as_bytes(), &cfg, &PlanOptions::default())
            .is_err_and(|e| e.contains("Move out of range")));
    }
}
