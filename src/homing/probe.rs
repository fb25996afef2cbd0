//! `PROBE`, `PROBE_ACCURACY` and `QUERY_PROBE` (the G-code commands of Klipper's `[probe]`) on a
//! live print, through the homing machinery (the endstop + trsync protocol of [`crate::homing`]).
//!
//! One sample: Z must be homed (`Must home before probe`) and the probe open (`Probe triggered
//! prior to movement`); then a homing pass in probe mode ([`PassKind::Probe`]): Z moves toward
//! `z_position` at the probing speed while the probe's MCU samples its pin into a trsync group
//! with the Z steppers' MCUs, which stop the steppers on the trigger (relayed by the host when
//! the probe sits on another MCU; on corexz both motors A and B move Z and both stop). The
//! trigger's position is the forward kinematics of the steppers' step indices commanded at the
//! trigger's print time (from the probe MCU's trigger clock; cartesian: `n_trig · step_dist`);
//! the toolhead is resynced to where the steppers halted (`stepper_get_position`), so
//! the overshoot is accounted for. Errors are the homing ones: `Communication timeout during
//! homing`, `No trigger on probe after full movement`.
//!
//! Several samples: between two samples Z rises to trigger + `sample_retract_dist` at
//! `lift_speed`; when the spread (max − min) of the samples so far exceeds `samples_tolerance`
//! the samples are dropped and taken again, at most `samples_tolerance_retries` times (then
//! `Probe samples exceed samples_tolerance`). The result is the `median` (the middle sample, the
//! mean of the middle two for an even count) or the `average`.
//!
//! Output lines are Klipper's: `probe at X,Y is z=Z` per sample, `Result is z=Z`,
//! `probe: open|TRIGGERED`, and PROBE_ACCURACY's header and statistics (population standard
//! deviation); then Cadence's line of the passes' stop latency against the 25 ms budget
//! (`PROBE: 2 probe passes, stop at most A..B us after trigger (budget 25000 us)`).

use sysconfig::printer::{ProbeSection, SamplesResult, SAMPLES_RESULTS};

use super::{
    endstop_state, homing_pass, plain_move, wait_motion_done, HomingCtx, HomingError, ParamProblem, PassKind,
    PassPlan,
};
use crate::hardware::ProbeOut;

/// The G-code commands this module runs (the bed levelling ones through
/// [`super::bed_mesh`]).
pub const COMMANDS: [&str; 5] = [
    "PROBE",
    "PROBE_ACCURACY",
    "QUERY_PROBE",
    "BLTOUCH_DEBUG",
    "BLTOUCH_STORE",
];

/// PROBE_ACCURACY's default sample count.
const ACCURACY_SAMPLES: u32 = 10;

/// True for a command name this module runs.
pub fn is_probe_command(name: &str) -> bool {
    COMMANDS.contains(&name)
        || super::smart_effector::COMMANDS.contains(&name)
        || super::bed_mesh::COMMANDS.contains(&name)
        || super::z_tilt::COMMANDS.contains(&name)
        || super::screws::COMMANDS.contains(&name)
}

/// False for a levelling command whose section the printer lacks (`BED_MESH_*` without
/// `[bed_mesh]`, `Z_TILT_ADJUST` without `[z_tilt]`…): it is then an unknown command, reported
/// and skipped as Klipper does (an error with `--strict`).
pub fn is_configured(machine: &crate::hardware::Machine, name: &str) -> bool {
    match name {
        n if super::bed_mesh::COMMANDS.contains(&n) => machine.bed_mesh.is_some(),
        "Z_TILT_ADJUST" => machine.z_tilt.is_some(),
        "QUAD_GANTRY_LEVEL" => machine.quad_gantry_level.is_some(),
        "SCREWS_TILT_CALCULATE" => machine.screws_tilt_adjust.is_some(),
        n if super::smart_effector::COMMANDS.contains(&n) => super::smart_effector::is_configured(machine, n),
        _ => true,
    }
}

/// The settings of one PROBE / PROBE_ACCURACY: the config's, overridden by the command's
/// parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct ProbeParams {
    pub samples: u32,
    pub sample_retract_dist: f64,
    pub speed: f64,
    pub lift_speed: f64,
    pub samples_result: SamplesResult,
    pub samples_tolerance: f64,
    pub samples_tolerance_retries: u32,
}

/// Parameter `problem` of command `raw`.
/// A bad parameter of command line `raw`.
pub(crate) fn bad(raw: &str, problem: ParamProblem) -> HomingError {
    HomingError::BadParameter {
        raw: raw.to_string(),
        problem,
    }
}

/// The value of the last `KEY=VALUE` word of `raw` after the command name whose key is `key`
/// (case-insensitive).
pub(crate) fn param(raw: &str, key: &str) -> Option<String> {
    raw.split_whitespace()
        .skip(1)
        .filter_map(|w| w.split_once('='))
        .filter(|(k, _)| k.eq_ignore_ascii_case(key))
        .map(|(_, v)| v.to_string())
        .last()
}

/// `NAME KEY=VALUE …` → the (upper-cased key, value) pairs.
fn params(raw: &str) -> Result<Vec<(String, String)>, HomingError> {
    raw.split_whitespace()
        .skip(1)
        .map(|word| match word.split_once('=') {
            Some((k, v)) if !k.is_empty() => Ok((k.to_ascii_uppercase(), v.to_string())),
            _ => Err(bad(
                raw,
                ParamProblem::Malformed {
                    word: word.to_string(),
                },
            )),
        })
        .collect()
}

impl ProbeParams {
    /// Parses the parameters of `raw` (`SAMPLES`, `SAMPLE_RETRACT_DIST`, `PROBE_SPEED`,
    /// `LIFT_SPEED`, `SAMPLES_RESULT`, `SAMPLES_TOLERANCE`, `SAMPLES_TOLERANCE_RETRIES`; others
    /// are ignored, as Klipper does) over `cfg`; `samples`: the default sample count.
    pub fn parse(cfg: &ProbeSection, raw: &str, samples: u32) -> Result<ProbeParams, HomingError> {
        let ps = params(raw)?;
        let get = |key: &str| ps.iter().rev().find(|(k, _)| k == key).map(|(_, v)| v.as_str());
        let unparsable = |v: &str, key: &str| {
            let (value, key) = (v.to_string(), key.to_string());
            bad(raw, ParamProblem::Unparsable { value, key })
        };
        let float = |key: &str, default: f64, min: f64, strict: bool| -> Result<f64, HomingError> {
            let Some(v) = get(key) else { return Ok(default) };
            let x: f64 = v
                .parse()
                .ok()
                .filter(|x: &f64| x.is_finite())
                .ok_or_else(|| unparsable(v, key))?;
            let key = key.to_string();
            match (strict, x) {
                (true, x) if x <= min => Err(bad(raw, ParamProblem::NotAbove { key, min })),
                (false, x) if x < min => Err(bad(raw, ParamProblem::BelowMinimum { key, min })),
                _ => Ok(x),
            }
        };
        let int = |key: &str, default: u32, min: u32| -> Result<u32, HomingError> {
            let Some(v) = get(key) else { return Ok(default) };
            let x: i64 = v.parse().map_err(|_| unparsable(v, key))?;
            let key = key.to_string();
            if x < i64::from(min) {
                let min = f64::from(min);
                return Err(bad(raw, ParamProblem::BelowMinimum { key, min }));
            }
            u32::try_from(x).map_err(|_| bad(raw, ParamProblem::TooLarge { key }))
        };
        let samples_result = match get("SAMPLES_RESULT") {
            None => cfg.samples_result,
            Some(v) => SAMPLES_RESULTS
                .iter()
                .find(|(name, _)| name.eq_ignore_ascii_case(v))
                .map(|&(_, r)| r)
                .ok_or_else(|| bad(raw, ParamProblem::SamplesResult { value: v.to_string() }))?,
        };
        let speed = float("PROBE_SPEED", cfg.speed, 0.0, true)?;
        Ok(ProbeParams {
            samples: int("SAMPLES", samples, 1)?,
            sample_retract_dist: float("SAMPLE_RETRACT_DIST", cfg.sample_retract_dist, 0.0, true)?,
            speed,
            lift_speed: float("LIFT_SPEED", cfg.lift_speed, 0.0, true)?,
            samples_result,
            samples_tolerance: float("SAMPLES_TOLERANCE", cfg.samples_tolerance, 0.0, false)?,
            samples_tolerance_retries: int("SAMPLES_TOLERANCE_RETRIES", cfg.samples_tolerance_retries, 0)?,
        })
    }
}

/// The median (mean of the middle two for an even count) or the average of `z` (not empty).
pub fn combine(z: &[f64], how: SamplesResult) -> f64 {
    if z.is_empty() {
        return f64::NAN;
    }
    match how {
        SamplesResult::Average => z.iter().sum::<f64>() / z.len() as f64,
        SamplesResult::Median => {
            let mut s = z.to_vec();
            s.sort_by(f64::total_cmp);
            let m = s.len() / 2;
            if s.len() % 2 == 1 {
                s[m]
            } else {
                (s[m - 1] + s[m]) / 2.0
            }
        }
    }
}

/// `probe accuracy results: …` of the samples `z`.
pub fn accuracy_line(z: &[f64]) -> String {
    let max = z.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let min = z.iter().copied().fold(f64::INFINITY, f64::min);
    let avg = combine(z, SamplesResult::Average);
    let median = combine(z, SamplesResult::Median);
    let var = z.iter().map(|v| (v - avg).powi(2)).sum::<f64>() / z.len().max(1) as f64;
    format!(
        "probe accuracy results: maximum {max:.6}, minimum {min:.6}, range {:.6}, average {avg:.6}, \
         median {median:.6}, standard deviation {:.6}",
        max - min,
        var.sqrt()
    )
}

/// Runs probe command `name` (one of [`COMMANDS`]) written as `raw`; its output lines go to
/// `out`.
pub fn run(ctx: &mut HomingCtx<'_>, name: &str, raw: &str, out: &mut Vec<String>) -> Result<(), HomingError> {
    if name.starts_with("BLTOUCH_") {
        return super::bltouch::run_command(ctx, name, raw, out);
    }
    if super::smart_effector::COMMANDS.contains(&name) {
        return super::smart_effector::run(ctx, name, raw, out);
    }
    if super::bed_mesh::COMMANDS.contains(&name) {
        return super::bed_mesh::run(ctx, name, raw, out);
    }
    if super::z_tilt::COMMANDS.contains(&name) {
        return super::z_tilt::run(ctx, name, raw, out);
    }
    if super::screws::COMMANDS.contains(&name) {
        return super::screws::run(ctx, name, raw, out);
    }
    let Some(probe) = ctx.machine.probe.clone() else {
        return Err(HomingError::NoSection {
            name: name.to_string(),
            section: "probe",
        });
    };
    match name {
        "QUERY_PROBE" => {
            wait_motion_done(ctx)?;
            let (_, triggered, _) = endstop_state(ctx, &probe.endstop)?;
            out.push(format!("probe: {}", if triggered { "TRIGGERED" } else { "open" }));
            Ok(())
        }
        "PROBE_ACCURACY" => {
            let p = ProbeParams::parse(&probe.cfg, raw, ACCURACY_SAMPLES)?;
            let pos = ctx.pipeline.position();
            out.push(format!(
                "PROBE_ACCURACY at X:{:.3} Y:{:.3} Z:{:.3} (samples={} retract={:.3} speed={:.1} lift_speed={:.1})",
                pos[0], pos[1], pos[2], p.samples, p.sample_retract_dist, p.speed, p.lift_speed
            ));
            let first_pass = ctx.probe_passes.len();
            let z = super::bltouch::session(ctx, |ctx| {
                let mut z = Vec::new();
                while z.len() < p.samples as usize {
                    let at = probe_once(ctx, &probe, p.speed, out)?;
                    z.push(at[2]);
                    lift(ctx, at[2] + p.sample_retract_dist, p.lift_speed)?;
                }
                Ok(z)
            })?;
            out.push(accuracy_line(&z));
            out.push(passes_line(ctx, name, first_pass));
            Ok(())
        }
        _ => {
            let p = ProbeParams::parse(&probe.cfg, raw, probe.cfg.samples)?;
            let first_pass = ctx.probe_passes.len();
            let z = super::bltouch::session(ctx, |ctx| run_probe(ctx, &probe, &p, out))?;
            out.push(format!("Result is z={z:.6}"));
            out.push(passes_line(ctx, name, first_pass));
            Ok(())
        }
    }
}

/// The stop latency line of command `name`'s probe passes (from pass `first_pass` on), against
/// the 25 ms budget.
fn passes_line(ctx: &HomingCtx<'_>, name: &str, first_pass: usize) -> String {
    let passes = &ctx.probe_passes[first_pass.min(ctx.probe_passes.len())..];
    super::bed_mesh::latency_line(name, passes)
}

/// The samples of one PROBE with tolerance retries; returns the combined Z.
pub(crate) fn run_probe(
    ctx: &mut HomingCtx<'_>,
    probe: &ProbeOut,
    p: &ProbeParams,
    out: &mut Vec<String>,
) -> Result<f64, HomingError> {
    let mut retries = 0;
    let mut z: Vec<f64> = Vec::new();
    while z.len() < p.samples as usize {
        let at = probe_once(ctx, probe, p.speed, out)?;
        z.push(at[2]);
        let max = z.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let min = z.iter().copied().fold(f64::INFINITY, f64::min);
        if max - min > p.samples_tolerance {
            if retries >= p.samples_tolerance_retries {
                return Err(HomingError::SamplesOutOfTolerance);
            }
            out.push("Probe samples exceed tolerance. Retrying...".to_string());
            retries += 1;
            z.clear();
        }
        if z.len() < p.samples as usize {
            lift(ctx, at[2] + p.sample_retract_dist, p.lift_speed)?;
        }
    }
    Ok(combine(&z, p.samples_result))
}

/// Z up (or down) to `z` at `speed`.
pub(crate) fn lift(ctx: &mut HomingCtx<'_>, z: f64, speed: f64) -> Result<(), HomingError> {
    let mut pos = ctx.pipeline.position();
    pos[2] = z;
    plain_move(ctx, pos, speed)
}

/// One probing move; returns the toolhead X, Y and the trigger's Z.
fn probe_once(
    ctx: &mut HomingCtx<'_>,
    probe: &ProbeOut,
    speed: f64,
    out: &mut Vec<String>,
) -> Result<[f64; 3], HomingError> {
    if !ctx.pipeline.gcode_state().homed()[2] {
        return Err(HomingError::NotHomed);
    }
    wait_motion_done(ctx)?;
    let target = probe.z_position;
    // A BLTouch is deployed first (and stowed after, also after a failure); a Smart Effector
    // limits the move's acceleration after its recovery dwell.
    let (pass, _) = super::bltouch::sample(ctx, |ctx| {
        if endstop_state(ctx, &probe.endstop)?.1 {
            return Err(HomingError::TriggeredBeforeMove);
        }
        super::smart_effector::sample(ctx, |ctx| {
            let kind = PassKind::Probe { target };
            homing_pass(ctx, &probe.endstop, kind, speed, PassPlan::default())
        })
    })?;
    ctx.probe_passes.push(pass.clone());
    let pos = ctx.pipeline.position();
    let at = [pos[0], pos[1], pass.trigger_position];
    out.push(format!("probe at {:.3},{:.3} is z={:.6}", at[0], at[1], at[2]));
    Ok(at)
}

#[cfg(test)]
mod tests {
    use super::*;
    use sysconfig::printer::PinRef;

    fn cfg() -> ProbeSection {
        ProbeSection {
            pin: PinRef {
                mcu: "probe_mcu".into(),
                pin: "PA4".into(),
                invert: false,
                pullup: true,
                pulldown: false,
            },
            x_offset: 0.0,
            y_offset: 0.0,
            z_offset: 1.0,
            speed: 5.0,
            lift_speed: 7.0,
            samples: 2,
            sample_retract_dist: 2.0,
            samples_result: SamplesResult::Average,
            samples_tolerance: 0.1,
            samples_tolerance_retries: 0,
            z_position: None,
            activate_gcode: None,
            deactivate_gcode: None,
        }
    }

    #[test]
    fn parameters_override_the_config() {
        let c = cfg();
        let p = ProbeParams::parse(&c, "PROBE", c.samples).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((p.samples, p.speed, p.lift_speed), (2, 5.0, 7.0));
        assert_eq!(p.samples_result, SamplesResult::Average);
        let p = ProbeParams::parse(
            &c,
            "PROBE samples=5 PROBE_SPEED=2.5 LIFT_SPEED=9 SAMPLE_RETRACT_DIST=1 SAMPLES_RESULT=median \
             SAMPLES_TOLERANCE=0 SAMPLES_TOLERANCE_RETRIES=3 OTHER=1",
            1,
        )
        .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            p,
            ProbeParams {
                samples: 5,
                sample_retract_dist: 1.0,
                speed: 2.5,
                lift_speed: 9.0,
                samples_result: SamplesResult::Median,
                samples_tolerance: 0.0,
                samples_tolerance_retries: 3,
            }
        );
    }

    #[test]
    fn bad_parameters_are_named() {
        let c = cfg();
        let err = |raw: &str| {
            ProbeParams::parse(&c, raw, 1)
                .err()
                .map(|e| e.to_string())
                .unwrap_or_default()
        };
        assert_eq!(
            err("PROBE SAMPLES=0"),
            "Error on 'PROBE SAMPLES=0': SAMPLES must have minimum of 1"
        );
        assert_eq!(
            err("PROBE SAMPLES=x"),
            "Error on 'PROBE SAMPLES=x': unable to parse 'x' for SAMPLES"
        );
        assert_eq!(
            err("PROBE PROBE_SPEED=0"),
            "Error on 'PROBE PROBE_SPEED=0': PROBE_SPEED must be above 0"
        );
        assert_eq!(
            err("PROBE PROBE_SPEED=nan"),
            "Error on 'PROBE PROBE_SPEED=nan': unable to parse 'nan' for PROBE_SPEED"
        );
        assert_eq!(
            err("PROBE SAMPLES_TOLERANCE=-1"),
            "Error on 'PROBE SAMPLES_TOLERANCE=-1': SAMPLES_TOLERANCE must have minimum of 0"
        );
        assert_eq!(
            err("PROBE SAMPLES_RESULT=mode"),
            "Error on 'PROBE SAMPLES_RESULT=mode': SAMPLES_RESULT must be median or average, got 'mode'"
        );
        assert_eq!(
            err("PROBE 5"),
            "Error on 'PROBE 5': malformed parameter '5' (expected KEY=VALUE)"
        );
    }

    #[test]
    fn median_and_average() {
        assert_eq!(combine(&[3.0, 1.0, 2.0], SamplesResult::Median), 2.0);
        assert_eq!(combine(&[4.0, 1.0, 2.0, 3.0], SamplesResult::Median), 2.5);
        assert_eq!(combine(&[1.0, 2.0, 6.0], SamplesResult::Average), 3.0);
        assert!(combine(&[], SamplesResult::Median).is_nan());
        assert_eq!(
            accuracy_line(&[1.0, 2.0, 3.0]),
            "probe accuracy results: maximum 3.000000, minimum 1.000000, range 2.000000, average \
             2.000000, median 2.000000, standard deviation 0.816497"
        );
    }

    #[test]
    fn parsing_never_panics() {
        let c = cfg();
        let words = [
            "SAMPLES=",
            "=",
            "SAMPLES=-9999999999999",
            "PROBE_SPEED=1e999",
            "X",
            "LIFT_SPEED=-0",
            "é=ü",
            "",
        ];
        for a in words {
            for b in words {
                let _ = ProbeParams::parse(&c, &format!("PROBE {a} {b}"), 1);
            }
        }
    }

    #[test]
    fn commands() {
        assert!(is_probe_command("PROBE") && is_probe_command("QUERY_PROBE"));
        assert!(!is_probe_command("probe") && !is_probe_command("G28"));
    }
}
