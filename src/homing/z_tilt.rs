//! `Z_TILT_ADJUST` (`[z_tilt]`): levels a gantry lifted by several independently driven Z
//! motors with the probe, on a live print.
//!
//! Each round: Z to `horizontal_move_z`, the nozzle to each of `points` at `speed`, one PROBE
//! there (the probe's samples and tolerance); the heights, placed at the probe's X, Y, are fitted
//! by a plane ([`planner::bed_mesh::tilt`]) and each motor moves alone by the fit at its
//! `z_positions` entry minus the mean of those (the other Z motors held still: their planner
//! lanes frozen for the move, then every Z lane resynced to the toolhead's unchanged position).
//! With `retries` > 0 the rounds repeat until the probed range is within `retry_tolerance`
//! (`Retries: N/M Probed points range: R tolerance: T`, Klipper's words), else
//! `Too many retries`. `QUAD_GANTRY_LEVEL` (`[quad_gantry_level]`) is the same with four corner
//! motors and the bilinear surface through its four points; a correction above `max_adjust`
//! aborts it.

use planner::bed_mesh::tilt::{motor_adjustments, quad_adjustments};

use super::error::{HomingError, LevelingError, ParamProblem};
use super::probe::{bad, lift, param, run_probe, ProbeParams};
use super::{plain_move, wait_motion_done, HomingCtx};

/// The G-code commands this module runs.
pub const COMMANDS: [&str; 2] = ["Z_TILT_ADJUST", "QUAD_GANTRY_LEVEL"];

fn num(raw: &str, key: &str, default: f64, min: f64) -> Result<f64, HomingError> {
    let Some(value) = param(raw, key) else {
        return Ok(default);
    };
    let key = key.to_string();
    match value.parse::<f64>() {
        Ok(x) if x.is_finite() && x >= min => Ok(x),
        Ok(_) => Err(bad(raw, ParamProblem::BelowMinimum { key, min })),
        Err(_) => Err(bad(raw, ParamProblem::Unparsable { value, key })),
    }
}

/// Runs `Z_TILT_ADJUST` or `QUAD_GANTRY_LEVEL` (`name`) `[RETRIES=] [RETRY_TOLERANCE=]
/// [HORIZONTAL_MOVE_Z=]` (and the probe's sample parameters); its output lines go to `out`.
pub fn run(ctx: &mut HomingCtx<'_>, name: &str, raw: &str, out: &mut Vec<String>) -> Result<(), HomingError> {
    let quad = name == "QUAD_GANTRY_LEVEL";
    let (cfg, who) = match quad {
        true => (ctx.machine.quad_gantry_level.clone(), "quad_gantry_level"),
        false => (ctx.machine.z_tilt.clone(), "z_tilt"),
    };
    let Some(zt) = cfg else {
        return Err(HomingError::NoSection {
            name: name.to_string(),
            section: who,
        });
    };
    let Some(probe) = ctx.machine.probe.clone() else {
        return Err(LevelingError::NeedsProbe {
            name: name.to_string(),
        }
        .into());
    };
    let retries = num(raw, "RETRIES", f64::from(zt.retries), 0.0)? as u32;
    let tolerance = num(raw, "RETRY_TOLERANCE", zt.retry_tolerance, 0.0)?;
    let hmz = num(raw, "HORIZONTAL_MOVE_Z", zt.horizontal_move_z, f64::NEG_INFINITY)?;
    let pp = ProbeParams::parse(&probe.cfg, raw, probe.cfg.samples)?;
    if !ctx.pipeline.gcode_state().homed().iter().all(|&h| h) {
        return Err(LevelingError::NotHomed.into());
    }
    let motors: Vec<usize> = (0..ctx.machine.steppers.len())
        .filter(|&i| ctx.machine.steppers[i].axis == 2)
        .collect();
    if motors.len() != zt.z_positions.len() {
        return Err(LevelingError::MotorCount {
            name: name.to_string(),
            motors: motors.len(),
            positions: zt.z_positions.len(),
        }
        .into());
    }
    let offset = [probe.cfg.x_offset, probe.cfg.y_offset];
    let first_pass = ctx.probe_passes.len();
    super::bltouch::session(ctx, |ctx| {
        let mut attempt = 0;
        loop {
            lift(ctx, hmz, probe.cfg.lift_speed)?;
            let mut probed = Vec::with_capacity(zt.points.len());
            for p in &zt.points {
                let mut pos = ctx.pipeline.position();
                pos[0] = p[0];
                pos[1] = p[1];
                pos[2] = hmz;
                plain_move(ctx, pos, zt.speed)?;
                let z = run_probe(ctx, &probe, &pp, out)?;
                probed.push(([p[0] + offset[0], p[1] + offset[1]], z));
                lift(ctx, hmz, probe.cfg.lift_speed)?;
            }
            let zs = probed.iter().map(|p| p.1);
            let range = zs.clone().fold(f64::NEG_INFINITY, f64::max) - zs.fold(f64::INFINITY, f64::min);
            if retries > 0 {
                out.push(format!(
                    "Retries: {attempt}/{retries} Probed points range: {range:.6} tolerance: {tolerance:.6}"
                ));
                if range <= tolerance {
                    return Ok(());
                }
                if attempt >= retries {
                    return Err(LevelingError::TooManyRetries.into());
                }
            }
            let adj = match quad {
                true => quad_adjustments(&probed, &zt.z_positions),
                false => motor_adjustments(&probed, &zt.z_positions),
            }
            .ok_or_else(|| LevelingError::NoSpan {
                name: name.to_string(),
            })?;
            if let Some(max) = zt.max_adjust {
                if let Some(a) = adj.iter().find(|a| a.abs() > max) {
                    return Err(LevelingError::MaxAdjust { adjust: a.abs(), max }.into());
                }
            }
            out.push("Making the following Z adjustments:".to_string());
            for (&i, a) in motors.iter().zip(&adj) {
                out.push(format!("{} = {a:.6}", ctx.machine.steppers[i].name));
            }
            for (k, a) in adj.iter().enumerate() {
                move_alone(ctx, &motors, k, *a, zt.speed)?;
            }
            attempt += 1;
            if retries == 0 {
                return Ok(());
            }
        }
    })?;
    let passes = &ctx.probe_passes[first_pass.min(ctx.probe_passes.len())..];
    out.push(super::bed_mesh::latency_line(who, passes));
    Ok(())
}

/// Moves Z motor `motors[k]` alone by `dz` (the others frozen), the toolhead's position
/// unchanged after it.
fn move_alone(
    ctx: &mut HomingCtx<'_>,
    motors: &[usize],
    k: usize,
    dz: f64,
    speed: f64,
) -> Result<(), HomingError> {
    if dz == 0.0 {
        return Ok(());
    }
    wait_motion_done(ctx)?;
    let home = ctx.pipeline.position();
    let others: Vec<usize> = motors.iter().copied().filter(|&i| i != motors[k]).collect();
    ctx.pipeline.freeze_lanes(&others)?;
    let mut to = home;
    to[2] += dz;
    let moved = plain_move(ctx, to, speed).and_then(|()| wait_motion_done(ctx));
    ctx.pipeline.thaw_lanes();
    moved?;
    super::motors::resync_motors(ctx, motors, home)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parameters() {
        let num = |raw: &str, key: &str, default: f64, min: f64| {
            num(raw, key, default, min).map_err(|e| e.to_string())
        };
        assert_eq!(num("Z_TILT_ADJUST RETRIES=3", "RETRIES", 0.0, 0.0), Ok(3.0));
        assert_eq!(num("Z_TILT_ADJUST", "RETRIES", 2.0, 0.0), Ok(2.0));
        assert_eq!(
            num("Z_TILT_ADJUST retry_tolerance=x", "RETRY_TOLERANCE", 0.0, 0.0),
            Err(
                "Error on 'Z_TILT_ADJUST retry_tolerance=x': unable to parse 'x' for RETRY_TOLERANCE"
                    .to_string()
            )
        );
        assert!(num("Z_TILT_ADJUST RETRIES=-1", "RETRIES", 0.0, 0.0)
            .unwrap_err()
            .contains("minimum of 0"));
    }
}
