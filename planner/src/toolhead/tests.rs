//! Toolhead and lookahead tests: profiles, junction speeds, finality, continuity.

use super::*;
use proptest::prelude::*;

fn cfg() -> ToolheadConfig {
    ToolheadConfig {
        max_velocity: 500.0,
        max_accel: 3000.0,
        minimum_cruise_ratio: 0.5,
        square_corner_velocity: 5.0,
        max_z_velocity: 25.0,
        max_z_accel: 30.0,
        max_extrude_only_velocity: 50.0,
        max_extrude_only_accel: 300.0,
        max_extrude_only_distance: 50.0,
        axis_limits: [(0.0, 200.0), (0.0, 200.0), (0.0, 200.0)],
    }
}

fn run(th: &mut Toolhead, targets: &[([f64; 4], f64)]) -> Vec<Move> {
    for &(p, v) in targets {
        th.move_to(p, v).unwrap();
    }
    th.flush();
    let mut out = Vec::new();
    th.take_moves(&mut out);
    out
}

/// Invariants every finalized sequence must hold.
fn check_sequence(moves: &[Move], cfg: &ToolheadConfig) {
    let tol = |v: f64| 1e-6 * v.max(1.0);
    for (i, m) in moves.iter().enumerate() {
        assert!(
            m.accel_t >= 0.0 && m.cruise_t >= 0.0 && m.decel_t >= 0.0,
            "{i}: {m:?}"
        );
        assert!(m.duration() > 0.0, "{i}: {m:?}");
        assert!(
            m.start_v <= m.cruise_v + tol(m.cruise_v) && m.end_v <= m.cruise_v + tol(m.cruise_v),
            "{i}: {m:?}"
        );
        if m.is_kinematic() {
            assert!(m.cruise_v <= cfg.max_velocity + 1e-9, "{i}: {m:?}");
            assert!(m.accel <= cfg.max_accel + 1e-9);
        }
        // The profile covers exactly the move distance.
        let covered = m.accel_d() + m.cruise_d() + (m.cruise_v + m.end_v) * 0.5 * m.decel_t;
        assert!(
            (covered - m.move_d).abs() < 1e-6 * m.move_d.max(1.0),
            "{i}: {covered} vs {m:?}"
        );
        if m.accel_t > 1e-9 {
            let a = (m.cruise_v - m.start_v) / m.accel_t;
            assert!((a - m.accel).abs() < 1e-6 * m.accel, "{i}: accel {a} vs {m:?}");
        }
        if m.decel_t > 1e-9 {
            let a = (m.cruise_v - m.end_v) / m.decel_t;
            assert!((a - m.accel).abs() < 1e-6 * m.accel, "{i}: decel {a} vs {m:?}");
        }
        if i > 0 {
            let p = &moves[i - 1];
            assert_eq!(p.end_pos, m.start_pos, "{i}: positions must chain exactly");
            assert!((p.end_time() - m.print_time).abs() < 1e-9, "{i}: time gap");
            assert!(
                (p.end_v - m.start_v).abs() < tol(m.start_v),
                "{i}: speed jump {} -> {}",
                p.end_v,
                m.start_v
            );
        } else {
            assert_eq!(m.start_v, 0.0);
        }
    }
    if let Some(last) = moves.last() {
        assert!(last.end_v.abs() < 1e-9);
    }
}

#[test]
fn single_move_trapezoid() {
    let c = cfg();
    let mut th = Toolhead::new(c, 1.0);
    let moves = run(&mut th, &[([100.0, 0.0, 0.0, 0.0], 100.0)]);
    assert_eq!(moves.len(), 1);
    let m = moves[0];
    check_sequence(&moves, &c);
    assert!((m.cruise_v - 100.0).abs() < 1e-9);
    // 0 → 100 mm/s at 3000 mm/s²: 1/30 s and 1.667 mm each way.
    assert!((m.accel_t - 1.0 / 30.0).abs() < 1e-9);
    assert!((m.decel_t - 1.0 / 30.0).abs() < 1e-9);
    assert!((m.print_time - 1.0).abs() < 1e-12);
    assert!((th.print_time() - m.end_time()).abs() < 1e-12);
    assert_eq!(th.position(), [100.0, 0.0, 0.0, 0.0]);
}

#[test]
fn speed_is_capped_by_max_velocity_and_z_limits() {
    let c = cfg();
    let mut th = Toolhead::new(c, 0.0);
    let moves = run(
        &mut th,
        &[
            ([200.0, 0.0, 0.0, 0.0], 1000.0),
            ([200.0, 0.0, 10.0, 0.0], 1000.0),
        ],
    );
    check_sequence(&moves, &c);
    assert!((moves[0].cruise_v - 500.0).abs() < 1e-9);
    assert!(moves[1].cruise_v <= 25.0 + 1e-9);
    assert!(moves[1].accel <= 30.0 + 1e-9);
}

#[test]
fn collinear_segments_do_not_slow_down() {
    let c = cfg();
    let mut th = Toolhead::new(c, 0.0);
    let targets: Vec<_> = (1..=40)
        .map(|i| ([i as f64 * 5.0, 0.0, 0.0, i as f64 * 0.2], 100.0))
        .collect();
    let moves = run(&mut th, &targets);
    check_sequence(&moves, &c);
    // Cruise at 100 mm/s needs 1.67 mm to reach: from the second segment on, every joint
    // before the final deceleration is at full speed.
    for m in &moves[1..moves.len() - 1] {
        assert!((m.start_v - 100.0).abs() < 1e-6, "{m:?}");
        assert!((m.end_v - 100.0).abs() < 1e-6, "{m:?}");
    }
}

#[test]
fn square_corner_respects_square_corner_velocity() {
    let c = cfg();
    let mut th = Toolhead::new(c, 0.0);
    let moves = run(
        &mut th,
        &[([50.0, 0.0, 0.0, 0.0], 100.0), ([50.0, 50.0, 0.0, 0.0], 100.0)],
    );
    check_sequence(&moves, &c);
    assert!((moves[0].end_v - 5.0).abs() < 1e-6, "{:?}", moves[0]);
    assert!((moves[1].start_v - 5.0).abs() < 1e-6);
    // A reversal stops.
    let moves = run(
        &mut th,
        &[([10.0, 50.0, 0.0, 0.0], 100.0), ([40.0, 50.0, 0.0, 0.0], 100.0)],
    );
    check_sequence(&moves, &c);
    assert!(moves[0].end_v.abs() < 1e-9);
}

#[test]
fn extrude_only_moves_stop_and_use_extruder_limits() {
    let c = cfg();
    let mut th = Toolhead::new(c, 0.0);
    let moves = run(
        &mut th,
        &[
            ([10.0, 0.0, 0.0, 0.0], 100.0),
            ([10.0, 0.0, 0.0, -1.0], 100.0),
            ([20.0, 0.0, 0.0, -1.0], 100.0),
        ],
    );
    check_sequence(&moves, &c);
    assert_eq!(moves.len(), 3);
    assert!(!moves[1].is_kinematic());
    assert_eq!(moves[1].axes_r, [0.0, 0.0, 0.0, -1.0]);
    assert!(moves[1].cruise_v <= 50.0 + 1e-9);
    assert!(moves[0].end_v == 0.0 && moves[2].start_v == 0.0);
}

#[test]
fn refuses_bad_moves_and_stays_put() {
    let c = cfg();
    let mut th = Toolhead::new(c, 0.0);
    th.move_to([10.0, 10.0, 1.0, 0.0], 50.0).unwrap();
    assert!(matches!(
        th.move_to([250.0, 10.0, 1.0, 0.0], 50.0),
        Err(MoveError::OutOfRange { .. })
    ));
    assert_eq!(
        th.move_to([10.0, 10.0, 1.0, 0.0], 50.0).map(|_| th.moves_total()),
        Ok(1),
        "zero-length move is ignored"
    );
    assert!(matches!(
        th.move_to([f64::NAN, 0.0, 0.0, 0.0], 50.0),
        Err(MoveError::BadPosition(_))
    ));
    assert!(matches!(
        th.move_to([1.0, 0.0, 0.0, 0.0], 0.0),
        Err(MoveError::BadSpeed(_))
    ));
    assert!(matches!(
        th.move_to([10.0, 10.0, 1.0, 80.0], 5.0),
        Err(MoveError::ExtrudeOnlyTooLong { .. })
    ));
    assert_eq!(th.position(), [10.0, 10.0, 1.0, 0.0]);
    let e = th.move_to([10.0, -1.0, 1.0, 0.0], 5.0).unwrap_err();
    assert_eq!(
        e.to_string(),
        "Move out of range: X=10.000 Y=-1.000 Z=1.000 [E=0.000]"
    );
}

#[test]
fn dwell_and_set_position() {
    let c = cfg();
    let mut th = Toolhead::new(c, 0.0);
    th.move_to([10.0, 0.0, 0.0, 0.0], 50.0).unwrap();
    th.dwell(1.5).unwrap();
    assert!(th.dwell(f64::NAN).is_err() && th.dwell(-1.0).is_err() && th.dwell(2e6).is_err());
    let t = th.print_time();
    th.set_position([0.0, 0.0, 0.0, 0.0]);
    th.move_to([5.0, 0.0, 0.0, 0.0], 50.0).unwrap();
    th.flush();
    let mut out = Vec::new();
    th.take_moves(&mut out);
    assert_eq!(out.len(), 2);
    assert!((out[1].print_time - t).abs() < 1e-12);
    assert!((out[1].print_time - out[0].end_time() - 1.5).abs() < 1e-9);
    assert_eq!(out[1].start_pos, [0.0; 4]);
}

#[test]
fn moves_become_final_before_the_end() {
    // A zig-zag of short moves: finality is decided lazily, well before the final flush.
    let c = cfg();
    let mut th = Toolhead::new(c, 0.0);
    let mut out = Vec::new();
    for i in 0..2000 {
        let x = 10.0 + (i % 2) as f64 * 20.0;
        let y = 10.0 + (i as f64 * 0.05) % 100.0;
        th.move_to([x, y, 0.0, 0.0], 150.0).unwrap();
        th.take_moves(&mut out);
        assert!(th.queued_moves() < 200, "queue grew to {}", th.queued_moves());
    }
    assert!(out.len() > 1900, "only {} final moves", out.len());
    th.flush();
    th.take_moves(&mut out);
    check_sequence(&out, &c);
}

#[test]
fn long_straight_runs_are_flushed_in_parts() {
    // Collinear segments never form a second hill: the 2 s limit finalizes the front anyway.
    let c = cfg();
    let mut th = Toolhead::new(c, 0.0);
    let mut out = Vec::new();
    for i in 1..=5000 {
        th.move_to([10.0 + (i as f64) * 0.03, 10.0, 0.0, 0.0], 10.0)
            .unwrap();
        th.take_moves(&mut out);
    }
    assert!(out.len() > 4000, "only {} final moves", out.len());
    th.flush();
    th.take_moves(&mut out);
    check_sequence(&out, &c);
    for m in &out[1..out.len() - 1] {
        assert!(
            (m.cruise_v - 10.0).abs() < 1e-9 && (m.start_v - 10.0).abs() < 1e-6,
            "{m:?}"
        );
    }
}

fn arb_targets() -> impl Strategy<Value = Vec<([f64; 4], f64)>> {
    let pt = (
        0.0f64..200.0,
        0.0f64..200.0,
        0.0f64..5.0,
        -2.0f64..2.0,
        1.0f64..400.0,
    );
    let small = (
        -3.0f64..3.0,
        -3.0f64..3.0,
        0.0f64..1.0,
        0.0f64..0.2,
        5.0f64..200.0,
    );
    (proptest::collection::vec(
        prop_oneof![pt.prop_map(|p| (true, p)), small.prop_map(|p| (false, p))],
        1..120,
    ))
    .prop_map(|steps| {
        let mut pos = [100.0, 100.0, 1.0, 0.0];
        let mut out = Vec::new();
        for (absolute, (a, b, c, e, v)) in steps {
            if absolute {
                pos = [a, b, c, pos[3] + e];
            } else {
                // Mostly small steps: zero Z change half of the time.
                pos[0] = (pos[0] + a).clamp(0.0, 200.0);
                pos[1] = (pos[1] + b).clamp(0.0, 200.0);
                if c > 0.5 {
                    pos[2] = (pos[2] + c - 0.5).min(200.0);
                }
                pos[3] += e;
            }
            out.push((pos, v));
        }
        out
    })
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 200, ..ProptestConfig::default() })]

    #[test]
    fn random_sequences_are_continuous(targets in arb_targets()) {
        let c = cfg();
        let mut th = Toolhead::new(c, 0.5);
        let mut out = Vec::new();
        for &(p, v) in &targets {
            th.move_to(p, v).unwrap();
            th.take_moves(&mut out);
        }
        th.flush();
        th.take_moves(&mut out);
        check_sequence(&out, &c);
        prop_assert_eq!(out.last().map(|m| m.end_pos), Some(th.position()));
    }

    #[test]
    fn lazy_flush_points_are_continuous(n in 50usize..400, seed in 0u64..1000) {
        // Many short moves with varied angles and speeds so that lazy and forced cuts happen.
        let c = cfg();
        let mut th = Toolhead::new(c, 0.0);
        let mut out = Vec::new();
        let mut x = 100.0;
        let mut y = 100.0;
        let mut s = seed;
        for _ in 0..n {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let ang = (s >> 11) as f64 / (1u64 << 53) as f64 * 0.8 - 0.4;
            let len = 0.2 + ((s >> 20) % 100) as f64 * 0.05;
            x = (x + len * ang.cos()).clamp(0.0, 200.0);
            y = (y + len * ang.sin()).clamp(0.0, 200.0);
            let v = 20.0 + ((s >> 40) % 300) as f64;
            th.move_to([x, y, 0.0, 0.0], v).unwrap();
            th.take_moves(&mut out);
        }
        th.flush();
        th.take_moves(&mut out);
        check_sequence(&out, &c);
    }
}
