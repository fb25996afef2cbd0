//! Compressor tests: every output is replayed by the checker.

use super::*;
use crate::checker::{check, CheckStats};
use proptest::prelude::*;

const MAX_ERR: u32 = 1250;

/// Compresses `steps` (ideal clock, dir) in one go and checks the result.
fn compress_all(steps: &[(f64, bool)]) -> (Vec<StepCmd>, CheckStats) {
    compress_with(steps, DEFAULT_LOOKAHEAD_BACKOFF)
}

fn compress_with(steps: &[(f64, bool)], backoff: usize) -> (Vec<StepCmd>, CheckStats) {
    compress_tuned(steps, backoff, SearchTuning::default())
}

fn compress_tuned(steps: &[(f64, bool)], backoff: usize, tuning: SearchTuning) -> (Vec<StepCmd>, CheckStats) {
    let mut c = StepCompressor::new(0.01, 50e6, MAX_ERR);
    c.set_lookahead_backoff(backoff);
    c.set_tuning(tuning);
    c.set_record_ideal(true);
    for &(clock, dir) in steps {
        c.push_step(clock, dir);
    }
    let mut out = Vec::new();
    c.finish(&mut out);
    let ideal = c.take_ideal();
    let stats = match check(&out, &ideal, MAX_ERR) {
        Ok(s) => s,
        Err(e) => panic!("{e}\ncommands: {out:?}"),
    };
    assert_eq!(c.step_count(), steps.len() as u64);
    assert_eq!(c.position_steps(), stats.position);
    (out, stats)
}

fn queue_steps(cmds: &[StepCmd]) -> Vec<(u32, u16, i16)> {
    cmds.iter()
        .filter_map(|c| match *c {
            StepCmd::QueueStep {
                interval, count, add, ..
            } => Some((interval, count, add)),
            _ => None,
        })
        .collect()
}

#[test]
fn constant_rate_packs_into_one_command() {
    let steps: Vec<_> = (1..=1000).map(|k| (1e6 + k as f64 * 5000.0, true)).collect();
    let (cmds, stats) = compress_all(&steps);
    assert_eq!(
        cmds[0],
        StepCmd::ResetClock {
            clock: 1e6 as u64 + 5000 - MAX_ERR as u64 - 1
        }
    );
    assert_eq!(cmds[1], StepCmd::SetDir { dir: true });
    assert!(stats.queue_steps <= 2, "{cmds:?}");
    assert_eq!(queue_steps(&cmds).last().map(|q| q.0), Some(5000));
}

#[test]
fn fractional_rate_needs_few_commands() {
    // 3333.3 ticks per step: an integer interval drifts 0.3 tick per step.
    let steps: Vec<_> = (1..=20000).map(|k| (k as f64 * 3333.3, true)).collect();
    let (_, stats) = compress_all(&steps);
    assert!(
        stats.queue_steps <= 20000 / 2000,
        "{} commands",
        stats.queue_steps
    );
}

#[test]
fn constant_acceleration_uses_add() {
    // Accelerating at 3000 mm/s² from rest with 80 steps/mm: t_k = sqrt(2k / (80·3000)).
    let steps: Vec<_> = (1..=3000)
        .map(|k| (1e7 + (2.0 * k as f64 / 240_000.0).sqrt() * 50e6, true))
        .collect();
    let (_, stats) = compress_all(&steps);
    assert!(stats.queue_steps < 60, "{} commands", stats.queue_steps);
}

#[test]
fn long_gap_resets_the_clock() {
    let steps = [
        (1000.0, true),
        (2000.0, true),
        (1e10, false),
        (1e10 + 4000.0, false),
    ];
    let (cmds, stats) = compress_all(&steps);
    assert_eq!(stats.resets, 2);
    assert_eq!(stats.dir_changes, 1);
    assert_eq!(stats.position, 0);
    assert!(
        cmds.iter()
            .filter(|c| matches!(c, StepCmd::ResetClock { .. }))
            .count()
            == 2
    );
}

#[test]
fn count_is_capped() {
    let steps: Vec<_> = (1..=140_000).map(|k| (k as f64 * 2000.0, true)).collect();
    // The full search takes 4 commands; the default (no latest-end search) ends its first
    // command earlier and takes one more.
    for (tuning, most) in [(SearchTuning::SEARCH, 4), (SearchTuning::default(), 5)] {
        let (cmds, stats) = compress_tuned(&steps, DEFAULT_LOOKAHEAD_BACKOFF, tuning);
        assert!(queue_steps(&cmds).iter().all(|q| q.1 as usize <= MAX_COUNT));
        assert!(stats.queue_steps <= most, "{tuning:?}: {cmds:?}");
    }
}

#[test]
fn simultaneous_steps_and_reversals() {
    let steps = [
        (5000.0, true),
        (5000.0, false),
        (5000.0, true),
        (9000.0, true),
        (9000.5, true),
    ];
    compress_all(&steps);
}

#[test]
fn flush_stops_at_the_horizon() {
    let mut c = StepCompressor::new(0.01, 50e6, MAX_ERR);
    for k in 1..=100 {
        c.push_step(k as f64 * 10_000.0, true);
    }
    let mut out = Vec::new();
    c.flush(500_000, &mut out);
    // Every step before the horizon is out; later ones may ride along in the last command.
    assert!(c.step_count() >= 49);
    let before = c.step_count();
    c.flush(500_000, &mut out);
    assert_eq!(c.step_count(), before);
    c.finish(&mut out);
    assert_eq!(c.step_count(), 100);
    assert_eq!(c.pending_steps(), 0);
}

fn arb_steps() -> impl Strategy<Value = Vec<(f64, bool)>> {
    // Gaps from "same tick" to seconds, with runs of similar gaps and occasional reversals.
    let gap = prop_oneof![
        3 => 500.0f64..5000.0,
        2 => 0.0f64..200.0,
        1 => 5000.0f64..200_000.0,
        1 => Just(0.0),
        1 => 1e6f64..3e9,
    ];
    proptest::collection::vec((gap, 0u8..20, 1usize..60, -3.0f64..3.0), 1..40).prop_map(|runs| {
        let mut t = 1000.0;
        let mut dir = true;
        let mut out = Vec::new();
        for (gap, flip, len, accel) in runs {
            if flip == 0 {
                dir = !dir;
            }
            let mut g = gap;
            for _ in 0..len {
                t += g;
                g = (g + accel).max(0.0);
                out.push((t, dir));
            }
        }
        out
    })
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 300, ..ProptestConfig::default() })]

    #[test]
    fn any_monotone_step_times_compress_correctly(steps in arb_steps(), backoff in 0usize..4) {
        compress_with(&steps, backoff);
    }

    #[test]
    fn incremental_flushes_are_correct(steps in arb_steps(), cut in 1usize..8) {
        let mut c = StepCompressor::new(0.01, 50e6, MAX_ERR);
        c.set_record_ideal(true);
        let mut out = Vec::new();
        let chunk = steps.len().div_ceil(cut);
        for part in steps.chunks(chunk.max(1)) {
            for &(clock, dir) in part {
                c.push_step(clock, dir);
            }
            let horizon = part.last().map_or(0.0, |s| s.0) as u64 / 2;
            c.flush(horizon, &mut out);
        }
        c.finish(&mut out);
        let ideal = c.take_ideal();
        prop_assert!(check(&out, &ideal, MAX_ERR).is_ok(), "{:?}", check(&out, &ideal, MAX_ERR));
    }
}

proptest! {
    /// The one-conversion window equals ⌈clock − max_err⌉ (clamped to 0) and ⌊clock⌋ taken
    /// with floating-point subtraction and the library's floor and ceiling.
    #[test]
    fn step_window_matches_float_floor_and_ceil(
        whole in 0u64..(1u64 << 44),
        frac in prop_oneof![Just(0.0f64), 0.0f64..1.0],
        max_err in 0i64..100_000,
    ) {
        let clock = whole as f64 + frac;
        let w = step_window(clock, max_err, true);
        prop_assert_eq!(w.hi, clock.floor() as u64);
        prop_assert_eq!(w.lo, (clock - max_err as f64).ceil().max(0.0) as u64);
    }
}

#[test]
fn step_window_near_zero_and_small_clocks() {
    for clock in [
        0.0,
        1e-300,
        0.25,
        1.0,
        1_249.999_999,
        1250.0,
        1_250.000_001,
        1251.5,
    ] {
        let w = step_window(clock, MAX_ERR as i64, false);
        assert_eq!(w.hi, clock.floor() as u64, "{clock}");
        assert_eq!(w.lo, (clock - MAX_ERR as f64).ceil().max(0.0) as u64, "{clock}");
    }
}
