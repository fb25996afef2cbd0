use super::halt::*;
use super::*;
use crate::hardware::StepperOut;
use planner::kinematics::{Kinematics, StepperKin};
use planner::toolhead::Move;
use sysconfig::printer::PinRef;

fn pin(mcu: &str, name: &str) -> PinRef {
    PinRef {
        mcu: mcu.to_string(),
        pin: name.to_string(),
        invert: false,
        pullup: false,
        pulldown: false,
    }
}

fn machine(z_mcus: &[&str], endstop_mcu: &str) -> Machine {
    let cfg = sysconfig::printer::builtin_simulated().unwrap();
    let mut m = Machine::from_config(&cfg).unwrap();
    m.steppers.retain(|s| s.axis != 2);
    for (i, mcu) in z_mcus.iter().enumerate() {
        m.steppers.push(StepperOut {
            name: format!("stepper_z{i}"),
            mcu: mcu.to_string(),
            oid: i as u8,
            axis: 2,
            step_pin: pin(mcu, "PC0"),
            dir_pin: pin(mcu, "PC1"),
            enable_pin: None,
            step_pulse_duration: crate::hardware::DEFAULT_STEP_PULSE_DURATION,
            step_dist: 0.0025,
            extruder: None,
        });
    }
    for e in m.endstops.iter_mut().filter(|e| e.axis == 2) {
        e.pin = pin(endstop_mcu, "PA3");
    }
    m
}

#[test]
fn axis_steppers_split_over_mcus_need_the_endstop_on_one_of_them() {
    assert!(check_config(&machine(&["mcu"], "probe_mcu")).is_ok());
    assert!(check_config(&machine(&["mcu", "mcu"], "probe_mcu")).is_ok());
    assert!(check_config(&machine(&["mcu", "z2"], "z2")).is_ok());
    let err = check_config(&machine(&["mcu", "z2"], "probe_mcu")).unwrap_err();
    assert!(matches!(&err, HomingError::Wiring(w) if w.axis == 'z'), "{err:?}");
    let err = err.to_string();
    assert!(
        err.contains("[stepper_z]") && err.contains("'probe_mcu'"),
        "{err}"
    );
}

#[test]
fn a_probe_on_yet_another_mcu_is_refused_too() {
    let mut m = machine(&["mcu", "z2"], "z2");
    let mut endstop = m.endstops[2].clone();
    endstop.stepper = "probe".into();
    endstop.pin = pin("probe_mcu", "PA4");
    endstop.probe = true;
    let cfg = sysconfig::parse_str(
        "[mcu]\nserial: x\n[mcu probe_mcu]\nserial: y\n[printer]\nkinematics: none\nmax_velocity: 1\n\
         max_accel: 1\n[probe]\npin: probe_mcu:PA4\nz_offset: 1\n",
        std::path::Path::new("printer.cfg"),
    )
    .unwrap();
    m.probe = Some(crate::hardware::ProbeOut {
        endstop,
        z_virtual_endstop: false,
        z_position: 0.0,
        cfg: cfg.probe.unwrap(),
    });
    let err = check_config(&m).unwrap_err().to_string();
    assert!(
        err.starts_with("[probe] pin 'probe_mcu:PA4': the steppers of axis z are on MCUs 'mcu', 'z2'"),
        "{err}"
    );
    if let Some(p) = m.probe.as_mut() {
        p.endstop.pin = pin("z2", "PA4");
    }
    assert!(check_config(&m).is_ok());
}

#[test]
fn step_index_rounds_half_steps_up() {
    assert_eq!(step_index(0.0, 0.01), 0);
    assert_eq!(step_index(0.0149, 0.01), 1);
    assert_eq!(step_index(-0.0051, 0.01), -1);
    assert_eq!(step_index(-0.0049, 0.01), 0);
}

fn toolhead() -> planner::toolhead::Toolhead {
    planner::toolhead::Toolhead::new(
        planner::toolhead::ToolheadConfig {
            max_velocity: 100.0,
            max_accel: 1000.0,
            minimum_cruise_ratio: 0.5,
            square_corner_velocity: 5.0,
            max_z_velocity: 10.0,
            max_z_accel: 100.0,
            max_extrude_only_velocity: 50.0,
            max_extrude_only_accel: 1000.0,
            max_extrude_only_distance: 50.0,
            axis_limits: [(-500.0, 500.0); 3],
        },
        2.0,
    )
}

/// The one move from `from` to `to` at `speed` (1000 mm/s² ramps).
fn one_move(from: [f64; 4], to: [f64; 4], speed: f64) -> Move {
    let mut th = toolhead();
    th.set_position(from);
    th.move_to(to, speed).unwrap();
    th.flush();
    let mut out = Vec::new();
    th.take_moves(&mut out);
    out[0]
}

fn homing_move() -> Move {
    // 100 mm → 0 at 10 mm/s, instant acceleration is not allowed: 1000 mm/s² ramps.
    one_move([100.0, 0.0, 0.0, 0.0], [0.0; 4], 10.0)
}

/// Stepper `kin`'s position (mm) in `mv` at print time `t`.
fn stepper_at(kin: &StepperKin, mv: &Move, t: f64) -> f64 {
    kin.position_at(mv, (t - mv.print_time).clamp(0.0, mv.duration()))
}

#[test]
fn move_position_and_time_are_inverse() {
    let mv = homing_move();
    let x = StepperKin::axis(0, 0.0125);
    for at in [99.0, 50.0, 0.5] {
        let t = time_at_stepper_pos(&mv, &x, at);
        assert!((stepper_at(&x, &mv, t) - at).abs() < 1e-9, "{at}");
    }
    assert_eq!(stepper_at(&x, &mv, 0.0), 100.0);
    assert_eq!(stepper_at(&x, &mv, 1e9), 0.0);
    // Cruise at 10 mm/s: 1 mm takes 0.1 s.
    let dt = time_at_stepper_pos(&mv, &x, 40.0) - time_at_stepper_pos(&mv, &x, 41.0);
    assert!((dt - 0.1).abs() < 1e-9);
    // Corexy B = x − y moving with X: the same times; a stepper that does not move: the end.
    let b = Kinematics::CoreXY.stepper(1, 0.0125).unwrap();
    let mv = one_move([100.0, 20.0, 0.0, 0.0], [0.0, 20.0, 0.0, 0.0], 10.0);
    assert!((time_at_stepper_pos(&mv, &b, 60.0) - time_at_stepper_pos(&mv, &x, 80.0)).abs() < 1e-12);
    let z = StepperKin::axis(2, 0.0025);
    assert_eq!(time_at_stepper_pos(&mv, &z, 1.0), mv.end_time());
}

/// A virtual homing pass: the endstop triggers when the commanded `axis` coordinate crosses
/// `trigger`; each stepper of `rails` halts at the step index it had `latency` s later. Returns
/// the trigger time, the halt time and the group.
fn virtual_pass(
    kin: &Kinematics,
    mv: &Move,
    rails: &[usize],
    axis: usize,
    trigger: f64,
    latency: f64,
) -> (f64, f64, Vec<GroupStepper>) {
    let x = StepperKin::axis(axis, 1.0);
    let t_trig = time_at_stepper_pos(mv, &x, trigger);
    let t_halt = t_trig + latency;
    let group = rails
        .iter()
        .map(|&rail| {
            let k = kin.stepper(rail, 0.0125).unwrap();
            let n = |mm: f64| step_index(mm, k.step_dist);
            GroupStepper {
                rail,
                kin: k,
                net_steps: n(stepper_at(&k, mv, t_halt)) - n(k.position(&mv.start_pos)),
            }
        })
        .collect();
    (t_trig, t_halt, group)
}

#[test]
fn corexy_x_homes_with_both_steppers_and_keeps_y() {
    // X from a pretended 300 toward the endstop at 0 at 10 mm/s, Y at 37.3 (not homed).
    let kin = Kinematics::CoreXY;
    let mv = one_move([300.0, 37.3, 5.0, 0.0], [0.0, 37.3, 5.0, 0.0], 10.0);
    for (trigger, latency) in [(150.004, 0.0005), (100.0, 0.0), (42.00625, 0.012)] {
        let (t_trig, t_halt, group) = virtual_pass(&kin, &mv, &[0, 1], 0, trigger, latency);
        assert!(group.iter().all(|g| g.net_steps < 0), "{group:?}");
        let halt = halt_position(&kin, &mv, &group, t_trig).unwrap();
        assert_eq!(halt.moved, [true, true, false]);
        // Halted and triggered are forward kinematics of step indices: a = x + y, b = x − y.
        let [a_halt, b_halt] = [0, 1].map(|i| {
            let n_start = step_index(group[i].kin.position(&mv.start_pos), 0.0125);
            (n_start + group[i].net_steps) as f64 * 0.0125
        });
        assert!((halt.halted[0] - 0.5 * (a_halt + b_halt)).abs() < 1e-9);
        assert!((halt.halted[1] - 0.5 * (a_halt - b_halt)).abs() < 1e-9);
        // The overshoot: how far X went on from the trigger, within a step of each stepper.
        let went_on = stepper_at(&StepperKin::axis(0, 1.0), &mv, t_trig)
            - stepper_at(&StepperKin::axis(0, 1.0), &mv, t_halt);
        let overshoot = halt.triggered[0] - halt.halted[0];
        assert!(
            (overshoot - went_on).abs() <= 0.0125 + 1e-9,
            "{overshoot} vs {went_on}"
        );
        let p = halt.homed([300.0, 37.3, 5.0, 0.0], 0, 0.0);
        assert!((p[0] + overshoot).abs() < 1e-9, "{p:?}");
        // Y comes out unchanged up to a step's rounding; Z and E untouched.
        assert!((p[1] - 37.3).abs() <= 0.0125 + 1e-9, "{p:?}");
        assert_eq!((p[2], p[3]), (5.0, 0.0));
    }
}

#[test]
fn corexy_y_and_corexz_z_probe() {
    // Corexy Y homing toward its max at 200: A up, B down.
    let kin = Kinematics::CoreXY;
    let mv = one_move([12.5, -100.0, 0.0, 0.0], [12.5, 200.0, 0.0, 0.0], 10.0);
    let (t_trig, _, group) = virtual_pass(&kin, &mv, &[0, 1], 1, 199.99, 0.002);
    assert!(group[0].net_steps > 0 && group[1].net_steps < 0);
    let halt = halt_position(&kin, &mv, &group, t_trig).unwrap();
    let p = halt.homed([12.5, -100.0, 0.0, 0.0], 1, 200.0);
    // 2 ms at 10 mm/s past the trigger: 0.02 mm, within a step.
    assert!((p[1] - 200.02).abs() <= 0.0125 + 1e-9, "{p:?}");
    assert!((p[0] - 12.5).abs() <= 0.0125 + 1e-9, "{p:?}");
    // Corexz probing down to z = −2: A = x + z, B = x − z; the bed at 0.3.
    let kin = Kinematics::CoreXZ;
    let mv = one_move([50.0, 20.0, 10.0, 0.0], [50.0, 20.0, -2.0, 0.0], 5.0);
    let (t_trig, t_halt, group) = virtual_pass(&kin, &mv, &[0, 2], 2, 0.3, 0.001);
    let halt = halt_position(&kin, &mv, &group, t_trig).unwrap();
    assert_eq!(halt.moved, [true, false, true]);
    assert!((halt.triggered[2] - 0.3).abs() <= 0.0125 + 1e-9, "{halt:?}");
    let z_halt = stepper_at(&StepperKin::axis(2, 1.0), &mv, t_halt);
    let p = halt.halted_at([50.0, 20.0, 10.0, 0.0]);
    assert!((p[2] - z_halt).abs() <= 0.0125 + 1e-9, "{p:?}");
    assert!((p[0] - 50.0).abs() <= 0.0125 + 1e-9 && p[1] == 20.0, "{p:?}");
}

#[test]
fn cartesian_halt_is_the_step_index_formula() {
    // The module doc's formula: position_endstop + (n_halt − n_trig) · step_dist.
    let kin = Kinematics::Cartesian;
    let mv = one_move([-30.0, 1.0, 2.0, 0.0], [0.0, 1.0, 2.0, 0.0], 10.0);
    let (t_trig, _, group) = virtual_pass(&kin, &mv, &[0], 0, -0.00314, 0.0007);
    let halt = halt_position(&kin, &mv, &group, t_trig).unwrap();
    assert_eq!(halt.moved, [true, false, false]);
    let x = StepperKin::axis(0, 0.0125);
    let n_halt = step_index(-30.0, 0.0125) + group[0].net_steps;
    let n_trig = step_index(stepper_at(&x, &mv, t_trig), 0.0125);
    let p = halt.homed([-30.0, 1.0, 2.0, 0.0], 0, 0.0);
    assert!((p[0] - (n_halt - n_trig) as f64 * 0.0125).abs() < 1e-12, "{p:?}");
    assert_eq!(&p[1..], &[1.0, 2.0, 0.0]);
    // A delta's steppers are not linear: no position from this computation.
    let delta = Kinematics::Delta(planner::kinematics::DeltaGeometry {
        radius: 100.0,
        arm_length: [250.0; 3],
        angles: [210.0, 330.0, 90.0],
    });
    let tower = GroupStepper {
        rail: 0,
        kin: delta.stepper(0, 0.0125).unwrap(),
        net_steps: 0,
    };
    assert_eq!(halt_position(&delta, &mv, &[tower], t_trig), None);
}

#[test]
fn report_names_axis_overshoot_and_position() {
    let r = HomingReport {
        axes: vec![AxisReport {
            axis: 2,
            mcus: vec!["probe_mcu".into(), "mcu".into()],
            passes: vec![PassReport {
                speed: 10.0,
                trigger_mcu: "probe_mcu".into(),
                trigger_clock: 1,
                trigger_print_time: 1.0,
                overshoot_mm: 0.0125,
                trigger_position: 0.0,
                steps: -4000,
                last_step_after_s: -0.0000421,
                next_step_after_s: 0.00065,
                trigger_received_at: 2.0,
                relay_written_at: Some(2.0001),
            }],
            position: 0.0125,
        }],
    };
    let s = r.to_string();
    assert!(
        s.starts_with("homing z: mcus probe_mcu+mcu; pass 1 at 10 mm/s"),
        "{s}"
    );
    assert!(
        s.contains("overshoot 0.0125 mm")
            && s.contains("last step 42 us before the trigger, first cancelled 650 us after the trigger")
            && s.ends_with("position 0.012500\n"),
        "{s}"
    );
}

#[test]
fn only_delta_homing_is_refused() {
    use planner::kinematics::DeltaGeometry;
    for kin in [Kinematics::Cartesian, Kinematics::CoreXY, Kinematics::CoreXZ] {
        assert_eq!(unsupported_kinematics(&kin), None, "{kin:?}");
    }
    let delta = Kinematics::Delta(DeltaGeometry {
        radius: 100.0,
        arm_length: [250.0; 3],
        angles: [210.0, 330.0, 90.0],
    });
    assert_eq!(unsupported_kinematics(&delta), Some("delta"));
}

#[test]
fn coupled_axes_group_every_stepper_that_moves_them() {
    let mut m = machine(&["mcu"], "mcu");
    let names = |m: &Machine, axis: usize| -> Vec<String> {
        axis_steppers(m, axis)
            .iter()
            .map(|&i| m.steppers[i].name.clone())
            .collect()
    };
    assert_eq!(names(&m, 0), ["stepper_x"]);
    assert_eq!(names(&m, 2), ["stepper_z0"]);
    m.options.kinematics = Kinematics::CoreXY;
    assert_eq!(names(&m, 0), ["stepper_x", "stepper_y"]);
    assert_eq!(names(&m, 1), ["stepper_x", "stepper_y"]);
    assert_eq!(names(&m, 2), ["stepper_z0"]);
    m.options.kinematics = Kinematics::CoreXZ;
    assert_eq!(names(&m, 0), ["stepper_x", "stepper_z0"]);
    assert_eq!(names(&m, 1), ["stepper_y"]);
    assert_eq!(names(&m, 2), ["stepper_x", "stepper_z0"]);
}
