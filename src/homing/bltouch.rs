//! `[bltouch]`: deploying, stowing and checking a BLTouch around each probing or Z-homing
//! move, `BLTOUCH_DEBUG` and `BLTOUCH_STORE`, with Klipper's timing.
//!
//! The servo signal: a command is a pulse of the command's width (the BLTouch's datasheet:
//! [`COMMANDS`]) repeated every [`SIGNAL_PERIOD`] (the control pin is a soft-PWM digital out with
//! that cycle), from print time `t` for `max(MIN_CMD_TIME, ⌊(duration − MIN_CMD_TIME) /
//! SIGNAL_PERIOD⌋ · SIGNAL_PERIOD)`, then off. The command's action ends at `t + duration`; the
//! next command may start at `max(action end, signal end + MIN_CMD_TIME)`. A deploy or stow
//! lasts `pin_move_time`, other commands [`MIN_CMD_TIME`]; the toolhead dwells until the probe
//! is ready (its next move starts after the last command's slot).
//!
//! Around one probing move (or Z homing pass on `probe:z_virtual_endstop`):
//! - before: the sensor self-test when none passed in the last [`TEST_TIME`] of print time
//!   (with `pin_up_touch_mode_reports_triggered`: pin_up, touch_mode, and the sensor must read
//!   triggered; three tries separated by a `reset`, then `BLTouch failed to verify sensor
//!   state`), then pin_down (and touch_mode with `probe_with_touch_mode`);
//! - after (also after a failed move): pin_up (`reset` first without
//!   `pin_up_reports_not_triggered`), then with `pin_up_reports_not_triggered` the sensor must
//!   read open (three tries with `reset` + pin_up between them, `Failed to verify BLTouch probe
//!   is raised; retrying.`, then `BLTouch failed to raise probe`).
//!
//! Without `stow_on_each_sample` the probe is deployed before the first sample of a command
//! (PROBE, PROBE_ACCURACY, G28 Z) and stowed after its last. The first use sends
//! `set_output_mode` and stows the probe (a failure there is a message, as Klipper logs it at
//! connect). A sensor check reads the sensor (`endstop_query_state`) from the command's action end
//! until 100 ms after it.

use std::time::{Duration, Instant};

use links::dict::{Cmd, Dictionary};
use sysconfig::printer::BlTouchOutputMode;

use super::{
    clock_at_print_time, endstop_state, mcu, print_now, print_time_of_clock, HomingCtx, HomingError,
};
use crate::hardware::{BlTouchOut, ProbeOut};

/// Servo signal period (s).
pub const SIGNAL_PERIOD: f64 = 0.020;
/// Shortest command slot (s).
pub const MIN_CMD_TIME: f64 = 5.0 * SIGNAL_PERIOD;
/// Print time between two sensor self-tests (s).
pub const TEST_TIME: f64 = 5.0 * 60.0;
/// Duration of the `reset` between retries (s).
pub const RETRY_RESET_TIME: f64 = 1.0;
/// How long after a command's action end the sensor may take to show the expected state (s).
const VERIFY_WINDOW: f64 = 0.100;
/// Updates kept pending on the servo output at once (well inside an MCU's update queue).
const MAX_PENDING_UPDATES: usize = 6;

/// The commands and their pulse widths (s), sorted by name (as BLTOUCH_DEBUG lists them).
pub const COMMANDS: [(&str, f64); 8] = [
    ("output_mode_store", 0.001884),
    ("pin_down", 0.000650),
    ("pin_up", 0.001475),
    ("reset", 0.002190),
    ("self_test", 0.001780),
    ("set_5V_output_mode", 0.001988),
    ("set_OD_output_mode", 0.002091),
    ("touch_mode", 0.001165),
];

/// Pulse width (s) of command `name`.
fn width(name: &str) -> Option<f64> {
    COMMANDS.iter().find(|(n, _)| *n == name).map(|&(_, w)| w)
}

/// Where a probing session stands without `stow_on_each_sample`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Multi {
    /// No session: deploy and stow around each sample.
    #[default]
    Off,
    /// Session started, not deployed yet.
    First,
    /// Deployed for the rest of the session.
    On,
}

/// Timing and session state of one BLTouch (print times of the main MCU).
#[derive(Debug, Clone, Default)]
pub struct BlTouchState {
    /// Earliest start of the next command.
    next_cmd_time: f64,
    /// When the last command's action ends.
    action_end_time: f64,
    /// The next sensor self-test is due from this toolhead print time.
    next_test_time: f64,
    multi: Multi,
    /// Print times of the digital out updates sent (to keep the MCU's queue from overflowing).
    pending: Vec<f64>,
    /// The start-up stow was done.
    started: bool,
}

/// `config_digital_out` + `set_digital_out_pwm_cycle` of the servo output (off; an inverted
/// `!` pin idles high).
pub fn config_commands(dict: &Dictionary, b: &BlTouchOut) -> Result<Vec<Cmd>, crate::mcus::ConfigureError> {
    let pin = dict
        .pin(&b.control_pin.pin)
        .map_err(|source| crate::hardware::PinError {
            what: "[bltouch] control_pin".to_string(),
            source,
        })?;
    let idle = i64::from(b.control_pin.invert);
    let cycle = (SIGNAL_PERIOD * dict.clock_freq()?).round() as i64;
    Ok(vec![
        dict.encode(
            "config_digital_out",
            &[i64::from(b.oid), i64::from(pin), idle, idle, 0],
        )?,
        dict.encode("set_digital_out_pwm_cycle", &[i64::from(b.oid), cycle])?,
    ])
}

/// The printer's BLTouch and probe, when it has a BLTouch.
fn parts(ctx: &HomingCtx<'_>) -> Option<(BlTouchOut, ProbeOut)> {
    Some((ctx.machine.bltouch.clone()?, ctx.machine.probe.clone()?))
}

/// Runs `f` on the BLTouch's state (a poisoned lock still holds valid timing).
fn with_state<T>(b: &BlTouchOut, f: impl FnOnce(&mut BlTouchState) -> T) -> T {
    let mut guard = b.state.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
    f(&mut guard)
}

/// One BLTouch operation in progress: the context, the device, its state (written back at
/// the end).
struct Op<'c, 'a> {
    ctx: &'c mut HomingCtx<'a>,
    b: BlTouchOut,
    probe: ProbeOut,
    st: BlTouchState,
}

impl<'c, 'a> Op<'c, 'a> {
    fn new(ctx: &'c mut HomingCtx<'a>) -> Option<Op<'c, 'a>> {
        let (b, probe) = parts(ctx)?;
        let st = with_state(&b, |s| s.clone());
        Some(Op { ctx, b, probe, st })
    }

    /// Every move planned so far is sent and done: the probe's commands and waits come after
    /// them, and the planner continues from a fresh print time ([`Op::settle`]).
    fn idle(&mut self) -> Result<(), HomingError> {
        super::wait_motion_done(self.ctx)
    }

    /// Writes the state back.
    fn done(self) {
        let st = self.st;
        with_state(&self.b, |s| *s = st);
    }

    fn say(&mut self, line: String) {
        self.ctx.messages.push(line);
    }

    /// The next command starts no earlier than a command sent now can act.
    fn sync_mcu_print_time(&mut self) {
        self.st.next_cmd_time = self.st.next_cmd_time.max(self.ctx.earliest_start());
    }

    /// The toolhead dwells until the next command slot, or the next command waits for the
    /// toolhead's last move.
    fn sync_print_time(&mut self) -> Result<(), HomingError> {
        let print_time = self
            .ctx
            .pipeline
            .toolhead_print_time()
            .max(self.ctx.earliest_start());
        if self.st.next_cmd_time > print_time {
            Ok(self.ctx.pipeline.raise_print_time(self.st.next_cmd_time)?)
        } else {
            self.st.next_cmd_time = print_time;
            Ok(())
        }
    }

    /// Sends command `name` for `duration` s from the next command slot.
    fn send_cmd(&mut self, name: &str, duration: f64) -> Result<(), HomingError> {
        let w = width(name).ok_or_else(|| HomingError::BlTouchUnknownCommand {
            name: name.to_string(),
        })?;
        let conn = mcu(self.ctx.mcus, &self.b.control_pin.mcu)?;
        // Room in the MCU's update queue: wait for the oldest updates to be applied.
        self.st.pending.retain(|&t| t > print_now(self.ctx.mcus));
        while self.st.pending.len() + 2 > MAX_PENDING_UPDATES {
            let oldest = self.st.pending.iter().copied().fold(f64::INFINITY, f64::min);
            wait_print_time(self.ctx, oldest)?;
            let now = print_now(self.ctx.mcus);
            self.st.pending.retain(|&t| t > now);
        }
        let t = self.st.next_cmd_time;
        let start = clock_at_print_time(self.ctx.mcus, conn, t);
        let signal = ((duration - MIN_CMD_TIME) / SIGNAL_PERIOD).trunc() * SIGNAL_PERIOD;
        let end = start + (MIN_CMD_TIME.max(signal) * conn.clock_freq).round() as u64;
        let end_time = print_time_of_clock(self.ctx.mcus, conn, end);
        let cycle = SIGNAL_PERIOD * conn.clock_freq;
        let on = (w * conn.clock_freq).round();
        self.queue_pwm(conn, start, on, cycle)?;
        self.queue_pwm(conn, end, 0.0, cycle)?;
        self.st.pending.extend([t, end_time]);
        self.st.action_end_time = t + duration;
        self.st.next_cmd_time = self.st.action_end_time.max(end_time + MIN_CMD_TIME);
        Ok(())
    }

    fn queue_pwm(
        &self,
        conn: &crate::mcus::McuConn,
        clock: u64,
        on: f64,
        cycle: f64,
    ) -> Result<(), HomingError> {
        let on = if self.b.control_pin.invert { cycle - on } else { on };
        let dict = conn.link.dictionary();
        let cmd = dict
            .encode(
                "queue_digital_out",
                &[
                    i64::from(self.b.oid),
                    (clock & 0xFFFF_FFFF) as i64,
                    on.round() as i64,
                ],
            )
            .map_err(|source| HomingError::Encode {
                mcu: conn.name.clone(),
                source,
            })?;
        conn.link
            .send_clocked(cmd, 0, clock)
            .map_err(|source| HomingError::McuLink {
                mcu: conn.name.clone(),
                source,
            })
    }

    /// Whether the sensor shows `triggered` within [`VERIFY_WINDOW`] of the last action's end.
    fn verify_state(&mut self, triggered: bool) -> Result<bool, HomingError> {
        let end = self.st.action_end_time;
        wait_print_time(self.ctx, end)?;
        loop {
            if endstop_state(self.ctx, &self.probe.endstop)?.1 == triggered {
                return Ok(true);
            }
            if print_now(self.ctx.mcus) > end + VERIFY_WINDOW {
                return Ok(false);
            }
            std::thread::sleep(Duration::from_millis(2));
        }
    }

    fn raise_probe(&mut self) -> Result<(), HomingError> {
        self.sync_mcu_print_time();
        if !self.b.cfg.pin_up_reports_not_triggered {
            self.send_cmd("reset", MIN_CMD_TIME)?;
        }
        self.send_cmd("pin_up", self.b.cfg.pin_move_time)
    }

    fn verify_raise_probe(&mut self) -> Result<(), HomingError> {
        if !self.b.cfg.pin_up_reports_not_triggered {
            // No way to tell.
            return Ok(());
        }
        for retry in 0..3 {
            if self.verify_state(false)? {
                return Ok(());
            }
            if retry >= 2 {
                return Err(HomingError::BlTouchRaise);
            }
            self.say("Failed to verify BLTouch probe is raised; retrying.".to_string());
            self.sync_mcu_print_time();
            self.send_cmd("reset", RETRY_RESET_TIME)?;
            self.send_cmd("pin_up", self.b.cfg.pin_move_time)?;
        }
        Ok(())
    }

    fn test_sensor(&mut self) -> Result<(), HomingError> {
        if !self.b.cfg.pin_up_touch_mode_reports_triggered {
            return Ok(());
        }
        let print_time = self.ctx.pipeline.toolhead_print_time();
        if print_time < self.st.next_test_time {
            self.st.next_test_time = print_time + TEST_TIME;
            return Ok(());
        }
        self.sync_print_time()?;
        for retry in 0..3 {
            self.send_cmd("pin_up", self.b.cfg.pin_move_time)?;
            self.send_cmd("touch_mode", MIN_CMD_TIME)?;
            let ok = self.verify_state(true)?;
            self.sync_print_time()?;
            if ok {
                self.st.next_test_time = print_time + TEST_TIME;
                return Ok(());
            }
            if retry >= 2 {
                return Err(HomingError::BlTouchSensor);
            }
            self.say(format!("{}; retrying.", HomingError::BlTouchSensor));
            self.send_cmd("reset", RETRY_RESET_TIME)?;
        }
        Ok(())
    }

    fn lower_probe(&mut self) -> Result<(), HomingError> {
        self.test_sensor()?;
        self.sync_print_time()?;
        self.send_cmd("pin_down", self.b.cfg.pin_move_time)?;
        if self.b.cfg.probe_with_touch_mode {
            self.send_cmd("touch_mode", MIN_CMD_TIME)?;
        }
        Ok(())
    }

    /// The connect-time set-up, on first use: the output mode, and the probe stowed.
    fn start(&mut self) -> Result<(), HomingError> {
        if self.st.started {
            return Ok(());
        }
        self.st.started = true;
        self.sync_mcu_print_time();
        self.st.next_cmd_time += 0.200;
        if let Some(mode) = self.b.cfg.set_output_mode {
            self.sync_mcu_print_time();
            self.send_cmd(output_mode_cmd(mode), MIN_CMD_TIME)?;
        }
        let raised = self.raise_probe().and_then(|()| self.verify_raise_probe());
        if let Err(e) = raised {
            self.say(format!("BLTouch raise probe error: {e}"));
        }
        Ok(())
    }

    /// Waits (wall time) until the probe is ready for the toolhead (the last command's slot);
    /// the toolhead's next move then starts no earlier than a move planned now can.
    fn settle(&mut self) -> Result<(), HomingError> {
        self.sync_print_time()?;
        let t = self.st.next_cmd_time;
        wait_print_time(self.ctx, t)?;
        let start = self.ctx.earliest_start();
        Ok(self.ctx.pipeline.raise_print_time(start)?)
    }
}

fn output_mode_cmd(mode: BlTouchOutputMode) -> &'static str {
    match mode {
        BlTouchOutputMode::FiveVolt => "set_5V_output_mode",
        BlTouchOutputMode::OpenDrain => "set_OD_output_mode",
    }
}

/// Waits (bounded, wall time) until the main MCU's print time reaches `t`.
fn wait_print_time(ctx: &HomingCtx<'_>, t: f64) -> Result<(), HomingError> {
    let ahead = (t - print_now(ctx.mcus)).max(0.0);
    let deadline = Instant::now() + Duration::from_secs_f64(ahead / ctx.time_scale.max(1e-3) + 5.0);
    while print_now(ctx.mcus) < t {
        ctx.mcus.check()?;
        if Instant::now() > deadline {
            return Err(HomingError::BlTouchClock);
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    Ok(())
}

/// Starts a probing session (PROBE, PROBE_ACCURACY, G28 Z on the probe); nothing without a
/// BLTouch.
pub(crate) fn start_session(ctx: &mut HomingCtx<'_>) -> Result<(), HomingError> {
    let Some(mut op) = Op::new(ctx) else {
        return Ok(());
    };
    let r = op.idle().and_then(|()| op.start()).and_then(|()| op.settle());
    if !op.b.cfg.stow_on_each_sample {
        op.st.multi = Multi::First;
    }
    op.done();
    r
}

/// Before one probing move: deployed (after the self-test when due) and settled.
pub(crate) fn prepare(ctx: &mut HomingCtx<'_>) -> Result<(), HomingError> {
    let Some(mut op) = Op::new(ctx) else {
        return Ok(());
    };
    let r = (|| {
        op.idle()?;
        if op.st.multi != Multi::On {
            op.lower_probe()?;
            if op.st.multi == Multi::First {
                op.st.multi = Multi::On;
            }
        }
        op.settle()
    })();
    op.done();
    r
}

/// After one probing move (successful or not): stowed and checked, unless the session keeps it
/// deployed.
pub(crate) fn finish(ctx: &mut HomingCtx<'_>) -> Result<(), HomingError> {
    let Some(mut op) = Op::new(ctx) else {
        return Ok(());
    };
    let r = (|| {
        op.idle()?;
        if op.st.multi == Multi::Off {
            op.raise_probe()?;
            op.verify_raise_probe()?;
        }
        op.settle()
    })();
    op.done();
    r
}

/// Ends the session: stowed and checked if it was kept deployed.
pub(crate) fn end_session(ctx: &mut HomingCtx<'_>) -> Result<(), HomingError> {
    let Some(mut op) = Op::new(ctx) else {
        return Ok(());
    };
    let r = (|| {
        if op.st.multi != Multi::Off {
            op.st.multi = Multi::Off;
            op.idle()?;
            op.sync_print_time()?;
            op.raise_probe()?;
            op.verify_raise_probe()?;
            op.settle()?;
        }
        Ok(())
    })();
    op.st.multi = Multi::Off;
    op.done();
    r
}

/// Runs `body` as one probing session: started, and ended also when `body` failed (its error
/// is the one reported).
pub(crate) fn session<T>(
    ctx: &mut HomingCtx<'_>,
    body: impl FnOnce(&mut HomingCtx<'_>) -> Result<T, HomingError>,
) -> Result<T, HomingError> {
    start_session(ctx)?;
    let r = body(ctx);
    let end = end_session(ctx);
    let v = r?;
    end.map(|()| v)
}

/// Runs one probing move `body` between [`prepare`] and [`finish`]; the probe is stowed also
/// when the move failed (its error is the one reported).
pub(crate) fn sample<T>(
    ctx: &mut HomingCtx<'_>,
    body: impl FnOnce(&mut HomingCtx<'_>) -> Result<T, HomingError>,
) -> Result<T, HomingError> {
    prepare(ctx)?;
    let r = body(ctx);
    let fin = finish(ctx);
    let v = r?;
    fin.map(|()| v)
}

/// `BLTOUCH_DEBUG [COMMAND=…]` and `BLTOUCH_STORE [MODE=5V|OD]`; their answers go to `out`.
pub fn run_command(
    ctx: &mut HomingCtx<'_>,
    name: &str,
    raw: &str,
    out: &mut Vec<String>,
) -> Result<(), HomingError> {
    let Some(mut op) = Op::new(ctx) else {
        return Err(HomingError::NoSection {
            name: name.to_string(),
            section: "bltouch",
        });
    };
    let value = |key: &str| super::probe::param(raw, key);
    let r = (|| match name {
        "BLTOUCH_DEBUG" => {
            let Some(cmd) = value("COMMAND").filter(|c| width(c).is_some()) else {
                let names: Vec<&str> = COMMANDS.iter().map(|(n, _)| *n).collect();
                out.push(format!("BLTouch commands: {}", names.join(", ")));
                return Ok(());
            };
            out.push(format!("Sending BLTOUCH_DEBUG COMMAND={cmd}"));
            op.idle()?;
            op.sync_print_time()?;
            let move_time = op.b.cfg.pin_move_time;
            op.send_cmd(&cmd, move_time)?;
            op.settle()
        }
        _ => {
            let Some(mode) = value("MODE").filter(|m| m == "5V" || m == "OD") else {
                out.push("BLTouch output modes: 5V, OD".to_string());
                return Ok(());
            };
            out.push(format!("Storing BLTouch output mode: {mode}"));
            op.idle()?;
            let set = if mode == "5V" {
                "set_5V_output_mode"
            } else {
                "set_OD_output_mode"
            };
            op.sync_print_time()?;
            for cmd in ["pin_down", set, "output_mode_store", set, "pin_up"] {
                op.send_cmd(cmd, MIN_CMD_TIME)?;
            }
            op.settle()
        }
    })();
    op.done();
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn commands_are_sorted_and_distinct_by_width() {
        assert!(COMMANDS.windows(2).all(|w| w[0].0 < w[1].0));
        let mut widths: Vec<f64> = COMMANDS.iter().map(|&(_, w)| w).collect();
        widths.sort_by(f64::total_cmp);
        // The simulated probe tells them apart within ±40 µs.
        assert!(widths.windows(2).all(|w| w[1] - w[0] > 80e-6));
        assert_eq!(width("pin_down"), Some(0.000650));
        assert_eq!(width("pin_sideways"), None);
    }

    #[test]
    fn signal_lasts_whole_periods_after_the_minimum() {
        // pin_move_time 0.68: pulses for 0.58 s; the next command 0.1 s after the signal.
        let signal = |d: f64| MIN_CMD_TIME.max(((d - MIN_CMD_TIME) / SIGNAL_PERIOD).trunc() * SIGNAL_PERIOD);
        assert!((signal(0.680) - 0.58).abs() < 1e-12);
        assert_eq!(signal(MIN_CMD_TIME), MIN_CMD_TIME);
        assert_eq!(signal(0.05), MIN_CMD_TIME);
        assert!((signal(RETRY_RESET_TIME) - 0.9).abs() < 1e-12);
    }
}
