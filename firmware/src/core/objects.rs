//! Commands and timer events of the oid objects other than steppers: endstops, trsyncs
//! (homing), digital outs, analog ins, and the Cadence `cadence_get_lateness` extension.
//!
//! Homing path: an endstop's timer reads its pin through the board; a confirmed trigger calls
//! [`Mcu::trsync_trigger`], which (once per `trsync_start`) stops every stepper attached with
//! `stepper_stop_on_trigger` — timer disarmed, queued moves given back to the pool, position
//! left at the last executed step, later `queue_step`s ignored until `reset_step_clock` —
//! records the trigger on the board and sends `trsync_state` at once. The trsync's own timer sends the periodic reports and expires it (self-trigger with
//! its `expire_reason`) when `trsync_set_timeout` was not renewed in time.
//!
//! A periodic timer re-armed more than `late_limit` ticks in the past shuts the MCU down with
//! "Rescheduled timer in the past" (off when `late_limit` is 0).

use super::analog_in::{AnalogEvent, AnalogIn, AnalogQuery};
use super::board::{Board, TriggerSource};
use super::commands::*;
use super::constants::{reason, ADC_TEMPERATURE_PIN};
use super::counter::Counter;
use super::digital_out::{DigitalOut, DigitalOutConfig, DigitalOutError};
use super::endstop::{Endstop, EndstopEvent, HomeParams};
use super::mcu::{Mcu, Object};
use super::pwm_out::{PwmOut, PwmOutConfig, PwmOutError};
use super::thermocouple::{Chip, Thermocouple, ThermocoupleEvent, ThermocoupleQuery};
use super::trsync::Trsync;
use links::proto::format::Value;
use rt_core::WireClock;

impl<B: Board, const OIDS: usize, const MOVES: usize> Mcu<B, OIDS, MOVES> {
    /// Runs one command of the objects in this module.
    pub(super) fn handle_object(&mut self, cmd: Cmd, args: &[Value<'_>], now: WireClock) {
        let arg = |i: usize| args.get(i).map_or(0, Value::int);
        let oid = arg(0);
        let clock = |i: usize| WireClock(arg(i) as u32);
        match cmd {
            Cmd::StepperStopOnTrigger => {
                if !matches!(self.object(arg(1)), Some(Object::Trsync(_))) {
                    return self.shutdown(reason::INVALID_OID, now);
                }
                match self.object(oid) {
                    Some(Object::Stepper(s)) => s.set_stop_on(Some(arg(1) as u8)),
                    _ => self.shutdown(reason::INVALID_OID, now),
                }
            }
            Cmd::ConfigEndstop => {
                let (pin, pull_up) = (arg(1) as u8, arg(2) != 0);
                self.board.config_input(pin, pull_up);
                self.config_object(oid, Object::Endstop(Endstop::new(pin, pull_up)), now);
            }
            Cmd::EndstopHome => {
                let p = HomeParams {
                    clock: clock(1),
                    sample_ticks: arg(2) as u32,
                    sample_count: arg(3) as u8,
                    rest_ticks: arg(4) as u32,
                    pin_value: arg(5) != 0,
                    trsync_oid: arg(6) as u8,
                    trigger_reason: arg(7) as u8,
                };
                let cancel = p.sample_count == 0 || p.clock.0 == 0;
                if !cancel && !matches!(self.object(arg(6)), Some(Object::Trsync(_))) {
                    return self.shutdown(reason::INVALID_OID, now);
                }
                let armed = match self.object(oid) {
                    Some(Object::Endstop(e)) => e.home(p),
                    _ => return self.shutdown(reason::INVALID_OID, now),
                };
                self.arm_or_disarm(oid as u8, armed);
            }
            Cmd::EndstopQueryState => {
                let Some(Object::Endstop(e)) = self.object(oid) else {
                    return self.shutdown(reason::INVALID_OID, now);
                };
                let (homing, next, pin) = (e.homing(), e.next_clock(), e.pin);
                let level = self.board.read_pin(pin, now);
                let args = [
                    Value::Int(oid),
                    Value::Int(homing as i64),
                    Value::Int(next.0 as i64),
                    Value::Int(level as i64),
                ];
                self.respond(ID_ENDSTOP_STATE, FMT_ENDSTOP_STATE, &args);
            }
            Cmd::ConfigTrsync => {
                self.config_object(oid, Object::Trsync(Trsync::new()), now);
            }
            Cmd::TrsyncStart => {
                let Some(Object::Trsync(t)) = self.object(oid) else {
                    return self.shutdown(reason::INVALID_OID, now);
                };
                t.start(clock(1), arg(2) as u32, arg(3) as u8);
                let wake = t.next_wake();
                self.detach_steppers(oid as u8);
                self.arm_or_disarm(oid as u8, wake);
            }
            Cmd::TrsyncSetTimeout => {
                let Some(Object::Trsync(t)) = self.object(oid) else {
                    return self.shutdown(reason::INVALID_OID, now);
                };
                t.set_timeout(clock(1));
                let wake = t.next_wake();
                self.arm_or_disarm(oid as u8, wake);
            }
            Cmd::TrsyncTrigger => {
                if !matches!(self.object(oid), Some(Object::Trsync(_))) {
                    return self.shutdown(reason::INVALID_OID, now);
                }
                // One report answers the command (from the trigger, or of the earlier
                // trigger), then the trsync is silent until the next trsync_start.
                let triggered = self.trsync_trigger(oid as u8, arg(1) as u8, now);
                if let Some(Object::Trsync(t)) = self.object(oid) {
                    t.stop();
                }
                self.arm_or_disarm(oid as u8, None);
                if !triggered {
                    self.report_trsync(oid as u8, now);
                }
            }
            Cmd::ConfigDigitalOut => {
                let config = DigitalOutConfig {
                    pin: arg(1) as u8,
                    value: arg(2) != 0,
                    default_value: arg(3) != 0,
                    max_duration: arg(4) as u32,
                };
                if self.config_object(oid, Object::DigitalOut(DigitalOut::new(config)), now) {
                    self.board.set_pin(config.pin, config.value, now);
                }
            }
            Cmd::SetDigitalOutPwmCycle => match self.object(oid) {
                Some(Object::DigitalOut(d)) => d.set_cycle(arg(1) as u32),
                _ => self.shutdown(reason::INVALID_OID, now),
            },
            Cmd::QueueDigitalOut => {
                let Some(Object::DigitalOut(d)) =
                    self.objects.get_mut(usize::try_from(oid).unwrap_or(usize::MAX))
                else {
                    return self.shutdown(reason::INVALID_OID, now);
                };
                match d.queue(&mut self.updates, clock(1), arg(2) as u32, now) {
                    Ok(()) => {
                        let wake = d.next_wake(&self.updates);
                        self.arm_or_disarm(oid as u8, wake);
                    }
                    Err(e) => self.digital_out_fault(e, now),
                }
            }
            Cmd::UpdateDigitalOut => {
                let Some(Object::DigitalOut(d)) =
                    self.objects.get_mut(usize::try_from(oid).unwrap_or(usize::MAX))
                else {
                    return self.shutdown(reason::INVALID_OID, now);
                };
                let level = d.update(&mut self.updates, arg(1) != 0, now);
                let (pin, wake) = (d.config().pin, d.next_wake(&self.updates));
                self.board.set_pin(pin, level, now);
                self.arm_or_disarm(oid as u8, wake);
            }
            Cmd::SetDigitalOut => self.board.set_pin(arg(0) as u8, arg(1) != 0, now),
            Cmd::ConfigPwmOut => {
                let config = PwmOutConfig {
                    pin: arg(1) as u8,
                    cycle_ticks: arg(2) as u32,
                    value: arg(3) as u16,
                    default_value: arg(4) as u16,
                    max_duration: arg(5) as u32,
                };
                if self.config_object(oid, Object::PwmOut(PwmOut::new(config)), now) {
                    self.board
                        .set_pwm(config.pin, config.cycle_ticks, config.value, now);
                }
            }
            Cmd::QueuePwmOut => {
                let Some(Object::PwmOut(p)) = self.object(oid) else {
                    return self.shutdown(reason::INVALID_OID, now);
                };
                match p.queue(clock(1), arg(2) as u16, now) {
                    Ok(()) => {
                        let wake = p.next_wake();
                        self.arm_or_disarm(oid as u8, wake);
                    }
                    Err(e) => self.pwm_out_fault(e, now),
                }
            }
            Cmd::SetPwmOut => self
                .board
                .set_pwm(arg(0) as u8, arg(1) as u32, arg(2) as u16, now),
            Cmd::ConfigCounter => {
                let (pin, pull_up) = (arg(1) as u8, arg(2) != 0);
                self.board.config_input(pin, pull_up);
                self.config_object(oid, Object::Counter(Counter::new(pin)), now);
            }
            Cmd::QueryCounter => {
                let armed = match self.object(oid) {
                    Some(Object::Counter(c)) => c.query(clock(1), arg(2) as u32, arg(3) as u32),
                    _ => return self.shutdown(reason::INVALID_OID, now),
                };
                self.arm_or_disarm(oid as u8, armed);
            }
            Cmd::ConfigAnalogIn => {
                self.config_object(oid, Object::AnalogIn(AnalogIn::new(arg(1) as u32)), now);
            }
            Cmd::QueryAnalogIn => {
                let q = AnalogQuery {
                    clock: clock(1),
                    sample_ticks: arg(2) as u32,
                    sample_count: arg(3) as u8,
                    rest_ticks: arg(4) as u32,
                    min_value: arg(5) as u16,
                    max_value: arg(6) as u16,
                    range_check_count: arg(7) as u8,
                };
                let armed = match self.object(oid) {
                    Some(Object::AnalogIn(a)) => a.query(q),
                    _ => return self.shutdown(reason::INVALID_OID, now),
                };
                self.arm_or_disarm(oid as u8, armed);
            }
            Cmd::ConfigThermocouple => {
                let Some(chip) = Chip::from_number(arg(2)) else {
                    return self.shutdown(reason::INVALID_THERMOCOUPLE_TYPE, now);
                };
                if !matches!(self.object(arg(1)), Some(Object::Spi(_))) {
                    return self.shutdown(reason::INVALID_OID, now);
                }
                let t = Thermocouple::new(arg(1) as u8, chip);
                self.config_object(oid, Object::Thermocouple(t), now);
            }
            Cmd::QueryThermocouple => {
                let q = ThermocoupleQuery {
                    clock: clock(1),
                    rest_ticks: arg(2) as u32,
                    min_value: arg(3) as u32,
                    max_value: arg(4) as u32,
                    max_invalid_count: arg(5) as u8,
                };
                let armed = match self.object(oid) {
                    Some(Object::Thermocouple(t)) => t.query(q),
                    _ => return self.shutdown(reason::INVALID_OID, now),
                };
                self.arm_or_disarm(oid as u8, armed);
            }
            Cmd::CadenceGetLateness => {
                let l = self.board.lateness();
                let args = [l.count, l.p50, l.p99, l.p999, l.max].map(|v| Value::Int(v as i64));
                self.respond(ID_CADENCE_LATENESS, FMT_CADENCE_LATENESS, &args);
            }
            _ => {}
        }
    }

    /// The timer of object `oid` (not a stepper) fired at `now` for the event at `at`.
    pub(super) fn object_timer(&mut self, oid: u8, at: WireClock, now: WireClock) {
        let Some(obj) = self.objects.get_mut(oid as usize) else {
            return;
        };
        match obj {
            Object::Endstop(e) => {
                let level = self.board.read_pin(e.pin, at);
                match e.event(at, level) {
                    EndstopEvent::Rearm(t) => self.rearm(oid, t, now),
                    EndstopEvent::Trigger { trsync_oid, reason } => {
                        self.board.triggered(TriggerSource::Endstop, oid, reason, at);
                        self.trsync_trigger(trsync_oid, reason, at);
                    }
                    EndstopEvent::Idle => {}
                }
            }
            Object::Trsync(t) => {
                let ev = t.event(at);
                if let Some(r) = ev.expired {
                    self.trsync_trigger(oid, r, at);
                } else if ev.report {
                    // The clock of the report is when it is made, as on Klipper's MCU: it
                    // tells the host the MCU was alive then, and the host extends the other
                    // MCUs' timeouts from it (a late timer reporting its due time would
                    // shorten them by its lateness).
                    self.report_trsync(oid, now);
                }
                if let Some(Object::Trsync(t)) = self.objects.get(oid as usize) {
                    if let Some(w) = t.next_wake() {
                        self.rearm(oid, w, now);
                    }
                }
            }
            Object::DigitalOut(d) => match d.event(&mut self.updates, at) {
                Ok(change) => {
                    let (pin, wake) = (d.config().pin, d.next_wake(&self.updates));
                    if let Some(level) = change {
                        self.board.set_pin(pin, level, at);
                    }
                    if let Some(w) = wake {
                        self.rearm(oid, w, now);
                    }
                }
                Err(e) => self.digital_out_fault(e, now),
            },
            Object::Counter(c) => {
                let level = self.board.read_pin(c.pin, at);
                let (next, report) = c.event(at, level);
                if let Some(r) = report {
                    let args = [
                        Value::Int(oid as i64),
                        Value::Int(r.next_clock.0 as i64),
                        Value::Int(r.count as i64),
                        Value::Int(r.count_clock.0 as i64),
                    ];
                    self.respond(ID_COUNTER_STATE, FMT_COUNTER_STATE, &args);
                }
                if let Some(w) = next {
                    self.rearm(oid, w, now);
                }
            }
            Object::PwmOut(p) => match p.event(at) {
                Ok(change) => {
                    let (pin, cycle, wake) = (p.config().pin, p.config().cycle_ticks, p.next_wake());
                    if let Some(value) = change {
                        self.board.set_pwm(pin, cycle, value, at);
                    }
                    if let Some(w) = wake {
                        self.rearm(oid, w, now);
                    }
                }
                Err(e) => self.pwm_out_fault(e, now),
            },
            Object::AnalogIn(a) => {
                let value = match u8::try_from(a.pin) {
                    Ok(pin) => self.board.read_adc(pin),
                    Err(_) if a.pin == ADC_TEMPERATURE_PIN => self.board.read_mcu_temperature(),
                    Err(_) => 0,
                };
                match a.event(at, value) {
                    AnalogEvent::Rearm(t) => self.rearm(oid, t, now),
                    AnalogEvent::Report { next_clock, value } => {
                        let args = [
                            Value::Int(oid as i64),
                            Value::Int(next_clock.0 as i64),
                            Value::Int(value as i64),
                        ];
                        self.respond(ID_ANALOG_IN_STATE, FMT_ANALOG_IN_STATE, &args);
                        self.rearm(oid, next_clock, now);
                    }
                    AnalogEvent::OutOfRange => self.shutdown(reason::ADC_OUT_OF_RANGE, now),
                    AnalogEvent::Idle => {}
                }
            }
            Object::Thermocouple(t) => {
                let (chip, spi_oid) = (t.chip, t.spi_oid);
                let Some(Object::Spi(dev)) = self.objects.get(usize::from(spi_oid)).cloned() else {
                    return self.shutdown(reason::INVALID_OID, now);
                };
                let (value, fault) = chip.read(&mut self.board, dev.cs_pin);
                let Some(Object::Thermocouple(t)) = self.objects.get_mut(oid as usize) else {
                    return;
                };
                let (next_clock, value, fault, failed) = match t.event(value, fault) {
                    ThermocoupleEvent::Report {
                        next_clock,
                        value,
                        fault,
                    } => (next_clock, value, fault, false),
                    ThermocoupleEvent::Fault {
                        next_clock,
                        value,
                        fault,
                    } => (next_clock, value, fault, true),
                    ThermocoupleEvent::Idle => return,
                };
                let args = [
                    Value::Int(oid as i64),
                    Value::Int(next_clock.0 as i64),
                    Value::Int(value as i64),
                    Value::Int(fault as i64),
                ];
                self.respond(ID_THERMOCOUPLE_RESULT, FMT_THERMOCOUPLE_RESULT, &args);
                if failed {
                    return self.shutdown(reason::THERMOCOUPLE_FAULT, now);
                }
                self.rearm(oid, next_clock, now);
            }
            Object::Stepper(_) | Object::Free | Object::TmcUart(_) | Object::Spi(_) => {}
        }
    }

    /// Triggers trsync `oid` at `clock` with `reason`: stops its steppers and reports at once.
    /// Returns false if it could not trigger (not a trsync, not started or already triggered).
    pub(super) fn trsync_trigger(&mut self, oid: u8, reason: u8, clock: WireClock) -> bool {
        let Some(Object::Trsync(t)) = self.objects.get_mut(oid as usize) else {
            return false;
        };
        if !t.trigger(reason, clock) {
            return false;
        }
        let wake = t.next_wake();
        for (i, obj) in self.objects.iter_mut().enumerate() {
            if let Object::Stepper(s) = obj {
                if s.stop_on() == Some(oid) {
                    s.discard(&mut self.pool);
                    self.sched.disarm(i as u8);
                }
            }
        }
        self.arm_or_disarm(oid, wake);
        self.board.triggered(TriggerSource::Trsync, oid, reason, clock);
        self.report_trsync(oid, clock);
        true
    }

    /// Sends `trsync_state` for trsync `oid` as of `at`.
    fn report_trsync(&mut self, oid: u8, at: WireClock) {
        let Some(Object::Trsync(t)) = self.objects.get(oid as usize) else {
            return;
        };
        let args = [
            Value::Int(oid as i64),
            Value::Int(t.can_trigger() as i64),
            Value::Int(t.trigger_reason() as i64),
            Value::Int(t.report_clock(at).0 as i64),
        ];
        self.respond(ID_TRSYNC_STATE, FMT_TRSYNC_STATE, &args);
    }

    /// `trsync_start` forgets the steppers attached to the previous homing.
    fn detach_steppers(&mut self, trsync_oid: u8) {
        for obj in self.objects.iter_mut() {
            if let Object::Stepper(s) = obj {
                if s.stop_on() == Some(trsync_oid) {
                    s.set_stop_on(None);
                }
            }
        }
    }

    fn digital_out_fault(&mut self, e: DigitalOutError, now: WireClock) {
        let r = match e {
            DigitalOutError::Missed => reason::MISSED_DIGITAL_OUT,
            DigitalOutError::ExceedsMaxDuration => reason::EXCEEDS_MAX_DURATION,
            DigitalOutError::QueueFull => reason::MOVE_QUEUE_OVERFLOW,
        };
        self.shutdown(r, now);
    }

    fn pwm_out_fault(&mut self, e: PwmOutError, now: WireClock) {
        let r = match e {
            PwmOutError::Missed => reason::MISSED_PWM,
            PwmOutError::ExceedsMaxDuration => reason::PWM_EXCEEDS_MAX_DURATION,
            PwmOutError::QueueFull => reason::MOVE_QUEUE_OVERFLOW,
        };
        self.shutdown(r, now);
    }

    fn arm_or_disarm(&mut self, oid: u8, at: Option<WireClock>) {
        match at {
            Some(t) => {
                self.sched.arm(oid, t);
            }
            None => self.sched.disarm(oid),
        }
    }

    /// Re-arms a periodic timer, shutting down if it is already more than `late_limit` late.
    fn rearm(&mut self, oid: u8, at: WireClock, now: WireClock) {
        if self.late_limit > 0 && at.add(self.late_limit).is_before(now) {
            return self.shutdown(reason::RESCHEDULED_PAST, now);
        }
        self.sched.arm(oid, at);
    }

    /// The object in slot `oid`.
    pub(super) fn object(&mut self, oid: i64) -> Option<&mut Object> {
        self.objects.get_mut(usize::try_from(oid).ok()?)
    }
}
