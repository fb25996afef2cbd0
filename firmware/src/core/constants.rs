//! The dictionary's static data besides messages: shutdown reasons (`static_string_id`),
//! the pin enumeration and the `config` constants.
//!
//! A shutdown reason travels as its index in [`SHUTDOWN_REASONS`]; the host maps it back to
//! the text through the `static_string_id` enumeration. Pins are ports A..L of 8 pins each,
//! numbered `8·port + bit`, published as Klipper range enumerations `"PA0": [0, 8]`.

/// Shutdown reasons. Every `&'static str` passed to `shutdown` must be one of these.
pub mod reason {
    /// A move's first step was already in the past when it was loaded.
    pub const TIMER_TOO_CLOSE: &str = "Timer too close";
    /// `queue_step` with count 0.
    pub const INVALID_COUNT: &str = "Invalid count parameter";
    /// The move pool is full.
    pub const MOVE_QUEUE_OVERFLOW: &str = "Move queue overflow";
    /// `reset_step_clock` on a busy stepper.
    pub const RESET_WHILE_ACTIVE: &str = "Can't reset time when stepper active";
    /// An oid that is not allocated or not of the right type.
    pub const INVALID_OID: &str = "Invalid oid";
    /// `config_*` for an oid that is already configured.
    pub const CANT_ASSIGN_OID: &str = "Can't assign oid";
    /// A second `allocate_oids`.
    pub const OIDS_ALREADY_ALLOCATED: &str = "oids already allocated";
    /// `allocate_oids` beyond the firmware's capacity.
    pub const TOO_MANY_OIDS: &str = "Too many oids";
    /// A configuration command after `finalize_config`.
    pub const ALREADY_CONFIGURED: &str = "Already configured";
    /// A message whose parameters do not decode.
    pub const PARSER_ERROR: &str = "Command parser error";
    /// A message id that is not a command.
    pub const INVALID_COMMAND: &str = "Invalid command";
    /// `emergency_stop`.
    pub const COMMAND_REQUEST: &str = "Command request";
    /// A periodic timer's next wake was already far in the past (the MCU fell behind).
    pub const RESCHEDULED_PAST: &str = "Rescheduled timer in the past";
    /// A step ran far later than scheduled (the MCU fell behind).
    pub const STEPPER_TOO_FAR_IN_PAST: &str = "Stepper too far in past";
    /// A digital out update scheduled in the past, or `max_duration` passed without an update.
    pub const MISSED_DIGITAL_OUT: &str = "Missed scheduling of next digital out event";
    /// An analog input out of its range for `range_check_count` rounds.
    pub const ADC_OUT_OF_RANGE: &str = "ADC out of range";
    /// `config_reset` while the MCU is not shut down.
    pub const CONFIG_RESET_NOT_SHUTDOWN: &str = "config_reset only available when shutdown";
    /// A reason not in the table (never sent by this firmware; kept so lookups cannot fail).
    pub const UNKNOWN: &str = "Unknown shutdown reason";
}

/// Every shutdown reason; the index is its `static_string_id`.
pub const SHUTDOWN_REASONS: &[&str] = &[
    reason::UNKNOWN,
    reason::TIMER_TOO_CLOSE,
    reason::INVALID_COUNT,
    reason::MOVE_QUEUE_OVERFLOW,
    reason::RESET_WHILE_ACTIVE,
    reason::INVALID_OID,
    reason::CANT_ASSIGN_OID,
    reason::OIDS_ALREADY_ALLOCATED,
    reason::TOO_MANY_OIDS,
    reason::ALREADY_CONFIGURED,
    reason::PARSER_ERROR,
    reason::INVALID_COMMAND,
    reason::COMMAND_REQUEST,
    reason::RESCHEDULED_PAST,
    reason::STEPPER_TOO_FAR_IN_PAST,
    reason::MISSED_DIGITAL_OUT,
    reason::ADC_OUT_OF_RANGE,
    reason::CONFIG_RESET_NOT_SHUTDOWN,
];

/// The `static_string_id` of `reason` (0, "Unknown shutdown reason", if it is not listed).
pub fn static_string_id(reason: &str) -> u16 {
    SHUTDOWN_REASONS.iter().position(|&r| r == reason).unwrap_or(0) as u16
}

/// Port letters of the pin enumeration.
pub const PIN_PORTS: &[u8] = b"ABCDEFGHIJKL";
/// Pins per port.
pub const PINS_PER_PORT: u8 = 8;

/// A `config` constant's value.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConstValue {
    /// A number.
    Int(i64),
    /// A string.
    Str(&'static str),
}

/// The `config` constants other than `CLOCK_FREQ` (which is set at start-up).
pub const CONSTANTS: &[(&str, ConstValue)] = &[
    ("MCU", ConstValue::Str("linux-sim")),
    ("STATS_SUMSQ_BASE", ConstValue::Int(STATS_SUMSQ_BASE as i64)),
    ("RECEIVE_WINDOW", ConstValue::Int(RECEIVE_WINDOW as i64)),
    ("SERIAL_BAUD", ConstValue::Int(250_000)),
    ("ADC_MAX", ConstValue::Int(4095)),
    ("PWM_MAX", ConstValue::Int(255)),
];

/// Divisor of squared loop times in `stats sumsq` (keeps the sum inside 32 bits).
pub const STATS_SUMSQ_BASE: u32 = 256;
/// Bytes the host may have in flight to this MCU (its receive buffer is at least this big).
pub const RECEIVE_WINDOW: usize = 192;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reasons_are_unique_and_found() {
        for (i, r) in SHUTDOWN_REASONS.iter().enumerate() {
            assert_eq!(static_string_id(r) as usize, i);
        }
        assert_eq!(static_string_id("no such reason"), 0);
        assert_eq!(
            SHUTDOWN_REASONS[static_string_id(reason::TIMER_TOO_CLOSE) as usize],
            "Timer too close"
        );
    }
}
