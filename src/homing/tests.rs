use super::*;
use crate::machine::StepperOut;
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
            step_pulse_duration: crate::machine::DEFAULT_STEP_PULSE_DURATION,
            step_dist: 0.0025,
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
    m.probe = Some(crate::machine::ProbeOut {
        endstop,
        z_virtual_endstop: false,
        z_position: 0.0,
        cfg: cfg.probe.unwrap(),
    });
    let err = check_config(&m).unwrap_err();
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

fn homing_move() -> Move {
    // 100 mm → 0 at 10 mm/s, instant acceleration is not allowed: 1000 mm/s² ramps.
    let mut th = planner::toolhead::Toolhead::new(
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
            axis_limits: [(0.0, 200.0); 3],
        },
        2.0,
    );
    th.set_position([100.0, 0.0, 0.0, 0.0]);
    th.move_to([0.0, 0.0, 0.0, 0.0], 10.0).unwrap();
    th.flush();
    let mut out = Vec::new();
    th.take_moves(&mut out);
    out[0]
}

#[test]
fn move_position_and_time_are_inverse() {
    let mv = homing_move();
    for x in [99.0, 50.0, 0.5] {
        let t = time_at_axis_pos(&mv, 0, x);
        assert!((axis_pos_at(&mv, 0, t) - x).abs() < 1e-9, "{x}");
    }
    assert_eq!(axis_pos_at(&mv, 0, 0.0), 100.0);
    assert_eq!(axis_pos_at(&mv, 0, 1e9), 0.0);
    // Cruise at 10 mm/s: 1 mm takes 0.1 s.
    let dt = time_at_axis_pos(&mv, 0, 40.0) - time_at_axis_pos(&mv, 0, 41.0);
    assert!((dt - 0.1).abs() < 1e-9);
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
                last_step_after_s: 0.0004,
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
            && s.contains("stop 400..650 us")
            && s.ends_with("position 0.012500\n"),
        "{s}"
    );
}

#[test]
fn axes_moved_by_shared_steppers_are_named() {
    use planner::kinematics::{DeltaGeometry, Kinematics};
    for axis in 0..3 {
        assert_eq!(coupled_kinematics(&Kinematics::Cartesian, axis), None);
    }
    let xy: Vec<_> = (0..3)
        .map(|a| coupled_kinematics(&Kinematics::CoreXY, a))
        .collect();
    assert_eq!(xy, [Some("corexy"), Some("corexy"), None]);
    let xz: Vec<_> = (0..3)
        .map(|a| coupled_kinematics(&Kinematics::CoreXZ, a))
        .collect();
    assert_eq!(xz, [Some("corexz"), None, Some("corexz")]);
    let delta = Kinematics::Delta(DeltaGeometry {
        radius: 100.0,
        arm_length: [250.0; 3],
        angles: [210.0, 330.0, 90.0],
    });
    assert_eq!(coupled_kinematics(&delta, 2), Some("delta"));
}
