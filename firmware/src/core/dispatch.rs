//! The command dispatcher: decodes every message of a received payload through the
//! [`MESSAGES`] table and runs its handler.
//!
//! A payload is `id params id params …`; each id is looked up by position in the table. An id
//! that is not a command stops the payload with shutdown "Invalid command", parameters that do
//! not decode stop it with "Command parser error" (the rest of the payload cannot be framed).
//! While shut down, commands not marked `in_shutdown` get `is_shutdown` instead of running.

use super::board::Board;
use super::commands::*;
use super::constants::{reason, static_string_id};
use super::mcu::{Mcu, Object};
use super::stepper::{Stepper, StepperConfig, StepperError};
use links::proto::format::{decode_params, Value};
use links::proto::vlq;
use rt_core::WireClock;

/// Largest `identify_response` data chunk: a block payload minus the message id (1 byte),
/// the offset (≤ 5 bytes) and the data length byte.
pub const IDENTIFY_CHUNK_MAX: usize = links::proto::MESSAGE_PAYLOAD_MAX - 7;

impl<B: Board, const OIDS: usize, const MOVES: usize> Mcu<B, OIDS, MOVES> {
    /// Runs every message of one in-order block payload.
    pub(super) fn dispatch(&mut self, payload: &[u8], now: WireClock) {
        let mut pos = 0;
        while let Some(rest) = payload.get(pos..).filter(|r| !r.is_empty()) {
            let Some((id, used)) = vlq::decode(rest) else {
                return self.shutdown(reason::PARSER_ERROR, now);
            };
            let Some(&MessageDef {
                format,
                kind: Kind::Command { handler, in_shutdown },
            }) = MESSAGES.get(id as usize)
            else {
                return self.shutdown(reason::INVALID_COMMAND, now);
            };
            let mut vals = [Value::Int(0); MAX_PARAMS];
            let params = rest.get(used..).unwrap_or(&[]);
            let Ok((count, params_len)) = decode_params(format, params, &mut vals) else {
                return self.shutdown(reason::PARSER_ERROR, now);
            };
            pos += used + params_len;
            match self.shutdown_reason {
                Some(r) if !in_shutdown => {
                    let id = static_string_id(r);
                    self.respond(ID_IS_SHUTDOWN, FMT_IS_SHUTDOWN, &[Value::Int(id as i64)]);
                }
                _ => self.handle(handler, &vals[..count], now),
            }
        }
    }

    fn handle(&mut self, cmd: Cmd, args: &[Value<'_>], now: WireClock) {
        let arg = |i: usize| args.get(i).map_or(0, Value::int);
        match cmd {
            Cmd::Identify => self.identify(arg(0), arg(1)),
            Cmd::GetUptime => {
                let up = self.uptime();
                let args = [Value::Int((up >> 32) as i64), Value::Int(up as u32 as i64)];
                self.respond(ID_UPTIME, FMT_UPTIME, &args);
            }
            Cmd::GetClock => self.respond(ID_CLOCK, FMT_CLOCK, &[Value::Int(now.0 as i64)]),
            Cmd::GetConfig => {
                let args = [
                    Value::Int(self.is_config as i64),
                    Value::Int(self.config_crc as i64),
                    Value::Int(self.shutdown_reason.is_some() as i64),
                    Value::Int(self.move_count() as i64),
                ];
                self.respond(ID_CONFIG, FMT_CONFIG, &args);
            }
            Cmd::AllocateOids => self.allocate_oids(arg(0), now),
            Cmd::FinalizeConfig => {
                if self.is_config {
                    return self.shutdown(reason::ALREADY_CONFIGURED, now);
                }
                self.is_config = true;
                self.config_crc = arg(0) as u32;
            }
            Cmd::EmergencyStop => self.shutdown(reason::COMMAND_REQUEST, now),
            Cmd::ClearShutdown => self.shutdown_reason = None,
            Cmd::ConfigReset => self.config_reset(now),
            Cmd::ConfigStepper => {
                let config = StepperConfig {
                    step_pin: arg(1) as u8,
                    dir_pin: arg(2) as u8,
                    invert_step: arg(3) != 0,
                    step_pulse_ticks: arg(4) as u32,
                };
                self.config_stepper(arg(0), config, now);
            }
            Cmd::QueueStep => self.queue_step(arg(0), arg(1) as u32, arg(2) as u16, arg(3) as i16, now),
            Cmd::SetNextStepDir => {
                if let Some(s) = self.stepper(arg(0)) {
                    s.set_next_dir(arg(1) != 0);
                } else {
                    self.shutdown(reason::INVALID_OID, now);
                }
            }
            Cmd::ResetStepClock => {
                let clock = WireClock(arg(1) as u32);
                match self.stepper(arg(0)).map(|s| s.reset_clock(clock)) {
                    Some(Ok(())) => {}
                    Some(Err(e)) => self.stepper_fault(e, now),
                    None => self.shutdown(reason::INVALID_OID, now),
                }
            }
            Cmd::StepperStopOnTrigger
            | Cmd::ConfigEndstop
            | Cmd::EndstopHome
            | Cmd::EndstopQueryState
            | Cmd::ConfigTrsync
            | Cmd::TrsyncStart
            | Cmd::TrsyncSetTimeout
            | Cmd::TrsyncTrigger
            | Cmd::ConfigDigitalOut
            | Cmd::SetDigitalOutPwmCycle
            | Cmd::QueueDigitalOut
            | Cmd::UpdateDigitalOut
            | Cmd::SetDigitalOut
            | Cmd::ConfigPwmOut
            | Cmd::QueuePwmOut
            | Cmd::SetPwmOut
            | Cmd::ConfigCounter
            | Cmd::QueryCounter
            | Cmd::ConfigAnalogIn
            | Cmd::QueryAnalogIn
            | Cmd::ConfigThermocouple
            | Cmd::QueryThermocouple
            | Cmd::CadenceGetLateness => self.handle_object(cmd, args, now),
            Cmd::ConfigTmcuart
            | Cmd::TmcuartSend
            | Cmd::ConfigSpi
            | Cmd::SpiSetBus
            | Cmd::SpiSetSwBus
            | Cmd::SpiTransfer
            | Cmd::SpiSend => self.handle_bus(cmd, args, now),
            Cmd::StepperGetPosition => {
                let oid = arg(0);
                match self.stepper(oid).map(|s| s.position()) {
                    Some(pos) => {
                        let args = [Value::Int(oid), Value::Int(pos as i64)];
                        self.respond(ID_STEPPER_POSITION, FMT_STEPPER_POSITION, &args);
                    }
                    None => self.shutdown(reason::INVALID_OID, now),
                }
            }
        }
    }

    /// `identify offset count`: the dictionary bytes `[offset, offset+count)`, clipped to its
    /// end (empty past it) and to one block.
    fn identify(&mut self, offset: i64, count: i64) {
        let len = self.dictionary.len();
        let start = usize::try_from(offset).unwrap_or(usize::MAX).min(len);
        let count = usize::try_from(count).unwrap_or(0).min(IDENTIFY_CHUNK_MAX);
        let end = start.saturating_add(count).min(len);
        let data = self.dictionary.get(start..end).unwrap_or(&[]);
        let args = [Value::Int(offset), Value::Bytes(data)];
        self.respond(ID_IDENTIFY_RESPONSE, links::proto::FMT_IDENTIFY_RESPONSE, &args);
    }

    fn allocate_oids(&mut self, count: i64, now: WireClock) {
        if self.oid_count.is_some() {
            return self.shutdown(reason::OIDS_ALREADY_ALLOCATED, now);
        }
        if self.is_config {
            return self.shutdown(reason::ALREADY_CONFIGURED, now);
        }
        match u8::try_from(count) {
            Ok(n) if (n as usize) <= OIDS => self.oid_count = Some(n),
            _ => self.shutdown(reason::TOO_MANY_OIDS, now),
        }
    }

    fn config_stepper(&mut self, oid: i64, config: StepperConfig, now: WireClock) {
        if self.config_object(oid, Object::Stepper(Stepper::new(config)), now) {
            self.board.config_stepper(oid as u8, &config);
        }
    }

    /// Puts `obj` in slot `oid` during configuration; false (after a shutdown) if the oid is not
    /// allocated, already configured, or configuration is over.
    pub(super) fn config_object(&mut self, oid: i64, obj: Object, now: WireClock) -> bool {
        if self.is_config {
            self.shutdown(reason::ALREADY_CONFIGURED, now);
            return false;
        }
        let allocated = self.oid_count.unwrap_or(0) as i64;
        let slot = usize::try_from(oid).ok().filter(|_| oid < allocated);
        match slot.and_then(|i| self.objects.get_mut(i)) {
            Some(o @ Object::Free) => {
                *o = obj;
                true
            }
            Some(_) => {
                self.shutdown(reason::CANT_ASSIGN_OID, now);
                false
            }
            None => {
                self.shutdown(reason::INVALID_OID, now);
                false
            }
        }
    }

    fn queue_step(&mut self, oid: i64, interval: u32, count: u16, add: i16, now: WireClock) {
        let Some(slot) = usize::try_from(oid).ok() else {
            return self.shutdown(reason::INVALID_OID, now);
        };
        let result = match self.objects.get_mut(slot) {
            Some(Object::Stepper(s)) => {
                // A stepper stopped by a trigger drops the move (not recorded as received).
                if count > 0 && !s.needs_reset() {
                    self.board
                        .queue_step_received(oid as u8, s.next_first_clock(interval), now);
                }
                s.queue_step(&mut self.pool, interval, count, add, now)
            }
            _ => return self.shutdown(reason::INVALID_OID, now),
        };
        match result {
            Ok(q) => {
                if let Some(at) = q.arm_at {
                    self.sched.arm(oid as u8, at);
                }
            }
            Err(e) => self.stepper_fault(e, now),
        }
    }

    fn stepper_fault(&mut self, e: StepperError, now: WireClock) {
        let r = match e {
            StepperError::InvalidCount => reason::INVALID_COUNT,
            StepperError::TimerTooClose => reason::TIMER_TOO_CLOSE,
            StepperError::QueueOverflow => reason::MOVE_QUEUE_OVERFLOW,
            StepperError::ResetWhileActive => reason::RESET_WHILE_ACTIVE,
        };
        self.shutdown(r, now);
    }

    fn stepper(&mut self, oid: i64) -> Option<&mut Stepper> {
        match self.objects.get_mut(usize::try_from(oid).ok()?) {
            Some(Object::Stepper(s)) => Some(s),
            _ => None,
        }
    }
}
