//! `[smart_effector]`: the probing moves' acceleration limit and recovery dwell,
//! `SET_SMART_EFFECTOR` and `RESET_SMART_EFFECTOR` (programming the effector through its
//! control pin), with Klipper's behaviour.
//!
//! Around each probing move (PROBE, PROBE_ACCURACY and the levelling commands' samples; not a
//! G28 on `probe:z_virtual_endstop`, as in Klipper): with `probe_accel` set the toolhead's
//! acceleration limit becomes it (as `M204 S`) and the old one is restored after the move,
//! also after a failed one; with `recovery_time` set the toolhead dwells that long first.
//!
//! Programming: the control pin is a digital output (`config_digital_out`, idle at its
//! inactive level, no `max_duration`) the host drives with `queue_digital_out` updates
//! scheduled on the MCU's clock, [`BITS_PER_SECOND`] bits/s. Each byte is the 14 bits
//! `0 0 1 0 b7 b6 b5 b4 !b4 b3 b2 b1 b0 !b0` ([`bit_stream`]); bit `k` of a command starts at
//! `t0 + k / BITS_PER_SECOND`, `t0` the toolhead's print time once every earlier move is done;
//! an update is sent only where the level changes, and a line left active after the last bit
//! goes back to idle one bit later ([`level_changes`]). The toolhead dwells until the end of
//! the stream and waits for it. SENSITIVITY=s sends `105 s 255−s`; RESET sends `131 131`. At
//! most 3 bytes, so at most 43 updates are queued at once (the firmware's digital outs share a
//! pool of 128).

use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use links::dict::{Cmd, Dictionary};
use sysconfig::printer::{PinRef, SmartEffectorSection};

use super::{clock_at_print_time, mcu, print_now, wait_motion_done, HomingCtx, HomingError, ParamProblem};

/// The control line's bit rate.
pub const BITS_PER_SECOND: f64 = 1000.0;
/// The G-code commands of this module.
pub const COMMANDS: [&str; 2] = ["SET_SMART_EFFECTOR", "RESET_SMART_EFFECTOR"];
/// The sensitivity command's first byte.
const CMD_SENSITIVITY: u8 = 105;
/// The reset command (sent twice).
const CMD_RESET: u8 = 131;

/// The probing settings `SET_SMART_EFFECTOR` can change.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Settings {
    /// Acceleration of the probing moves (mm/s²); 0: the toolhead's.
    pub probe_accel: f64,
    /// Dwell before each probing move (s); 0: none.
    pub recovery_time: f64,
}

/// A `[smart_effector]`: its control output, if wired, and its settings (kept across G-code
/// commands); the probe it is, is the machine's [`crate::hardware::ProbeOut`].
#[derive(Debug, Clone)]
pub struct SmartEffectorOut {
    /// The control pin and its oid on its MCU (after that MCU's steppers and endstops).
    pub control: Option<(PinRef, u8)>,
    pub settings: Arc<Mutex<Settings>>,
}

impl SmartEffectorOut {
    /// From the config; `next_oid` numbers the control output on its MCU.
    pub fn new(cfg: &SmartEffectorSection, next_oid: impl FnOnce(&str) -> u8) -> SmartEffectorOut {
        SmartEffectorOut {
            control: cfg.control_pin.clone().map(|p| {
                let oid = next_oid(&p.mcu);
                (p, oid)
            }),
            settings: Arc::new(Mutex::new(Settings {
                probe_accel: cfg.probe_accel,
                recovery_time: cfg.recovery_time,
            })),
        }
    }

    /// The settings now (a poisoned lock still holds valid numbers).
    pub fn settings(&self) -> Settings {
        *self.settings.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn set(&self, s: Settings) {
        *self.settings.lock().unwrap_or_else(PoisonError::into_inner) = s;
    }
}

/// `config_digital_out` of the control output: idle (its inactive level, high for a `!` pin)
/// from configuration on and at shutdown.
pub fn config_commands(
    dict: &Dictionary,
    pin: &PinRef,
    oid: u8,
) -> Result<Vec<Cmd>, crate::mcus::ConfigureError> {
    let number = dict.pin(&pin.pin).map_err(|source| crate::hardware::PinError {
        what: "[smart_effector] control_pin".to_string(),
        source,
    })?;
    let idle = i64::from(pin.invert);
    Ok(vec![dict.encode(
        "config_digital_out",
        &[i64::from(oid), i64::from(number), idle, idle, 0],
    )?])
}

/// The line's bits for `bytes`.
pub fn bit_stream(bytes: &[u8]) -> Vec<bool> {
    let mut bits = Vec::with_capacity(bytes.len() * 14);
    for &b in bytes {
        let bit = |i: u8| (b >> i) & 1 == 1;
        bits.extend([false, false, true, false]);
        bits.extend([bit(7), bit(6), bit(5), bit(4), !bit(4)]);
        bits.extend([bit(3), bit(2), bit(1), bit(0), !bit(0)]);
    }
    bits
}

/// The pin updates of `bits` on a pin inverted or not: (bit index, pin level) where the level
/// changes, the return to idle included; and the stream's length in bits.
pub fn level_changes(bits: &[bool], invert: bool) -> (Vec<(usize, bool)>, usize) {
    let idle = invert;
    let mut last = idle;
    let mut changes = Vec::new();
    for (k, &b) in bits.iter().enumerate() {
        let level = b != invert;
        if level != last {
            changes.push((k, level));
            last = level;
        }
    }
    let mut end = bits.len();
    if last != idle {
        changes.push((end, idle));
        end += 1;
    }
    (changes, end)
}

/// Runs one probing move `body` with the effector's acceleration limit and after its recovery
/// dwell; the toolhead's acceleration is restored also when the move failed (its error is the
/// one reported). Just `body` without a `[smart_effector]`.
pub(crate) fn sample<T>(
    ctx: &mut HomingCtx<'_>,
    body: impl FnOnce(&mut HomingCtx<'_>) -> Result<T, HomingError>,
) -> Result<T, HomingError> {
    let Some(s) = ctx
        .machine
        .smart_effector
        .as_ref()
        .map(SmartEffectorOut::settings)
    else {
        return body(ctx);
    };
    let old_accel = ctx.pipeline.max_accel();
    if s.probe_accel > 0.0 {
        ctx.pipeline.set_max_accel(s.probe_accel)?;
    }
    let r = (|| {
        if s.recovery_time > 0.0 {
            let t = ctx.pipeline.toolhead_print_time().max(ctx.earliest_start());
            ctx.pipeline.raise_print_time(t + s.recovery_time)?;
        }
        body(ctx)
    })();
    if s.probe_accel > 0.0 {
        let restored = ctx.pipeline.set_max_accel(old_accel);
        let v = r?;
        return restored.map(|()| v).map_err(HomingError::from);
    }
    r
}

/// True when command `name` exists on this printer: SET_SMART_EFFECTOR with a
/// `[smart_effector]`, RESET_SMART_EFFECTOR only with its `control_pin` (as Klipper registers
/// them).
pub fn is_configured(machine: &crate::hardware::Machine, name: &str) -> bool {
    match (name, &machine.smart_effector) {
        ("RESET_SMART_EFFECTOR", Some(e)) => e.control.is_some(),
        (_, e) => e.is_some(),
    }
}

/// `SET_SMART_EFFECTOR [SENSITIVITY=0..255] [ACCEL=] [RECOVERY_TIME=]` and
/// `RESET_SMART_EFFECTOR`; their answers go to `out`.
pub fn run(ctx: &mut HomingCtx<'_>, name: &str, raw: &str, out: &mut Vec<String>) -> Result<(), HomingError> {
    let Some(e) = ctx.machine.smart_effector.clone() else {
        return Err(HomingError::NoSection {
            name: name.to_string(),
            section: "smart_effector",
        });
    };
    if name == "RESET_SMART_EFFECTOR" {
        send(ctx, &e, &[CMD_RESET, CMD_RESET])?;
        out.push("SmartEffector sensitivity was reset".to_string());
        return Ok(());
    }
    let old = e.settings();
    let sensitivity = int_param(raw, "SENSITIVITY", 0, 255)?;
    let new = Settings {
        probe_accel: float_param(raw, "ACCEL")?.unwrap_or(old.probe_accel),
        recovery_time: float_param(raw, "RECOVERY_TIME")?.unwrap_or(old.recovery_time),
    };
    let mut lines = vec!["SmartEffector:".to_string()];
    if let Some(s) = sensitivity {
        if e.control.is_none() {
            return Err(HomingError::SmartEffectorNoControlPin);
        }
        send(ctx, &e, &[CMD_SENSITIVITY, s, 255 - s])?;
        lines.push(format!("sensitivity: {s}"));
    }
    e.set(new);
    // Klipper's words, its spelling included.
    lines.push(match new.probe_accel {
        a if a > 0.0 => format!("probing accelartion: {a:.3}"),
        _ => "probing acceleration control disabled".to_string(),
    });
    lines.push(match new.recovery_time {
        t if t > 0.0 => format!("probe recovery time: {t:.3}"),
        _ => "probe recovery time disabled".to_string(),
    });
    out.extend(lines);
    Ok(())
}

/// Integer parameter `key` of `raw` within `min..=max`, if given.
fn int_param(raw: &str, key: &str, min: i64, max: i64) -> Result<Option<u8>, HomingError> {
    let Some(v) = super::probe::param(raw, key) else {
        return Ok(None);
    };
    let bad = |problem| super::probe::bad(raw, problem);
    let key = key.to_string();
    let x: i64 = v.parse().map_err(|_| {
        bad(ParamProblem::Unparsable {
            value: v.clone(),
            key: key.clone(),
        })
    })?;
    if x < min {
        return Err(bad(ParamProblem::BelowMinimum { key, min: min as f64 }));
    }
    if x > max {
        return Err(bad(ParamProblem::AboveMaximum { key, max: max as f64 }));
    }
    u8::try_from(x)
        .map(Some)
        .map_err(|_| bad(ParamProblem::TooLarge { key }))
}

/// Parameter `key` of `raw`, a number ≥ 0, if given.
fn float_param(raw: &str, key: &str) -> Result<Option<f64>, HomingError> {
    let Some(v) = super::probe::param(raw, key) else {
        return Ok(None);
    };
    let bad = |problem| super::probe::bad(raw, problem);
    let key = key.to_string();
    let x: f64 = v.parse().ok().filter(|x: &f64| x.is_finite()).ok_or_else(|| {
        bad(ParamProblem::Unparsable {
            value: v.clone(),
            key: key.clone(),
        })
    })?;
    if x < 0.0 {
        return Err(bad(ParamProblem::BelowMinimum { key, min: 0.0 }));
    }
    Ok(Some(x))
}

/// Sends `bytes` on the control line after every earlier move, then dwells until the stream
/// ends and waits for it.
fn send(ctx: &mut HomingCtx<'_>, e: &SmartEffectorOut, bytes: &[u8]) -> Result<(), HomingError> {
    let Some((pin, oid)) = e.control.clone() else {
        return Err(HomingError::SmartEffectorNoControlPin);
    };
    wait_motion_done(ctx)?;
    let start = ctx.pipeline.toolhead_print_time().max(ctx.earliest_start());
    let (changes, bits) = level_changes(&bit_stream(bytes), pin.invert);
    let conn = mcu(ctx.mcus, &pin.mcu)?;
    let step = 1.0 / BITS_PER_SECOND;
    let dict = conn.link.dictionary();
    let encode_err = |source| HomingError::Encode {
        mcu: conn.name.clone(),
        source,
    };
    for (k, level) in changes {
        let clock = clock_at_print_time(ctx.mcus, conn, start + k as f64 * step);
        let args = [i64::from(oid), (clock & 0xFFFF_FFFF) as i64, i64::from(level)];
        let cmd = dict.encode("queue_digital_out", &args).map_err(encode_err)?;
        conn.link
            .send_clocked(cmd, 0, clock)
            .map_err(|source| HomingError::McuLink {
                mcu: conn.name.clone(),
                source,
            })?;
    }
    let end = start + bits as f64 * step;
    ctx.pipeline.raise_print_time(end)?;
    // Wait (bounded, wall time) until the main MCU's print time has passed the stream's end.
    let ahead = (end - print_now(ctx.mcus)).max(0.0);
    let deadline = Instant::now() + Duration::from_secs_f64(ahead / ctx.time_scale.max(1e-3) + 5.0);
    while print_now(ctx.mcus) < end {
        ctx.mcus.check()?;
        if Instant::now() > deadline {
            return Err(HomingError::ClockStalled {
                mcu: ctx.mcus.main().name.clone(),
            });
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    let resume = ctx.earliest_start();
    Ok(ctx.pipeline.raise_print_time(resume)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bytes_go_out_as_klipper_frames_them() {
        // 105 = 0110 1001: start, 0110, !0, 1001, !1.
        let bits: String = bit_stream(&[105])
            .iter()
            .map(|&b| if b { '1' } else { '0' })
            .collect();
        assert_eq!(bits, "00100110110010");
        assert_eq!(bit_stream(&[131, 131]).len(), 28);
    }

    #[test]
    fn only_changes_are_sent_and_the_line_returns_to_idle() {
        // 0x10 ends in b0 = 0, !b0 = 1: back to idle one bit after the stream.
        let bits = bit_stream(&[0x10]);
        let (changes, end) = level_changes(&bits, false);
        assert_eq!(
            changes,
            [
                (2, true),
                (3, false),
                (7, true),
                (8, false),
                (13, true),
                (14, false)
            ]
        );
        assert_eq!(end, 15);
        // Inverted: the same instants, opposite levels.
        let (inv, end_inv) = level_changes(&bits, true);
        assert_eq!(end_inv, end);
        assert!(inv.iter().zip(&changes).all(|(a, b)| a.0 == b.0 && a.1 != b.1));
        // Ending low: no extra update, the stream is 14 bits.
        let (c, end) = level_changes(&bit_stream(&[0x01]), false);
        assert_eq!((c.last().copied(), end), (Some((13, false)), 14));
        // The longest command fits the firmware's update pool (128) with room to spare.
        for s in 0..=255u8 {
            let (c, _) = level_changes(&bit_stream(&[CMD_SENSITIVITY, s, 255 - s]), false);
            assert!(c.len() <= 43, "{s}: {}", c.len());
        }
    }
}
