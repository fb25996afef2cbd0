//! Several extruders and forced moves through the whole planner: the steps each extruder
//! stepper gets (the inactive one's none, the active one's the E distance), what syncing and
//! a new rotation distance change, and FORCE_MOVE / STEPPER_BUZZ step counts.

#[allow(dead_code)]
mod common;

use planner::gcode::{parse_line, GcodeLine};
use planner::machine::Applied;
use planner::pipeline::{ExtruderLink, Pipeline, PipelineOptions, StepperSpec};
use planner::pressure_advance::PressureAdvance;
use planner::stepgen::StepCmd;

const E_STEP: f64 = 33.5 / 3200.0;

/// The benchy cartesian printer with `extruder`, `extruder1` and `[extruder_stepper e2]`
/// (following nothing at the start); `advance` for every extruder stepper.
fn printer(advance: f64, threads: usize) -> Pipeline {
    let mut cfg = common::benchy_cartesian();
    let link = |queue| {
        Some(ExtruderLink {
            queue,
            pressure_advance: PressureAdvance {
                advance,
                smooth_time: 0.04,
            },
            rotation_distance: 33.5,
        })
    };
    cfg.steppers[3].extruder = link(Some(0));
    for (name, queue) in [("extruder1", Some(1)), ("e2", None)] {
        cfg.steppers.push(StepperSpec {
            name: name.into(),
            axis: 3,
            step_dist: E_STEP,
            extruder: link(queue),
        });
    }
    let opts = PipelineOptions {
        extruders: 2,
        threads,
        ..PipelineOptions::default()
    };
    let mut p = Pipeline::with_options(cfg, 0.5, opts).unwrap_or_else(|e| panic!("{e}"));
    p.set_homed([true; 3]);
    p
}

/// Plans `gcode`; (net steps per stepper, total steps per stepper, the reports).
fn run(p: &mut Pipeline, gcode: &str) -> (Vec<i64>, Vec<u64>, Vec<String>) {
    let mut out = Vec::new();
    let mut reports = Vec::new();
    for (i, text) in gcode.lines().enumerate() {
        let Some(cmd) = parse_line(i + 1, text.as_bytes()).unwrap_or_else(|e| panic!("{e}")) else {
            continue;
        };
        match p.apply(&GcodeLine { line_no: i + 1, cmd }) {
            Ok(Applied::Report(t)) => reports.push(t.as_str().to_string()),
            Ok(_) => {}
            Err(e) => panic!("{text}: {e}"),
        }
        p.generate(&mut out);
    }
    p.finish(&mut out);
    (net(&out, p.stats().steps.len()), p.stats().steps, reports)
}

/// Net signed steps per stepper from the commands.
fn net(cmds: &[(usize, StepCmd)], n: usize) -> Vec<i64> {
    let mut dir = vec![true; n];
    let mut pos = vec![0i64; n];
    for &(i, c) in cmds {
        match c {
            StepCmd::SetDir { dir: d } => dir[i] = d,
            StepCmd::QueueStep { count, .. } => pos[i] += if dir[i] { count as i64 } else { -(count as i64) },
            StepCmd::ResetClock { .. } => {}
        }
    }
    pos
}

/// Steps for `mm` of filament.
fn steps(mm: f64) -> i64 {
    (mm / E_STEP).round() as i64
}

/// Steps from E `from` to E `to` (the step grid is anchored at 0 of the coordinate followed).
fn span(from: f64, to: f64) -> i64 {
    let index = |x: f64| (x / E_STEP + 0.5).floor() as i64;
    index(to) - index(from)
}

#[test]
fn only_the_active_extruders_stepper_moves() {
    for (advance, threads) in [(0.0, 0), (0.05, 0), (0.0, 2)] {
        let mut p = printer(advance, threads);
        let (pos, _, reports) = run(
            &mut p,
            "G1 X10 Y10 F6000\nG1 X30 E4 F1200\n\
             ACTIVATE_EXTRUDER EXTRUDER=extruder1\n\
             G1 X50 E2\nG1 X60 E3\nG1 E-1 F1800\n\
             ACTIVATE_EXTRUDER EXTRUDER=extruder1\n\
             ACTIVATE_EXTRUDER EXTRUDER=extruder\n\
             G92 E0\nG1 X70 E1.5 F1200\n",
        );
        // extruder: 4 mm, then 1.5 mm after it is active again (its E resumes at 4).
        assert_eq!(pos[3], steps(5.5), "advance {advance} threads {threads}: {pos:?}");
        // Absolute E on extruder1: 0 → 2 → 3 → −1 (G1 E-1 is absolute): net −1 mm.
        assert_eq!(
            pos[4],
            steps(-1.0),
            "advance {advance} threads {threads}: {pos:?}"
        );
        assert_eq!(pos[5], 0, "the unsynced extruder_stepper moved: {pos:?}");
        assert_eq!(
            reports,
            [
                "Activating extruder extruder1",
                "Extruder extruder1 already active",
                "Activating extruder extruder"
            ]
        );
    }
}

#[test]
fn a_synced_stepper_follows_its_extruder() {
    let mut p = printer(0.0, 0);
    let (pos, _, reports) = run(
        &mut p,
        "M83\nG1 X10 E2 F1200\n\
         SYNC_EXTRUDER_MOTION EXTRUDER=e2 MOTION_QUEUE=extruder\n\
         G1 X20 E3\n\
         ACTIVATE_EXTRUDER EXTRUDER=extruder1\n\
         G1 X30 E4\n\
         SYNC_EXTRUDER_MOTION EXTRUDER=e2 MOTION_QUEUE=extruder1\n\
         G1 X40 E5\n\
         SYNC_EXTRUDER_MOTION EXTRUDER=e2 MOTION_QUEUE=\n\
         G1 X50 E6\n",
    );
    assert_eq!(pos[3], steps(5.0), "{pos:?}");
    assert_eq!(pos[4], steps(15.0), "{pos:?}");
    // e2: 3 mm following extruder (E 2 → 5), then 5 mm following extruder1 (E 4 → 9: its
    // step grid re-anchored on extruder1's coordinate, as Klipper's set_position), then nothing.
    assert_eq!(pos[5], span(2.0, 5.0) + span(4.0, 9.0), "{pos:?}");
    assert!(reports.contains(&"Extruder 'e2' now syncing with 'extruder1'".to_string()));
    assert!(reports.contains(&"Extruder 'e2' now syncing with ''".to_string()));
}

#[test]
fn a_new_rotation_distance_scales_and_a_negative_one_inverts() {
    let mut p = printer(0.0, 0);
    let (pos, _, reports) = run(
        &mut p,
        "M83\nG1 X10 E2 F1200\n\
         SET_EXTRUDER_ROTATION_DISTANCE EXTRUDER=extruder DISTANCE=67\n\
         G1 X20 E4\n\
         SET_EXTRUDER_ROTATION_DISTANCE EXTRUDER=extruder DISTANCE=-33.5\n\
         G1 X30 E1\n",
    );
    // 2 mm at 33.5, 4 mm at 67 (half the steps), then 1 mm backwards.
    assert_eq!(pos[3], steps(2.0) + steps(2.0) - steps(1.0), "{pos:?}");
    assert_eq!(
        reports[1],
        "Extruder 'extruder' rotation distance set to -33.500000"
    );
}

#[test]
fn per_extruder_pressure_advance_and_heater_commands() {
    let mut p = printer(0.0, 0);
    let (pos, _, reports) = run(
        &mut p,
        "M83\nSET_PRESSURE_ADVANCE EXTRUDER=extruder1 ADVANCE=0.05\n\
         ACTIVATE_EXTRUDER EXTRUDER=extruder1\nG1 X10 E2 F1200\nG1 X20 E2\n",
    );
    assert_eq!(pos[4], steps(4.0), "{pos:?}");
    assert_eq!(pos[3], 0, "{pos:?}");
    assert_eq!(reports, ["Activating extruder extruder1"]);
    let mut p = printer(0.0, 0);
    let line = |t: &str| GcodeLine {
        line_no: 1,
        cmd: parse_line(1, t.as_bytes()).unwrap().unwrap(),
    };
    let heater = |a: Applied| match a {
        Applied::Heater { heater, .. } => heater.name(),
        other => panic!("{other:?}"),
    };
    assert_eq!(heater(p.apply(&line("M104 S200 T1")).unwrap()), "extruder1");
    assert_eq!(heater(p.apply(&line("M104 S200")).unwrap()), "extruder");
    p.apply(&line("ACTIVATE_EXTRUDER EXTRUDER=extruder1")).unwrap();
    assert_eq!(heater(p.apply(&line("M109 S200")).unwrap()), "extruder1");
    assert!(p.apply(&line("M104 S200 T2")).is_err());
    assert!(p.apply(&line("ACTIVATE_EXTRUDER EXTRUDER=extruder2")).is_err());
}

#[test]
fn force_move_and_buzz_step_the_named_stepper_alone() {
    let mut p = printer(0.0, 0);
    let mut out = Vec::new();
    p.force_move("stepper_y", 10.0, 20.0, 0.0, &mut out)
        .unwrap_or_else(|e| panic!("{e}"));
    p.force_move("extruder1", -5.0, 10.0, 500.0, &mut out)
        .unwrap_or_else(|e| panic!("{e}"));
    let pos = net(&out, 6);
    assert_eq!(pos, vec![0, 800, 0, 0, steps(-5.0), 0]);
    assert!(p.force_move("stepper_q", 1.0, 1.0, 0.0, &mut out).is_err());
    assert!(p.force_move("stepper_x", 1.0, 0.0, 0.0, &mut out).is_err());
    // The toolhead's next move starts after the forced ones and moves from where it was.
    let mut all = out.clone();
    let mut q = Vec::new();
    p.stepper_buzz("stepper_x", &mut q)
        .unwrap_or_else(|e| panic!("{e}"));
    let buzz = net(&q, 6);
    assert_eq!(buzz[0], 0, "{buzz:?}");
    let moved: u64 = q
        .iter()
        .map(|&(i, c)| match c {
            StepCmd::QueueStep { count, .. } if i == 0 => u64::from(count),
            _ => 0,
        })
        .sum();
    assert_eq!(moved, 20 * 80, "ten cycles of 1 mm out and back at 80 steps/mm");
    all.extend(q);
    let (pos, _, _) = run(&mut p, "G1 Y20 F6000\n");
    // Y: the commanded 0 → 20 mm on top of the forced 10 mm.
    assert_eq!(pos[1], 1600, "{pos:?}");
    // Commands stay in clock order across the forced moves.
    let mut last = 0;
    for &(_, c) in &all {
        if let StepCmd::QueueStep { first_clock, .. } = c {
            assert!(first_clock >= last, "out of order");
            last = first_clock;
        }
    }
}
