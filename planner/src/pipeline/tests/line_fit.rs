//! Cruise lines' commands from their formula (`compress::line`), and with them the commands
//! from constant-acceleration curves tried from the curve's adds (`compress::curve`), against
//! the per-step search, on random programs through every kinematics, shaped and not: the
//! checker passes on every stepper (`run_cfg_modes` checks each command as it comes), the step
//! counts are the same, and no stepper takes more `queue_step` commands than the per-step
//! search gives it.

use super::*;

/// Per stepper: (queue_step commands, steps).
fn counts(r: &Run) -> Vec<(usize, u64)> {
    r.per_stepper
        .iter()
        .map(|cmds| {
            cmds.iter().fold((0, 0), |(n, steps), c| match *c {
                StepCmd::QueueStep { count, .. } => (n + 1, steps + u64::from(count)),
                _ => (n, steps),
            })
        })
        .collect()
}

/// Runs `program` both ways and compares them stepper by stepper.
fn compare(program: &str, cfg: PipelineConfig, opts: PipelineOptions) -> Result<(), TestCaseError> {
    let per_step = run_cfg_fit(program, cfg.clone(), opts, false);
    for (what, tuning) in [
        ("line", SearchTuning::SEARCH),
        ("line and curve", SearchTuning::default()),
    ] {
        let fit = run_cfg_modes(program, cfg.clone(), opts, true, tuning);
        prop_assert!(fit.keys.windows(2).all(|w| w[0] <= w[1]));
        prop_assert_eq!(
            fit.pipeline.stepper_positions(),
            per_step.pipeline.stepper_positions()
        );
        for (i, (l, p)) in counts(&fit).into_iter().zip(counts(&per_step)).enumerate() {
            let name = &cfg.steppers[i].name;
            prop_assert_eq!(l.1, p.1, "{} steps", name);
            prop_assert!(
                l.0 <= p.0,
                "{}: {} queue_step with {} commands, {} per step",
                name,
                l.0,
                what,
                p.0
            );
        }
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    #[test]
    fn line_commands_check_and_take_no_more_commands(
        (program, _end) in arb_program(),
        kin in prop_oneof![
            Just(Kinematics::Cartesian),
            Just(Kinematics::CoreXY),
            Just(Kinematics::CoreXZ)
        ],
        threads in 0usize..3,
        pa in proptest::option::of((0.0f64..0.2, 0.005f64..0.1)),
        shaper in proptest::option::of((0usize..6, 20.0f64..90.0, 20.0f64..90.0)),
    ) {
        let opts = PipelineOptions {
            kinematics: kin,
            threads,
            pressure_advance: pa.map(|(advance, smooth_time)| PressureAdvance { advance, smooth_time }),
            input_shaper: shaper.map(|(kind, fx, fy)| shaper_of(kind, fx, fy)),
            ..PipelineOptions::default()
        };
        compare(&program, benchy_config(), opts)?;
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 8, ..ProptestConfig::default() })]

    /// On a delta the carriages take the per-step path (not polynomial); the extruder's
    /// cruises still come from their formula.
    #[test]
    fn line_commands_on_a_delta(
        pts in proptest::collection::vec((-1.0f64..1.0, -1.0f64..1.0, 1.0f64..60.0, 0.0f64..20.0), 1..6),
    ) {
        let mut g = String::from("G28\nM83\n");
        for (x, y, z, e) in pts {
            let (x, y) = ((x * 90.0 * 1e3f64).round() / 1e3, (y * 90.0 * 1e3f64).round() / 1e3);
            let (z, e) = ((z * 1e3f64).round() / 1e3, (e * 1e3f64).round() / 1e3);
            g.push_str(&format!("G1 X{x} Y{y} Z{z} E{e} F6000\n"));
        }
        let opts = PipelineOptions { kinematics: Kinematics::Delta(delta_geometry()), ..PipelineOptions::default() };
        compare(&g, delta_config(), opts)?;
    }
}

/// Long straight cruises (the case the formula is for): the same checks, and most steps come
/// in few commands.
#[test]
fn long_cruises_take_few_commands() {
    let g = "G28\nM83\nG1 X150 Y20 E30 F6000\nG1 X20 Y170 E30\nG1 X190 Y190 F12000\nG1 X10 Y10 E40 F3000\n";
    for kin in [Kinematics::Cartesian, Kinematics::CoreXY] {
        let opts = PipelineOptions {
            kinematics: kin,
            threads: 0,
            ..PipelineOptions::default()
        };
        if let Err(e) = compare(g, benchy_config(), opts) {
            panic!("{kin:?}: {e}");
        }
        let r = run_cfg_fit(g, benchy_config(), opts, true);
        let c = counts(&r);
        assert!(c[0].1 > 20_000, "{c:?}");
        assert!(c[0].0 * 50 < c[0].1 as usize, "{c:?}");
    }
}
