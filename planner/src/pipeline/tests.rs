//! End-to-end tests: G-code text → merged step commands, replayed by the checker.

use super::*;
use crate::checker::Checker;
use crate::compress::SearchTuning;
use crate::gcode::GcodeReader;
use crate::kinematics::Kinematics;
use crate::pressure_advance::PressureAdvance;
use proptest::prelude::*;

mod line_fit;

const FREQ: f64 = 50e6;

pub(crate) fn benchy_config() -> PipelineConfig {
    PipelineConfig {
        toolhead: ToolheadConfig {
            max_velocity: 500.0,
            max_accel: 3000.0,
            minimum_cruise_ratio: 0.5,
            square_corner_velocity: 5.0,
            max_z_velocity: 25.0,
            max_z_accel: 30.0,
            max_extrude_only_velocity: 52.0,
            max_extrude_only_accel: 312.0,
            max_extrude_only_distance: 500.0,
            axis_limits: [(0.0, 200.0), (0.0, 200.0), (0.0, 200.0)],
        },
        steppers: vec![
            StepperSpec {
                name: "stepper_x".into(),
                axis: 0,
                step_dist: 1.0 / 80.0,
                extruder: None,
            },
            StepperSpec {
                name: "stepper_y".into(),
                axis: 1,
                step_dist: 1.0 / 80.0,
                extruder: None,
            },
            StepperSpec {
                name: "stepper_z".into(),
                axis: 2,
                step_dist: 1.0 / 400.0,
                extruder: None,
            },
            StepperSpec {
                name: "extruder".into(),
                axis: 3,
                step_dist: 33.5 / 3200.0,
                extruder: None,
            },
        ],
        clock_freq: FREQ,
        max_error_s: 25e-6,
        home_position: [0.0, 0.0, 0.5],
    }
}

/// What a run produced: per-stepper commands, the checkers' verdicts, the merged order.
struct Run {
    pipeline: Pipeline,
    per_stepper: Vec<Vec<StepCmd>>,
    keys: Vec<u64>,
}

/// Runs G-code text through a pipeline, checking every stepper incrementally.
fn run_gcode(text: &str) -> Run {
    run_gcode_with(text, PipelineOptions::default())
}

/// [`run_gcode`] with a kinematics / threading choice.
fn run_gcode_with(text: &str, opts: PipelineOptions) -> Run {
    run_cfg(text, benchy_config(), opts)
}

/// [`run_gcode`] with a configuration and options.
fn run_cfg(text: &str, cfg: PipelineConfig, opts: PipelineOptions) -> Run {
    run_cfg_fit(text, cfg, opts, true)
}

/// [`run_cfg`] with the per-command design (`line_fit`, the default: cruise lines' and curves'
/// commands from their formulas) or all commands from the per-step search.
fn run_cfg_fit(text: &str, cfg: PipelineConfig, opts: PipelineOptions, line_fit: bool) -> Run {
    let tuning = if line_fit {
        SearchTuning::default()
    } else {
        SearchTuning::SEARCH
    };
    run_cfg_modes(text, cfg, opts, line_fit, tuning)
}

/// [`run_cfg_fit`], also choosing how the commands off the lines are found.
fn run_cfg_modes(
    text: &str,
    cfg: PipelineConfig,
    opts: PipelineOptions,
    line_fit: bool,
    tuning: SearchTuning,
) -> Run {
    let n = cfg.steppers.len();
    let mut p = Pipeline::with_options(cfg, 0.25, opts).unwrap();
    p.set_line_fit(line_fit);
    p.set_tuning(tuning);
    p.set_record_ideal(true);
    let mut checkers: Vec<Checker> = (0..n).map(|_| Checker::new(p.max_error_ticks())).collect();
    let mut per_stepper = vec![Vec::new(); n];
    let mut merged = Vec::new();
    let mut out = Vec::new();
    let mut last_planned = 0.0;
    let mut feed = |p: &mut Pipeline, out: &mut Vec<(usize, StepCmd)>, checkers: &mut Vec<Checker>| {
        for (i, c) in checkers.iter_mut().enumerate() {
            c.push_ideal(p.take_ideal(i));
        }
        for &(i, cmd) in out.iter() {
            if let Err(e) = checkers[i].check_cmd(&cmd) {
                panic!("stepper {i}: {e}");
            }
            per_stepper[i].push(cmd);
            merged.push((i, cmd));
        }
        out.clear();
    };
    for line in GcodeReader::new(text.as_bytes()) {
        let line = line.unwrap();
        p.apply(&line).unwrap();
        p.generate(&mut out);
        feed(&mut p, &mut out, &mut checkers);
        assert!(p.planned_until() >= last_planned);
        last_planned = p.planned_until();
    }
    p.finish(&mut out);
    feed(&mut p, &mut out, &mut checkers);
    for (i, c) in checkers.iter().enumerate() {
        let stats = c.finish().unwrap_or_else(|e| panic!("stepper {i}: {e}"));
        assert_eq!(stats.position, p.stepper_positions()[i]);
    }
    // Sort keys of the merged stream.
    let mut keys = vec![0; merged.len()];
    let mut next_key: Vec<Option<u64>> = vec![None; n];
    for (j, &(i, cmd)) in merged.iter().enumerate().rev() {
        if let StepCmd::QueueStep { first_clock, .. } = cmd {
            next_key[i] = Some(first_clock);
        }
        keys[j] = next_key[i].expect("reset/dir must precede a queue_step");
    }
    Run {
        pipeline: p,
        per_stepper,
        keys,
    }
}

/// round(b / step_dist) − round(a / step_dist), rounding half up like step generation.
fn steps_between(a: f64, b: f64, step_dist: f64) -> i64 {
    let n = |x: f64| (x * (1.0 / step_dist) + 0.5).floor() as i64;
    n(b) - n(a)
}

#[test]
fn square_with_extrusion() {
    let g = "G28\nG1 Z0.3 F600\nM83\nG1 X10 Y10 F6000\nG1 X50 E2 F1800\nG1 Y50 E2\nG1 X10 E2\nG1 Y10 E2\n\
             G1 E-1 F2400\nG4 P200\nG1 X100 Y100 F9000\n";
    let r = run_gcode(g);
    assert!(
        r.keys.windows(2).all(|w| w[0] <= w[1]),
        "merged output must be time-ordered"
    );
    let pos = r.pipeline.stepper_positions();
    assert_eq!(
        pos,
        vec![
            8000,
            8000,
            steps_between(0.5, 0.3, 0.0025),
            steps_between(0.0, 7.0, 33.5 / 3200.0)
        ]
    );
    assert_eq!(r.pipeline.position(), [100.0, 100.0, 0.3, 7.0]);
    let stats = r.pipeline.stats();
    assert_eq!(stats.moves, 8);
    assert_eq!(
        stats.steps.iter().sum::<u64>(),
        r.per_stepper
            .iter()
            .flatten()
            .map(|c| match c {
                StepCmd::QueueStep { count, .. } => *count as u64,
                _ => 0,
            })
            .sum::<u64>()
    );
    assert!(r.pipeline.planned_until() >= stats.print_time_end - 1e-3);
}

#[test]
fn idle_flush_releases_everything() {
    let mut p = Pipeline::new(benchy_config(), 1.0).unwrap();
    p.set_homed([true; 3]);
    let mut out = Vec::new();
    for (i, g) in ["G1 X10 Y5 F3000", "G1 X20 Y5"].iter().enumerate() {
        let cmd = crate::gcode::parse_line(i + 1, g.as_bytes()).unwrap().unwrap();
        p.apply(&GcodeLine { line_no: i + 1, cmd }).unwrap();
        p.generate(&mut out);
    }
    assert!(out.is_empty(), "moves are still in the lookahead");
    p.flush_lookahead();
    p.generate(&mut out);
    assert_eq!(p.stepper_positions(), vec![1600, 400, 0, 0]);
    assert!((p.planned_until() - p.stats().print_time_end).abs() < 1e-3);
    let n = out.len();
    p.generate(&mut out);
    assert_eq!(out.len(), n, "nothing new");
}

#[test]
fn rejects_bad_configs() {
    let mut c = benchy_config();
    c.clock_freq = 0.0;
    assert!(Pipeline::new(c, 0.0).is_err());
    let mut c = benchy_config();
    c.steppers[0].axis = 7;
    assert!(Pipeline::new(c, 0.0).is_err());
    let mut c = benchy_config();
    c.max_error_s = 0.0;
    assert!(Pipeline::new(c, 0.0).is_err());
    let mut c = benchy_config();
    c.toolhead.max_accel = f64::NAN;
    assert!(Pipeline::new(c, 0.0).is_err());
}

fn arb_program() -> impl Strategy<Value = (String, [f64; 4])> {
    let mv = (
        0.0f64..200.0,
        0.0f64..200.0,
        0.3f64..20.0,
        -1.0f64..3.0,
        5.0f64..300.0,
        0u8..13,
    );
    proptest::collection::vec(mv, 1..60).prop_map(|moves| {
        let mut g = String::from("G28\nM83\n");
        let mut pos = [0.0, 0.0, 0.5, 0.0];
        let mut e_total = 0.0;
        for (x, y, z, e, f, kind) in moves {
            // Round like slicers do (3 decimals for XYZ, 5 for E).
            let (x, y, z, e) = (
                (x * 1e3f64).round() / 1e3,
                (y * 1e3f64).round() / 1e3,
                (z * 1e3f64).round() / 1e3,
                (e * 1e5f64).round() / 1e5,
            );
            match kind {
                0 => g.push_str(&format!("G1 E{e} F{}\n", f * 10.0)),
                1 => g.push_str("G92 E0\n"),
                2 => g.push_str("G4 P50\n"),
                3 => g.push_str(&format!("G1 Z{z} F{}\n", f * 60.0)),
                12 => g.push_str(&format!("SET_PRESSURE_ADVANCE ADVANCE={:.4}\n", (e + 1.0) * 0.03)),
                4..=7 => {
                    // Short moves near the current position.
                    let nx = (pos[0] + (x - 100.0) / 50.0).clamp(0.0, 200.0);
                    let ny = (pos[1] + (y - 100.0) / 50.0).clamp(0.0, 200.0);
                    let (nx, ny) = ((nx * 1e3f64).round() / 1e3, (ny * 1e3f64).round() / 1e3);
                    g.push_str(&format!("G1 X{nx} Y{ny} E{} F{}\n", e.abs() / 10.0, f * 60.0));
                    pos[0] = nx;
                    pos[1] = ny;
                    e_total += e.abs() / 10.0;
                    continue;
                }
                _ => {
                    g.push_str(&format!("G1 X{x} Y{y} F{}\n", f * 60.0));
                    pos[0] = x;
                    pos[1] = y;
                    continue;
                }
            }
            if kind == 0 {
                e_total += e;
            }
            if kind == 3 {
                pos[2] = z;
            }
        }
        pos[3] = e_total;
        (g, pos)
    })
}

/// A print with extruding moves on both sides of `mid` (G-code lines inserted between them).
fn pa_print(mid: &str) -> String {
    let mut g = String::from("G28\nG1 Z0.3 F600\nM83\nG1 X10 Y10 F6000\n");
    for i in 0..6 {
        g.push_str(&format!("G1 X{} Y{} E0.8 F3000\n", 20 + 7 * i, 10 + 3 * (i % 2)));
    }
    g.push_str(mid);
    for i in 0..6 {
        g.push_str(&format!("G1 X{} Y{} E0.8 F3000\n", 60 - 7 * i, 20 + 3 * (i % 2)));
    }
    g.push_str("G1 E-1 F2400\nG1 X100 Y100 F9000\n");
    g
}

fn extruder_cmds(mid: &str, threads: usize, pa: Option<PressureAdvance>) -> Vec<StepCmd> {
    let opts = PipelineOptions {
        threads,
        pressure_advance: pa,
        ..PipelineOptions::default()
    };
    let r = run_gcode_with(&pa_print(mid), opts);
    assert!(r.keys.windows(2).all(|w| w[0] <= w[1]));
    let e = r.pipeline.stepper_positions()[3];
    assert_eq!(e, steps_between(0.0, 12.0 * 0.8 - 1.0, 33.5 / 3200.0));
    r.per_stepper[3].clone()
}

#[test]
fn set_pressure_advance_applies_during_the_print() {
    let pa = |advance| PressureAdvance {
        advance,
        smooth_time: 0.04,
    };
    for threads in [0, 2] {
        let plain = extruder_cmds("", threads, None);
        // Set before the first move: the same as configuring it.
        let configured = extruder_cmds("", threads, Some(pa(0.08)));
        let early = pa_print("").replacen("M83\n", "M83\nSET_PRESSURE_ADVANCE ADVANCE=0.08\n", 1);
        let r = run_gcode_with(
            &early,
            PipelineOptions {
                threads,
                ..PipelineOptions::default()
            },
        );
        assert_eq!(r.per_stepper[3], configured);
        assert_ne!(configured, plain);
        // Set half-way: the first half is extruded as without pressure advance (the change
        // blends in over smooth_time from the next move on), the rest differs.
        let mid = extruder_cmds("SET_PRESSURE_ADVANCE ADVANCE=0.08\n", threads, None);
        let same = mid.iter().zip(&plain).take_while(|(a, b)| a == b).count();
        assert!(
            same > 4 && same < plain.len().min(mid.len()),
            "{same} of {}",
            plain.len()
        );
        // Changing a configured advance, and turning it off, also works (checked by the run).
        let changed = extruder_cmds(
            "SET_PRESSURE_ADVANCE ADVANCE=0.02\nSET_PRESSURE_ADVANCE ADVANCE=0\n",
            threads,
            Some(pa(0.08)),
        );
        assert_ne!(changed, configured);
    }
}

#[test]
fn set_pressure_advance_checks_its_numbers() {
    let mut p = Pipeline::new(benchy_config(), 0.25).unwrap();
    let line = |g: &str| GcodeLine {
        line_no: 1,
        cmd: crate::gcode::parse_line(1, g.as_bytes()).unwrap().unwrap(),
    };
    assert!(p.apply(&line("SET_PRESSURE_ADVANCE ADVANCE=12")).is_err());
    assert!(p.apply(&line("SET_PRESSURE_ADVANCE SMOOTH_TIME=0.3")).is_err());
    assert!(p.apply(&line("SET_PRESSURE_ADVANCE SMOOTH_TIME=0")).is_err());
    assert!(matches!(
        p.apply(&line("SET_PRESSURE_ADVANCE ADVANCE=0.05")),
        Ok(Applied::PressureAdvance { advance, .. }) if advance == 0.05
    ));
    assert!(matches!(
        p.apply(&line("SET_PRESSURE_ADVANCE SMOOTH_TIME=0.1")),
        Ok(Applied::PressureAdvance { advance, smooth_time }) if advance == 0.05 && smooth_time == 0.1
    ));
}

#[test]
fn set_pressure_advance_changes_the_smooth_time_during_the_print() {
    let pa = |advance, smooth_time| PressureAdvance { advance, smooth_time };
    for threads in [0, 2] {
        // extruder_cmds checks the order, the extruder's final position and (run_gcode_with)
        // every stepper with the checker.
        let configured = extruder_cmds("", threads, Some(pa(0.08, 0.04)));
        let wide = extruder_cmds("", threads, Some(pa(0.08, 0.1)));
        assert_ne!(configured, wide);
        // Half-way: the first half as configured, then the new window.
        let mid = extruder_cmds(
            "SET_PRESSURE_ADVANCE SMOOTH_TIME=0.1\n",
            threads,
            Some(pa(0.08, 0.04)),
        );
        let same = mid.iter().zip(&configured).take_while(|(a, b)| a == b).count();
        assert!(
            same > 4 && same < configured.len().min(mid.len()),
            "{same} of {}",
            configured.len()
        );
        assert_ne!(mid, wide);
        // Both at once, with pressure advance off before; and back to the configured window.
        extruder_cmds(
            "SET_PRESSURE_ADVANCE ADVANCE=0.05 SMOOTH_TIME=0.02\n",
            threads,
            None,
        );
        extruder_cmds(
            "SET_PRESSURE_ADVANCE SMOOTH_TIME=0.15\nG1 X30 E0.5\nG1 E-0.5\nSET_PRESSURE_ADVANCE SMOOTH_TIME=0.04\n",
            threads,
            Some(pa(0.08, 0.04)),
        );
    }
}

#[test]
fn threaded_matches_inline_order_and_counts() {
    let g = "G28\nG1 Z0.3 F600\nM83\nG1 X10 Y10 F6000\nG1 X50 E2 F1800\nG1 Y50 E2\nG1 X10 E2\nG1 Y10 E2\n\
             G1 E-1 F2400\nG4 P200\nG1 X100 Y100 F9000\nG1 X0 Y20\n";
    for threads in [1, 2, 3] {
        let opts = PipelineOptions {
            threads,
            batch_moves: 2,
            ..PipelineOptions::default()
        };
        let r = run_gcode_with(g, opts);
        assert!(r.keys.windows(2).all(|w| w[0] <= w[1]), "threads {threads}");
        assert_eq!(
            r.pipeline.stepper_positions(),
            vec![0, 1600, -80, steps_between(0.0, 7.0, 33.5 / 3200.0)]
        );
        assert!(r.pipeline.worker_error().is_none());
    }
}

/// Rails (stepper positions in mm) of a toolhead position.
fn rails(kin: Kinematics, p: [f64; 4]) -> [f64; 4] {
    let r = kin.inverse([p[0], p[1], p[2]]);
    [r[0], r[1], r[2], p[3]]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    #[test]
    fn random_programs_step_exactly_and_check(
        (program, end) in arb_program(),
        kin in prop_oneof![
            Just(Kinematics::Cartesian),
            Just(Kinematics::CoreXY),
            Just(Kinematics::CoreXZ)
        ],
        threads in 0usize..3,
        batch_moves in 1usize..20,
        pa in proptest::option::of((0.0f64..0.2, 0.005f64..0.1)),
    ) {
        let pressure_advance = pa.map(|(advance, smooth_time)| PressureAdvance { advance, smooth_time });
        let opts = PipelineOptions {
            kinematics: kin,
            threads,
            batch_moves,
            pressure_advance,
            ..PipelineOptions::default()
        };
        let r = run_gcode_with(&program, opts);
        prop_assert!(r.keys.windows(2).all(|w| w[0] <= w[1]));
        let cfg = benchy_config();
        let start = rails(kin, [0.0, 0.0, 0.5, 0.0]);
        let th = r.pipeline.position();
        for i in 0..4 {
            prop_assert!((th[i] - end[i]).abs() < 1e-6, "axis {i} at {}, expected {}", th[i], end[i]);
        }
        let rail = rails(kin, th);
        let pos = r.pipeline.stepper_positions();
        for (i, s) in cfg.steppers.iter().enumerate() {
            prop_assert_eq!(pos[i], steps_between(start[s.axis], rail[s.axis], s.step_dist), "{}", s.name);
        }
    }
}

/// Each stepper's commands for `text` with the ideal steps not recorded (the print's and the
/// benchmark's path, where a cruise is written as one line of windows: see `StepSink::line`).
fn unrecorded_cmds(text: &str, opts: PipelineOptions) -> Vec<Vec<StepCmd>> {
    let cfg = benchy_config();
    let mut per_stepper = vec![Vec::new(); cfg.steppers.len()];
    let mut p = Pipeline::with_options(cfg, 0.25, opts).unwrap();
    let mut out = Vec::new();
    for line in GcodeReader::new(text.as_bytes()) {
        p.apply(&line.unwrap()).unwrap();
        p.generate(&mut out);
    }
    p.finish(&mut out);
    for (i, cmd) in out {
        per_stepper[i].push(cmd);
    }
    per_stepper
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]

    /// Recording the ideal steps (tests, `--check`) takes every step one at a time; a print
    /// writes cruises in one loop (shaped or not). Both give the same windows, so the same
    /// commands, which the recorded run's checker has proven.
    #[test]
    fn commands_do_not_depend_on_recording_the_ideal_steps(
        (program, _end) in arb_program(),
        kin in prop_oneof![Just(Kinematics::Cartesian), Just(Kinematics::CoreXY)],
        pa in proptest::option::of((0.0f64..0.2, 0.005f64..0.1)),
        shaper in proptest::option::of((0usize..6, 20.0f64..90.0, 20.0f64..90.0)),
    ) {
        let pressure_advance = pa.map(|(advance, smooth_time)| PressureAdvance { advance, smooth_time });
        let input_shaper = shaper.map(|(kind, fx, fy)| shaper_of(kind, fx, fy));
        let opts = PipelineOptions {
            kinematics: kin,
            threads: 0,
            pressure_advance,
            input_shaper,
            ..PipelineOptions::default()
        };
        let recorded = run_gcode_with(&program, opts);
        prop_assert_eq!(recorded.per_stepper, unrecorded_cmds(&program, opts));
    }
}

fn delta_geometry() -> crate::kinematics::DeltaGeometry {
    crate::kinematics::DeltaGeometry {
        radius: 140.0,
        arm_length: [270.0, 270.0, 271.0],
        angles: [210.0, 330.0, 90.0],
    }
}

fn delta_config() -> PipelineConfig {
    let mut c = benchy_config();
    c.toolhead.axis_limits = [(-130.0, 130.0), (-130.0, 130.0), (0.0, 250.0)];
    c.toolhead.max_z_velocity = 200.0;
    c.toolhead.max_z_accel = 3000.0;
    for s in c.steppers.iter_mut().take(3) {
        s.step_dist = 0.0125;
    }
    c.home_position = [0.0, 0.0, 250.0];
    c
}

#[test]
fn delta_refuses_moves_outside_its_radius() {
    let opts = PipelineOptions {
        kinematics: Kinematics::Delta(delta_geometry()),
        ..PipelineOptions::default()
    };
    let mut p = Pipeline::with_options(delta_config(), 0.25, opts).unwrap();
    let lines = ["G28", "G1 X100 Y100 Z10"];
    let mut res = Vec::new();
    for (i, g) in lines.iter().enumerate() {
        let cmd = crate::gcode::parse_line(i + 1, g.as_bytes()).unwrap().unwrap();
        res.push(p.apply(&GcodeLine { line_no: i + 1, cmd }));
    }
    assert_eq!(
        res[1].as_ref().unwrap_err().to_string(),
        "line 2: Move out of range: X=100.000 Y=100.000 Z=10.000 [E=0.000]"
    );
    let mut bad = delta_geometry();
    bad.arm_length[0] = 10.0;
    let opts = PipelineOptions {
        kinematics: Kinematics::Delta(bad),
        ..PipelineOptions::default()
    };
    assert!(Pipeline::with_options(delta_config(), 0.25, opts).is_err());
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 12, ..ProptestConfig::default() })]

    /// Random moves on a delta (iterative solver): every carriage ends exactly at the step
    /// count of its final height and the checker passes.
    #[test]
    fn delta_programs_step_exactly_and_check(
        pts in proptest::collection::vec((-1.0f64..1.0, -1.0f64..1.0, 1.0f64..60.0, 0.0f64..1.0), 1..8),
        threads in 0usize..3,
    ) {
        let kin = Kinematics::Delta(delta_geometry());
        let mut g = String::from("G28\nM83\n");
        let mut end = [0.0, 0.0, 250.0, 0.0];
        for (x, y, z, e) in pts {
            let (x, y) = ((x * 90.0 * 1e3f64).round() / 1e3, (y * 90.0 * 1e3f64).round() / 1e3);
            let z = (z * 1e3f64).round() / 1e3;
            let e = (e * 1e3f64).round() / 1e3;
            g.push_str(&format!("G1 X{x} Y{y} Z{z} E{e} F9000\n"));
            end = [x, y, z, end[3] + e];
        }
        let opts = PipelineOptions { kinematics: kin, threads, ..PipelineOptions::default() };
        let r = run_cfg(&g, delta_config(), opts);
        prop_assert!(r.keys.windows(2).all(|w| w[0] <= w[1]));
        let start = rails(kin, [0.0, 0.0, 250.0, 0.0]);
        let rail = rails(kin, end);
        let pos = r.pipeline.stepper_positions();
        for (i, s) in delta_config().steppers.iter().enumerate() {
            prop_assert_eq!(pos[i], steps_between(start[s.axis], rail[s.axis], s.step_dist), "{}", s.name);
        }
    }
}

/// Every step's clock of one stepper's commands (replaying resets and queue_steps).
fn step_clocks(cmds: &[StepCmd]) -> Vec<u64> {
    let mut out = Vec::new();
    let mut clock = 0u64;
    for c in cmds {
        match *c {
            StepCmd::ResetClock { clock: c } => clock = c,
            StepCmd::QueueStep {
                interval, count, add, ..
            } => {
                let mut iv = interval as i64;
                for _ in 0..count {
                    clock = (clock as i64 + iv) as u64;
                    out.push(clock);
                    iv += add as i64;
                }
            }
            StepCmd::SetDir { .. } => {}
        }
    }
    out
}

/// Runs `g` with the steppers' clock maps `maps` (empty: all on the print clock), changing the
/// maps of the steppers in `drift` by `+ppm` per line; returns the commands per stepper and
/// the merged keys.
fn run_clocks(
    g: &str,
    maps: &[ClockMap],
    drift: Option<(&[usize], f64)>,
) -> (Vec<Vec<StepCmd>>, Vec<u64>, Pipeline) {
    let cfg = benchy_config();
    let n = cfg.steppers.len();
    let mut p = Pipeline::with_clocks(cfg, 0.25, PipelineOptions::default(), maps).unwrap();
    let mut per = vec![Vec::new(); n];
    let mut keys = Vec::new();
    let mut out = Vec::new();
    let mut current = maps.to_vec();
    let mut take = |out: &mut Vec<(usize, StepCmd)>| {
        for &(i, c) in out.iter() {
            if let StepCmd::QueueStep { first_clock, .. } = c {
                // Keys in print ticks: the first step's clock carried back by its map.
                let key = match maps.get(i) {
                    Some(m) => (m.print_time(first_clock as f64) * FREQ) as u64,
                    None => first_clock,
                };
                keys.push(key);
            }
            per[i].push(c);
        }
        out.clear();
    };
    for line in GcodeReader::new(g.as_bytes()) {
        p.apply(&line.unwrap()).unwrap();
        p.generate(&mut out);
        take(&mut out);
        if let Some((steppers, ppm)) = drift {
            for &i in steppers {
                current[i].freq *= 1.0 + ppm * 1e-6;
                p.set_clock_map(i, current[i]).unwrap();
            }
        }
    }
    p.finish(&mut out);
    take(&mut out);
    (per, keys, p)
}

#[test]
fn clock_maps_put_each_steppers_steps_in_its_mcus_clock() {
    let g = "G28\nG1 Z0.3 F600\nM83\nG1 X10 Y10 F6000\nG1 X50 Z2 E2 F1800\nG1 Y50 E2\nG1 X10 Z0.5 E2\n\
             G1 Y10 E2\nG1 E-1 F2400\nG4 P200\nG1 X100 Y100 Z3 F9000\n";
    let (base, _, p0) = run_clocks(g, &[], None);
    // Z on a 16 MHz board whose clock read 7e9 at print time 0 and runs 30 ppm fast; the
    // extruder on one 5 s ahead of the main clock at 50 MHz.
    let z = ClockMap {
        offset: 7e9,
        freq: 16e6 * (1.0 + 30e-6),
    };
    let e = ClockMap {
        offset: 5.0 * FREQ,
        freq: FREQ,
    };
    let maps = [ClockMap::identity(FREQ), ClockMap::identity(FREQ), z, e];
    let (per, keys, p) = run_clocks(g, &maps, None);
    assert_eq!(p.stepper_positions(), p0.stepper_positions());
    assert!(
        keys.windows(2).all(|w| w[0] <= w[1]),
        "merged output in print-time order"
    );
    // X, Y: the very same commands; Z and E: every step at its print time through the map,
    // within the compression's error (25 µs) plus rounding.
    assert_eq!(per[0], base[0]);
    assert_eq!(per[1], base[1]);
    for (i, map) in [(2, z), (3, e)] {
        let want: Vec<f64> = step_clocks(&base[i])
            .iter()
            .map(|&c| map.clock(c as f64 / FREQ))
            .collect();
        let got = step_clocks(&per[i]);
        assert_eq!(got.len(), want.len(), "stepper {i}");
        let tol = 2.0 * 25e-6 * map.freq + 2.0;
        for (g, w) in got.iter().zip(&want) {
            assert!(
                (*g as f64 - w).abs() <= tol,
                "stepper {i}: step at {g}, expected {w:.0}"
            );
        }
    }
}

#[test]
fn a_drifting_clock_map_keeps_steps_in_order_and_counts_exact() {
    let g = "G28\nM83\nG1 X10 Y10 F6000\nG1 X50 Z2 E2 F1800\nG1 Y50 E2\nG1 X10 Z0.5 E2\nG1 Y10 E2\n\
             G1 X100 Y100 Z3 F9000\n";
    let z = ClockMap {
        offset: 1e9,
        freq: 16e6,
    };
    let maps = [ClockMap::identity(FREQ), ClockMap::identity(FREQ), z, z];
    let (_, _, p0) = run_clocks(g, &maps, None);
    // 50 ppm more per line: far more drift than a crystal shows, to make it visible.
    let (per, _, p) = run_clocks(g, &maps, Some((&[2, 3], 50.0)));
    assert_eq!(p.stepper_positions(), p0.stepper_positions());
    for (i, cmds) in per.iter().enumerate() {
        let clocks = step_clocks(cmds);
        assert!(
            clocks.windows(2).all(|w| w[0] <= w[1]),
            "stepper {i}: steps out of order"
        );
    }
    let mut p = p;
    assert!(p
        .set_clock_map(
            9,
            ClockMap {
                offset: 0.0,
                freq: 1e6
            }
        )
        .is_err());
    assert!(p
        .set_clock_map(
            2,
            ClockMap {
                offset: f64::NAN,
                freq: 1e6
            }
        )
        .is_err());
    let bad = [ClockMap::identity(FREQ); 2];
    assert!(Pipeline::with_clocks(benchy_config(), 0.0, PipelineOptions::default(), &bad).is_err());
}

#[test]
fn lanes_are_placed_by_weight() {
    let lanes = |kin: Kinematics, axes: &[usize]| -> Vec<LaneState> {
        axes.iter()
            .map(|&a| {
                LaneState::new(
                    kin.stepper(a, 0.01).unwrap(),
                    StepCompressor::new(0.01, FREQ, 1250),
                    None,
                )
            })
            .collect()
    };
    let idx = |g: &[(usize, LaneState)]| g.iter().map(|(i, _)| *i).collect::<Vec<_>>();
    let placed = |kin: Kinematics, axes: &[usize], threads: usize| {
        let (groups, local) = place(lanes(kin, axes), threads);
        (groups.iter().map(|g| idx(g)).collect::<Vec<_>>(), idx(&local))
    };
    // Cartesian (or corexy) X, Y, Z, E: with one or two threads, one worker takes X, Z and E
    // (weight 1.25) and the caller Y (0.5 + 1); with three, X and Y on a worker each and Z and
    // E on the caller (0.75); with four, Z and E on the third worker.
    for kin in [Kinematics::Cartesian, Kinematics::CoreXY] {
        for threads in [1, 2] {
            assert_eq!(
                placed(kin, &[0, 1, 2, 3], threads),
                (vec![vec![0, 2, 3]], vec![1])
            );
        }
        assert_eq!(
            placed(kin, &[0, 1, 2, 3], 3),
            (vec![vec![0], vec![1]], vec![2, 3])
        );
        assert_eq!(
            placed(kin, &[0, 1, 2, 3], 4),
            (vec![vec![0], vec![1], vec![2, 3]], vec![])
        );
    }
    // Light lanes alone: both on the worker (0.25, below the caller's 0.5).
    assert_eq!(
        placed(Kinematics::Cartesian, &[2, 3], 2),
        (vec![vec![0, 1]], vec![])
    );
    // A single lane goes to the worker.
    assert_eq!(placed(Kinematics::Cartesian, &[3], 4), (vec![vec![0]], vec![]));
}

/// `[input_shaper]` with `kind` on both axes at `fx` / `fy` Hz.
fn shaper_of(kind: usize, fx: f64, fy: f64) -> crate::shaper::InputShaper {
    use crate::shaper::{AxisShaper, InputShaper, ShaperType};
    let shaper_type = ShaperType::ALL[kind % ShaperType::ALL.len()].1;
    let axis = |freq| AxisShaper {
        shaper_type,
        freq,
        damping_ratio: 0.1,
    };
    InputShaper {
        x: axis(fx),
        y: axis(fy),
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    /// Shaped random programs on every linear kinematics, with a SET_INPUT_SHAPER somewhere:
    /// the checker passes on every stepper, commands are time-ordered, and every stepper ends
    /// exactly at the commanded position.
    #[test]
    fn shaped_programs_step_exactly_and_check(
        (program, end) in arb_program(),
        kin in prop_oneof![
            Just(Kinematics::Cartesian),
            Just(Kinematics::CoreXY),
            Just(Kinematics::CoreXZ)
        ],
        threads in 0usize..3,
        batch_moves in 1usize..20,
        kind in 0usize..6,
        fx in prop_oneof![Just(0.0), 20.0f64..90.0],
        fy in 20.0f64..90.0,
        change in proptest::option::of((0usize..60, 0usize..6, prop_oneof![Just(0.0), 30.0f64..90.0])),
        pa in proptest::option::of((0.0f64..0.2, 0.005f64..0.1)),
    ) {
        let pressure_advance = pa.map(|(advance, smooth_time)| PressureAdvance { advance, smooth_time });
        let opts = PipelineOptions {
            kinematics: kin,
            threads,
            batch_moves,
            pressure_advance,
            input_shaper: Some(shaper_of(kind, fx, fy)),
            ..PipelineOptions::default()
        };
        let mut lines: Vec<String> = program.lines().map(str::to_string).collect();
        if let Some((at, kind, freq)) = change {
            let name = crate::shaper::ShaperType::ALL[kind].0;
            let at = at.min(lines.len());
            lines.insert(at, format!("SET_INPUT_SHAPER SHAPER_TYPE={name} SHAPER_FREQ_X={freq:.2} SHAPER_FREQ_Y=45"));
        }
        let program = lines.join("\n") + "\n";
        let r = run_gcode_with(&program, opts);
        prop_assert!(r.keys.windows(2).all(|w| w[0] <= w[1]));
        let cfg = benchy_config();
        let start = rails(kin, [0.0, 0.0, 0.5, 0.0]);
        let th = r.pipeline.position();
        for i in 0..4 {
            prop_assert!((th[i] - end[i]).abs() < 1e-6, "axis {i} at {}, expected {}", th[i], end[i]);
        }
        let rail = rails(kin, th);
        let pos = r.pipeline.stepper_positions();
        for (i, s) in cfg.steppers.iter().enumerate() {
            prop_assert_eq!(pos[i], steps_between(start[s.axis], rail[s.axis], s.step_dist), "{}", s.name);
        }
    }
}

#[test]
fn shaping_moves_steps_and_keeps_the_square() {
    let g = "G28\nG1 Z0.3 F600\nM83\nG1 X10 Y10 F6000\nG1 X50 E2 F1800\nG1 Y50 E2\nG1 X10 E2\nG1 Y10 E2\n\
             G1 E-1 F2400\nG4 P200\nG1 X100 Y100 F9000\n";
    let plain = run_gcode(g);
    let opts = PipelineOptions {
        input_shaper: Some(shaper_of(1, 50.0, 40.0)),
        ..PipelineOptions::default()
    };
    let shaped = run_gcode_with(g, opts);
    assert!(shaped.keys.windows(2).all(|w| w[0] <= w[1]));
    assert_eq!(
        shaped.pipeline.stepper_positions(),
        plain.pipeline.stepper_positions()
    );
    // X and Y step at other times; Z and the extruder are not shaped.
    for i in 0..2 {
        assert_ne!(
            step_clocks(&shaped.per_stepper[i]),
            step_clocks(&plain.per_stepper[i]),
            "{i}"
        );
    }
    for i in 2..4 {
        let (a, b) = (
            step_clocks(&shaped.per_stepper[i]),
            step_clocks(&plain.per_stepper[i]),
        );
        assert_eq!(a.len(), b.len());
    }
    // Frequency 0 on both axes is no shaping: the plain commands exactly.
    let off = run_gcode_with(
        g,
        PipelineOptions {
            input_shaper: Some(shaper_of(1, 0.0, 0.0)),
            ..PipelineOptions::default()
        },
    );
    assert_eq!(off.per_stepper, plain.per_stepper);
}

#[test]
fn set_input_shaper_needs_the_section_and_checks_its_numbers() {
    let line = |text: &str| {
        let cmd = crate::gcode::parse_line(3, text.as_bytes()).unwrap().unwrap();
        GcodeLine { line_no: 3, cmd }
    };
    let mut p = Pipeline::new(benchy_config(), 0.25).unwrap();
    let e = p.apply(&line("SET_INPUT_SHAPER SHAPER_FREQ_X=40")).unwrap_err();
    assert_eq!(e.to_string(), "line 3: Unknown command:\"SET_INPUT_SHAPER\"");
    let opts = PipelineOptions {
        input_shaper: Some(shaper_of(1, 0.0, 0.0)),
        ..PipelineOptions::default()
    };
    let mut p = Pipeline::with_options(benchy_config(), 0.25, opts).unwrap();
    for (text, want) in [
        ("SET_INPUT_SHAPER SHAPER_TYPE=foo", "Unsupported shaper type: foo"),
        (
            "SET_INPUT_SHAPER SHAPER_FREQ_Y=-3",
            "SHAPER_FREQ_Y=-3 must be ≥ 0",
        ),
        (
            "SET_INPUT_SHAPER SHAPER_TYPE_X=EI DAMPING_RATIO_X=0.5",
            "axis X: damping ratio 0.5",
        ),
        ("SET_INPUT_SHAPER SHAPER_FREQ_X=1", "raise the frequency"),
    ] {
        let e = p.apply(&line(text)).unwrap_err().to_string();
        assert!(e.contains(want), "{text}: {e}");
    }
    assert_eq!(p.gcode_state().input_shaper(), Some(shaper_of(1, 0.0, 0.0)));
    let r = p
        .apply(&line(
            "SET_INPUT_SHAPER SHAPER_TYPE_X=2HUMP_EI SHAPER_FREQ_X=55.5",
        ))
        .unwrap();
    assert_eq!(
        r,
        Applied::Report(
            "shaper_type_x:2hump_ei shaper_freq_x:55.500 damping_ratio_x:0.100000\n\
             shaper_type_y:mzv shaper_freq_y:0.000 damping_ratio_y:0.100000"
                .into()
        )
    );
    // Delta: refused in the configuration and at run time.
    let delta = |s| PipelineOptions {
        kinematics: Kinematics::Delta(delta_geometry()),
        input_shaper: Some(s),
        ..PipelineOptions::default()
    };
    assert!(Pipeline::with_options(delta_config(), 0.25, delta(shaper_of(1, 50.0, 50.0))).is_err());
    let mut p = Pipeline::with_options(delta_config(), 0.25, delta(shaper_of(1, 0.0, 0.0))).unwrap();
    let e = p.apply(&line("SET_INPUT_SHAPER SHAPER_FREQ_X=50")).unwrap_err();
    assert!(e.to_string().contains("delta"), "{e}");
    assert_eq!(p.gcode_state().input_shaper(), Some(shaper_of(1, 0.0, 0.0)));
}
