//! `SCREWS_TILT_CALCULATE` (`[screws_tilt_adjust]`): probes each bed screw and tells how far to
//! turn each one, in Klipper's words. (`[bed_screws]`'s `BED_SCREWS_ADJUST` needs no probe: the
//! G-code feed runs it, `planner::gcode::bed_screws`.)
//!
//! The probe runs at each screw (the nozzle at `screwN`, Z at `horizontal_move_z` between
//! them). With the base screw's height `z₀` and a screw's `z`, `adjust = (z₀ − z) / pitch` turns:
//! for a clockwise thread CW when the bed is low there (adjust ≥ 0), else CCW, written as
//! `hh:mm` (full turns, then minutes of 1/60 turn). The base is `screw1`, or with
//! `DIRECTION=CW|CCW` the screw that makes every other adjustment go that way.
//! `MAX_DEVIATION=` fails the command when a screw's height is farther than that from the base.

use sysconfig::printer::{ScrewThread, ScrewsSection};

use super::probe::{bad, lift, param, run_probe, ProbeParams};
use super::{plain_move, HomingCtx, HomingError, LevelingError, ParamProblem};

/// The G-code commands this module runs.
pub const COMMANDS: [&str; 1] = ["SCREWS_TILT_CALCULATE"];

/// Klipper's legend line.
pub const LEGEND: &str = "01:20 means 1 full turn and 20 minutes, CW=clockwise, CCW=counter-clockwise";

/// The direction and `hh:mm` of the turn that moves a screw measured at `z` to the base's `z0`.
pub fn turns(z0: f64, z: f64, thread: ScrewThread) -> (&'static str, u32, u32) {
    let adjust = (z0 - z) / thread.pitch;
    let cw = (adjust >= 0.0) == thread.clockwise;
    let total = (adjust.abs() * 60.0).round() as u32;
    (if cw { "CW" } else { "CCW" }, total / 60, total % 60)
}

/// The report lines of screws at `z` (in `screws` order) against the base `base`.
pub fn report(cfg: &ScrewsSection, z: &[f64], base: usize) -> Vec<String> {
    let mut lines = vec![LEGEND.to_string()];
    let z0 = z.get(base).copied().unwrap_or(0.0);
    for (i, (s, &zi)) in cfg.screws.iter().zip(z).enumerate() {
        let head = format!("{} : x={:.1}, y={:.1}, z={zi:.5}", s.name, s.xy[0], s.xy[1]);
        if i == base {
            lines.push(format!(
                "{} (base) : x={:.1}, y={:.1}, z={zi:.5}",
                s.name, s.xy[0], s.xy[1]
            ));
        } else {
            let (dir, h, m) = turns(z0, zi, cfg.thread);
            lines.push(format!("{head} : adjust {dir} {h:02}:{m:02}"));
        }
    }
    lines
}

/// The base screw: `screw1`, or for `DIRECTION` the one every other screw turns away from in
/// that direction (the highest for CW on a clockwise thread, the lowest for CCW).
pub fn base_screw(z: &[f64], direction: Option<&str>, thread: ScrewThread) -> Result<usize, ParamProblem> {
    let pick_max = match direction.map(str::to_ascii_uppercase).as_deref() {
        None => return Ok(0),
        Some("CW") => thread.clockwise,
        Some("CCW") => !thread.clockwise,
        Some(other) => {
            return Err(ParamProblem::Direction {
                value: other.to_string(),
            })
        }
    };
    let mut best = 0;
    for (i, v) in z.iter().enumerate() {
        let better = if pick_max { *v > z[best] } else { *v < z[best] };
        if better {
            best = i;
        }
    }
    Ok(best)
}

/// Runs `name` written as `raw`; its output lines go to `out`.
pub fn run(ctx: &mut HomingCtx<'_>, name: &str, raw: &str, out: &mut Vec<String>) -> Result<(), HomingError> {
    let no_section = |section| HomingError::NoSection {
        name: name.to_string(),
        section,
    };
    let Some(cfg) = ctx.machine.screws_tilt_adjust.clone() else {
        return Err(no_section("screws_tilt_adjust"));
    };
    let Some(probe) = ctx.machine.probe.clone() else {
        return Err(LevelingError::NeedsProbe {
            name: name.to_string(),
        }
        .into());
    };
    let max_dev = match param(raw, "MAX_DEVIATION") {
        None => None,
        Some(v) => Some(
            v.parse::<f64>()
                .ok()
                .filter(|x| x.is_finite() && *x >= 0.0)
                .ok_or_else(|| {
                    let (value, key) = (v.clone(), "MAX_DEVIATION".to_string());
                    bad(raw, ParamProblem::Unparsable { value, key })
                })?,
        ),
    };
    let direction = param(raw, "DIRECTION");
    let pp = ProbeParams::parse(&probe.cfg, raw, probe.cfg.samples)?;
    if !ctx.pipeline.gcode_state().homed().iter().all(|&h| h) {
        return Err(LevelingError::NotHomed.into());
    }
    let z = super::bltouch::session(ctx, |ctx| {
        lift(ctx, cfg.horizontal_move_z, probe.cfg.lift_speed)?;
        let mut z = Vec::with_capacity(cfg.screws.len());
        for s in &cfg.screws {
            let mut pos = ctx.pipeline.position();
            pos[0] = s.xy[0];
            pos[1] = s.xy[1];
            pos[2] = cfg.horizontal_move_z;
            plain_move(ctx, pos, cfg.speed)?;
            z.push(run_probe(ctx, &probe, &pp, out)?);
            lift(ctx, cfg.horizontal_move_z, probe.cfg.lift_speed)?;
        }
        Ok(z)
    })?;
    let base =
        base_screw(&z, direction.as_deref(), cfg.thread).map_err(|p| bad("SCREWS_TILT_CALCULATE", p))?;
    out.extend(report(&cfg, &z, base));
    if let Some(max) = max_dev {
        if z.iter().any(|v| (v - z[base]).abs() > max) {
            return Err(LevelingError::ExceedsLimits { max }.into());
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use sysconfig::printer::{Screw, SCREW_THREADS};

    fn cfg() -> ScrewsSection {
        let screw = |name: &str, x: f64, y: f64| Screw {
            name: name.into(),
            xy: [x, y],
            fine_adjust: None,
        };
        ScrewsSection {
            screws: vec![
                screw("front left screw", -5.0, 30.0),
                screw("front right screw", 155.0, 30.0),
                screw("rear right screw", 155.0, 190.0),
            ],
            horizontal_move_z: 5.0,
            speed: 50.0,
            thread: SCREW_THREADS[0].1,
            probe_height: 0.0,
            probe_speed: 5.0,
        }
    }

    #[test]
    fn turns_and_report() {
        let cw_m3 = SCREW_THREADS[0].1;
        // 0.125 mm low on a 0.5 mm pitch: a quarter turn clockwise.
        assert_eq!(turns(2.5, 2.375, cw_m3), ("CW", 0, 15));
        assert_eq!(turns(2.5, 3.25, cw_m3), ("CCW", 1, 30));
        assert_eq!(turns(2.5, 2.375, SCREW_THREADS[1].1), ("CCW", 0, 15));
        let lines = report(&cfg(), &[2.4875, 2.36, 2.715], 0);
        assert_eq!(
            lines,
            [
                LEGEND,
                "front left screw (base) : x=-5.0, y=30.0, z=2.48750",
                "front right screw : x=155.0, y=30.0, z=2.36000 : adjust CW 00:15",
                "rear right screw : x=155.0, y=190.0, z=2.71500 : adjust CCW 00:27",
            ]
        );
    }

    #[test]
    fn direction_picks_the_base() {
        let t = SCREW_THREADS[0].1;
        let z = [2.4, 2.6, 2.3];
        assert_eq!(base_screw(&z, None, t), Ok(0));
        assert_eq!(base_screw(&z, Some("cw"), t), Ok(1));
        assert_eq!(base_screw(&z, Some("CCW"), t), Ok(2));
        assert!(base_screw(&z, Some("up"), t)
            .unwrap_err()
            .to_string()
            .contains("DIRECTION must be CW or CCW"));
        // With the CW base every other screw turns CW.
        for (i, &v) in z.iter().enumerate().filter(|(i, _)| *i != 1) {
            assert_eq!(turns(z[1], v, t).0, "CW", "screw {i}");
        }
    }
}
