//! The dictionary's static data besides messages: shutdown reasons (`static_string_id`),
//! the pin enumeration and the `config` constants.
//!
//! A shutdown reason travels as its index in [`SHUTDOWN_REASONS`]; the host maps it back to
//! the text through the `static_string_id` enumeration. Pins are named by [`Chip`]: the
//! simulator's ports A..L of 8 pins each (numbered `8·port + bit`), a Cortex-M board's as its
//! chip names them (STM32: ports of 16), published as Klipper range enumerations
//! `"PA0": [0, 8]`.

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
    /// A `queue_digital_out` further than `max_duration` after the previous update, which left
    /// the pin away from its default.
    pub const EXCEEDS_MAX_DURATION: &str = "Scheduled digital out event will exceed max_duration";
    /// An analog input out of its range for `range_check_count` rounds.
    pub const ADC_OUT_OF_RANGE: &str = "ADC out of range";
    /// `config_reset` while the MCU is not shut down.
    pub const CONFIG_RESET_NOT_SHUTDOWN: &str = "config_reset only available when shutdown";
    /// A reason not in the table (never sent by this firmware; kept so lookups cannot fail).
    pub const UNKNOWN: &str = "Unknown shutdown reason";
    pub const TMCUART_TOO_LARGE: &str = "tmcuart data too large";
    pub const SPI_TOO_LARGE: &str = "spi data too large";
    /// A hardware PWM change scheduled in the past, or `max_duration` passed without one.
    pub const MISSED_PWM: &str = "Missed scheduling of next hard pwm event";
    /// A `queue_pwm_out` further than `max_duration` after the change away from the default.
    pub const PWM_EXCEEDS_MAX_DURATION: &str = "Scheduled pwm event will exceed max_duration";
    /// An SPI temperature chip faulted or read out of range `max_invalid_count` times in a row.
    pub const THERMOCOUPLE_FAULT: &str = "Thermocouple reader fault";
    /// `config_thermocouple` with a chip type that is not in the enumeration.
    pub const INVALID_THERMOCOUPLE_TYPE: &str = "Invalid thermocouple chip type";
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
    reason::EXCEEDS_MAX_DURATION,
    reason::TMCUART_TOO_LARGE,
    reason::SPI_TOO_LARGE,
    reason::MISSED_PWM,
    reason::PWM_EXCEEDS_MAX_DURATION,
    reason::THERMOCOUPLE_FAULT,
    reason::INVALID_THERMOCOUPLE_TYPE,
];

/// The `static_string_id` of `reason` (0, "Unknown shutdown reason", if it is not listed).
pub fn static_string_id(reason: &str) -> u16 {
    SHUTDOWN_REASONS.iter().position(|&r| r == reason).unwrap_or(0) as u16
}

/// What the dictionary says about the chip a target runs on: its `MCU` name and its pins.
/// Pin `n` is bit `n % pins_per_port` of port `ports[n / pins_per_port]`, named `P<port><bit>`.
/// No ports: the simulator, whose pins answer to every board family's names
/// ([`links::pinmap`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Chip {
    /// The dictionary's `MCU` constant.
    pub mcu: &'static str,
    /// Port letters, in pin-number order; empty for the simulator's [`links::pinmap`] names.
    pub ports: &'static [u8],
    /// Pins per port.
    pub pins_per_port: u8,
}

impl Chip {
    /// Port index and bit of pin `pin`, if the chip has it (never for the simulator, whose
    /// pins are only numbers).
    pub fn port_bit(&self, pin: u8) -> Option<(usize, u8)> {
        let port = (pin / self.pins_per_port.max(1)) as usize;
        (port < self.ports.len()).then_some((port, pin % self.pins_per_port.max(1)))
    }
}

/// The Linux-process target (the simulator): every board family's pin names.
pub const SIM_CHIP: Chip = Chip {
    mcu: "linux-sim",
    ports: &[],
    pins_per_port: 0,
};

/// A `config` constant's value.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConstValue {
    /// A number.
    Int(i64),
    /// A string.
    Str(&'static str),
}

/// The `config` constants other than `CLOCK_FREQ` (set at start-up) and `MCU` (the target's
/// [`Chip::mcu`]).
pub const CONSTANTS: &[(&str, ConstValue)] = &[
    ("STATS_SUMSQ_BASE", ConstValue::Int(STATS_SUMSQ_BASE as i64)),
    ("RECEIVE_WINDOW", ConstValue::Int(RECEIVE_WINDOW as i64)),
    ("SERIAL_BAUD", ConstValue::Int(250_000)),
    ("ADC_MAX", ConstValue::Int(4095)),
    ("PWM_MAX", ConstValue::Int(PWM_MAX as i64)),
];

/// The pin number of the MCU's own temperature sensor (Klipper's `ADC_TEMPERATURE` pin name):
/// above every GPIO number (pins travel as `%c` elsewhere, so no GPIO can reach it), read by
/// `config_analog_in` (whose `pin` is `%u`) through [`Board::read_mcu_temperature`].
///
/// [`Board::read_mcu_temperature`]: super::board::Board::read_mcu_temperature
pub const ADC_TEMPERATURE_PIN: u32 = 256;

/// The largest hardware PWM duty (`PWM_MAX`): `value / PWM_MAX` of `queue_pwm_out`.
pub const PWM_MAX: u16 = 255;

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

    #[test]
    fn chip_pins_split_into_port_and_bit() {
        let stm32 = Chip {
            mcu: "stm32f405",
            ports: b"ABCDEFGHI",
            pins_per_port: 16,
        };
        assert_eq!(stm32.port_bit(0), Some((0, 0)));
        assert_eq!(stm32.port_bit(24), Some((1, 8)));
        assert_eq!(stm32.port_bit(143), Some((8, 15)));
        assert_eq!(stm32.port_bit(144), None);
        assert_eq!(SIM_CHIP.port_bit(95), None);
    }
}
