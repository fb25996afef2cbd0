//! The message table, declared once: the dispatcher and the data dictionary both come from it.
//!
//! A message's id is its position in [`MESSAGES`]; ids are shared by commands (host → MCU)
//! and responses (MCU → host), as in Klipper. Ids 0 (`identify_response`) and 1 (`identify`)
//! are fixed by the protocol; a test checks it. The host never hard-codes any other id: it
//! reads the table back from the dictionary. Response ids are found at compile time by
//! [`message_id`], so a response missing from the table is a build error, not a runtime one.

use links::proto::{FMT_IDENTIFY, FMT_IDENTIFY_RESPONSE};

/// The handler of a command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Cmd {
    /// `identify`: serve a chunk of the dictionary.
    Identify,
    /// `get_uptime`.
    GetUptime,
    /// `get_clock`.
    GetClock,
    /// `get_config`.
    GetConfig,
    /// `allocate_oids`.
    AllocateOids,
    /// `finalize_config`.
    FinalizeConfig,
    /// `emergency_stop`.
    EmergencyStop,
    /// `clear_shutdown`.
    ClearShutdown,
    /// `config_reset`.
    ConfigReset,
    /// `config_stepper`.
    ConfigStepper,
    /// `queue_step`.
    QueueStep,
    /// `set_next_step_dir`.
    SetNextStepDir,
    /// `reset_step_clock`.
    ResetStepClock,
    /// `stepper_get_position`.
    StepperGetPosition,
    /// `stepper_stop_on_trigger`.
    StepperStopOnTrigger,
    /// `config_endstop`.
    ConfigEndstop,
    /// `endstop_home`.
    EndstopHome,
    /// `endstop_query_state`.
    EndstopQueryState,
    /// `config_trsync`.
    ConfigTrsync,
    /// `trsync_start`.
    TrsyncStart,
    /// `trsync_set_timeout`.
    TrsyncSetTimeout,
    /// `trsync_trigger`.
    TrsyncTrigger,
    /// `config_digital_out`.
    ConfigDigitalOut,
    /// `set_digital_out_pwm_cycle`.
    SetDigitalOutPwmCycle,
    /// `queue_digital_out`.
    QueueDigitalOut,
    /// `update_digital_out`.
    UpdateDigitalOut,
    /// `set_digital_out` (a pin set once, no object).
    SetDigitalOut,
    /// `config_analog_in`.
    ConfigAnalogIn,
    /// `query_analog_in`.
    QueryAnalogIn,
    /// `cadence_get_lateness` (Cadence extension).
    CadenceGetLateness,
    /// `config_tmcuart`.
    ConfigTmcuart,
    /// `tmcuart_send`.
    TmcuartSend,
    /// `config_spi`.
    ConfigSpi,
    /// `spi_set_bus`.
    SpiSetBus,
    /// `spi_set_sw_bus`.
    SpiSetSwBus,
    /// `spi_transfer`.
    SpiTransfer,
    /// `spi_send`.
    SpiSend,
    /// `config_pwm_out`.
    ConfigPwmOut,
    /// `queue_pwm_out`.
    QueuePwmOut,
    /// `set_pwm_out` (a pin set once, no object).
    SetPwmOut,
    /// `config_counter`.
    ConfigCounter,
    /// `query_counter`.
    QueryCounter,
    /// `config_thermocouple`.
    ConfigThermocouple,
    /// `query_thermocouple`.
    QueryThermocouple,
}

/// Whether a table entry is a command or a response.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// Host → MCU. `in_shutdown`: still served after a shutdown (others get `is_shutdown`).
    Command { handler: Cmd, in_shutdown: bool },
    /// MCU → host.
    Response,
}

/// One message: its Klipper format string and its kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MessageDef {
    /// `name param=%x ...`
    pub format: &'static str,
    /// Command (with handler) or response.
    pub kind: Kind,
}

const fn cmd(format: &'static str, handler: Cmd, in_shutdown: bool) -> MessageDef {
    MessageDef {
        format,
        kind: Kind::Command { handler, in_shutdown },
    }
}

const fn resp(format: &'static str) -> MessageDef {
    MessageDef {
        format,
        kind: Kind::Response,
    }
}

/// `uptime` response.
pub const FMT_UPTIME: &str = "uptime high=%u clock=%u";
/// `clock` response.
pub const FMT_CLOCK: &str = "clock clock=%u";
/// `config` response.
pub const FMT_CONFIG: &str = "config is_config=%c crc=%u is_shutdown=%c move_count=%hu";
/// `shutdown` response (sent once, when the MCU shuts down).
pub const FMT_SHUTDOWN: &str = "shutdown clock=%u static_string_id=%hu";
/// `is_shutdown` response (answer to a command that needs a live MCU).
pub const FMT_IS_SHUTDOWN: &str = "is_shutdown static_string_id=%hu";
/// `starting` response.
pub const FMT_STARTING: &str = "starting";
/// Periodic `stats` response.
pub const FMT_STATS: &str = "stats count=%u sum=%u sumsq=%u";
/// `stepper_position` response.
pub const FMT_STEPPER_POSITION: &str = "stepper_position oid=%c pos=%i";

/// `endstop_state` response.
pub const FMT_ENDSTOP_STATE: &str = "endstop_state oid=%c homing=%c next_clock=%u pin_value=%c";
/// `trsync_state` response (periodic, and at once on a trigger).
pub const FMT_TRSYNC_STATE: &str = "trsync_state oid=%c can_trigger=%c trigger_reason=%c clock=%u";
/// `analog_in_state` response (after each sampling round).
pub const FMT_ANALOG_IN_STATE: &str = "analog_in_state oid=%c next_clock=%u value=%hu";
/// `cadence_lateness` response (Cadence extension): step lateness in µs of MCU time.
pub const FMT_CADENCE_LATENESS: &str = "cadence_lateness count=%u p50=%u p99=%u p999=%u max=%u";

/// `tmcuart_response` response: the bits sampled from the line after a `tmcuart_send`.
pub const FMT_TMCUART_RESPONSE: &str = "tmcuart_response oid=%c read=%*s";
/// `spi_transfer_response` response: the bytes clocked in during an `spi_transfer`.
pub const FMT_SPI_TRANSFER_RESPONSE: &str = "spi_transfer_response oid=%c response=%*s";

/// `counter_state` response: a pulse counter's count, the clock of its last change and the
/// clock of its next poll.
pub const FMT_COUNTER_STATE: &str = "counter_state oid=%c next_clock=%u count=%u count_clock=%u";

/// `thermocouple_result` response: an SPI temperature chip's raw reading and fault bits.
pub const FMT_THERMOCOUPLE_RESULT: &str = "thermocouple_result oid=%c next_clock=%u value=%u fault=%c";

/// Every message the firmware knows; the index is the message id.
pub const MESSAGES: &[MessageDef] = &[
    resp(FMT_IDENTIFY_RESPONSE),
    cmd(FMT_IDENTIFY, Cmd::Identify, true),
    cmd("get_uptime", Cmd::GetUptime, true),
    cmd("get_clock", Cmd::GetClock, true),
    cmd("get_config", Cmd::GetConfig, true),
    cmd("allocate_oids count=%c", Cmd::AllocateOids, false),
    cmd("finalize_config crc=%u", Cmd::FinalizeConfig, false),
    cmd("emergency_stop", Cmd::EmergencyStop, true),
    cmd("clear_shutdown", Cmd::ClearShutdown, true),
    cmd(
        "config_stepper oid=%c step_pin=%c dir_pin=%c invert_step=%c step_pulse_ticks=%u",
        Cmd::ConfigStepper,
        false,
    ),
    cmd(
        "queue_step oid=%c interval=%u count=%hu add=%hi",
        Cmd::QueueStep,
        false,
    ),
    cmd("set_next_step_dir oid=%c dir=%c", Cmd::SetNextStepDir, false),
    cmd("reset_step_clock oid=%c clock=%u", Cmd::ResetStepClock, false),
    cmd("stepper_get_position oid=%c", Cmd::StepperGetPosition, true),
    resp(FMT_UPTIME),
    resp(FMT_CLOCK),
    resp(FMT_CONFIG),
    resp(FMT_SHUTDOWN),
    resp(FMT_IS_SHUTDOWN),
    resp(FMT_STARTING),
    resp(FMT_STATS),
    resp(FMT_STEPPER_POSITION),
    cmd(
        "stepper_stop_on_trigger oid=%c trsync_oid=%c",
        Cmd::StepperStopOnTrigger,
        false,
    ),
    cmd(
        "config_endstop oid=%c pin=%c pull_up=%c",
        Cmd::ConfigEndstop,
        false,
    ),
    cmd(
        "endstop_home oid=%c clock=%u sample_ticks=%u sample_count=%c rest_ticks=%u pin_value=%c \
         trsync_oid=%c trigger_reason=%c",
        Cmd::EndstopHome,
        false,
    ),
    cmd("endstop_query_state oid=%c", Cmd::EndstopQueryState, true),
    cmd("config_trsync oid=%c", Cmd::ConfigTrsync, false),
    cmd(
        "trsync_start oid=%c report_clock=%u report_ticks=%u expire_reason=%c",
        Cmd::TrsyncStart,
        false,
    ),
    cmd("trsync_set_timeout oid=%c clock=%u", Cmd::TrsyncSetTimeout, false),
    cmd("trsync_trigger oid=%c reason=%c", Cmd::TrsyncTrigger, false),
    cmd(
        "config_digital_out oid=%c pin=%u value=%c default_value=%c max_duration=%u",
        Cmd::ConfigDigitalOut,
        false,
    ),
    cmd(
        "set_digital_out_pwm_cycle oid=%c cycle_ticks=%u",
        Cmd::SetDigitalOutPwmCycle,
        false,
    ),
    cmd(
        "queue_digital_out oid=%c clock=%u on_ticks=%u",
        Cmd::QueueDigitalOut,
        false,
    ),
    cmd("update_digital_out oid=%c value=%c", Cmd::UpdateDigitalOut, false),
    cmd("set_digital_out pin=%u value=%c", Cmd::SetDigitalOut, false),
    cmd("config_analog_in oid=%c pin=%u", Cmd::ConfigAnalogIn, false),
    cmd(
        "query_analog_in oid=%c clock=%u sample_ticks=%u sample_count=%c rest_ticks=%u \
         min_value=%hu max_value=%hu range_check_count=%c",
        Cmd::QueryAnalogIn,
        false,
    ),
    cmd("cadence_get_lateness", Cmd::CadenceGetLateness, true),
    resp(FMT_ENDSTOP_STATE),
    resp(FMT_TRSYNC_STATE),
    resp(FMT_ANALOG_IN_STATE),
    resp(FMT_CADENCE_LATENESS),
    cmd("config_reset", Cmd::ConfigReset, true),
    cmd(
        "config_tmcuart oid=%c rx_pin=%u pull_up=%c tx_pin=%u bit_time=%u",
        Cmd::ConfigTmcuart,
        false,
    ),
    cmd("tmcuart_send oid=%c write=%*s read=%c", Cmd::TmcuartSend, false),
    resp(FMT_TMCUART_RESPONSE),
    cmd(
        "config_spi oid=%c pin=%u cs_active_high=%c",
        Cmd::ConfigSpi,
        false,
    ),
    cmd(
        "spi_set_bus oid=%c spi_bus=%u mode=%u rate=%u",
        Cmd::SpiSetBus,
        false,
    ),
    cmd(
        "spi_set_sw_bus oid=%c miso_pin=%u mosi_pin=%u sclk_pin=%u mode=%u pulse_ticks=%u",
        Cmd::SpiSetSwBus,
        false,
    ),
    cmd("spi_transfer oid=%c data=%*s", Cmd::SpiTransfer, false),
    cmd("spi_send oid=%c data=%*s", Cmd::SpiSend, false),
    resp(FMT_SPI_TRANSFER_RESPONSE),
    cmd(
        "config_pwm_out oid=%c pin=%u cycle_ticks=%u value=%hu default_value=%hu max_duration=%u",
        Cmd::ConfigPwmOut,
        false,
    ),
    cmd("queue_pwm_out oid=%c clock=%u value=%hu", Cmd::QueuePwmOut, false),
    cmd(
        "set_pwm_out pin=%u cycle_ticks=%u value=%hu",
        Cmd::SetPwmOut,
        false,
    ),
    cmd(
        "config_counter oid=%c pin=%u pull_up=%c",
        Cmd::ConfigCounter,
        false,
    ),
    cmd(
        "query_counter oid=%c clock=%u poll_ticks=%u sample_ticks=%u",
        Cmd::QueryCounter,
        false,
    ),
    resp(FMT_COUNTER_STATE),
    cmd(
        "config_thermocouple oid=%c spi_oid=%c thermocouple_type=%c",
        Cmd::ConfigThermocouple,
        false,
    ),
    cmd(
        "query_thermocouple oid=%c clock=%u rest_ticks=%u min_value=%u max_value=%u \
         max_invalid_count=%c",
        Cmd::QueryThermocouple,
        false,
    ),
    resp(FMT_THERMOCOUPLE_RESULT),
];

/// Most parameters of any message in the table (checked by a test).
pub const MAX_PARAMS: usize = 8;

/// The id of the message whose format is exactly `format`. Evaluated at compile time for the
/// response ids below: an unknown format stops the build.
pub const fn message_id(format: &str) -> u32 {
    let mut i = 0;
    while i < MESSAGES.len() {
        if str_eq(MESSAGES[i].format, format) {
            return i as u32;
        }
        i += 1;
    }
    panic!("message format not in MESSAGES")
}

const fn str_eq(a: &str, b: &str) -> bool {
    let (a, b) = (a.as_bytes(), b.as_bytes());
    if a.len() != b.len() {
        return false;
    }
    let mut i = 0;
    while i < a.len() {
        if a[i] != b[i] {
            return false;
        }
        i += 1;
    }
    true
}

/// Id of `identify_response`.
pub const ID_IDENTIFY_RESPONSE: u32 = message_id(FMT_IDENTIFY_RESPONSE);
/// Id of `uptime`.
pub const ID_UPTIME: u32 = message_id(FMT_UPTIME);
/// Id of `clock`.
pub const ID_CLOCK: u32 = message_id(FMT_CLOCK);
/// Id of `config`.
pub const ID_CONFIG: u32 = message_id(FMT_CONFIG);
/// Id of `shutdown`.
pub const ID_SHUTDOWN: u32 = message_id(FMT_SHUTDOWN);
/// Id of `is_shutdown`.
pub const ID_IS_SHUTDOWN: u32 = message_id(FMT_IS_SHUTDOWN);
/// Id of `stats`.
pub const ID_STATS: u32 = message_id(FMT_STATS);
/// Id of `stepper_position`.
pub const ID_STEPPER_POSITION: u32 = message_id(FMT_STEPPER_POSITION);
/// Id of `endstop_state`.
pub const ID_ENDSTOP_STATE: u32 = message_id(FMT_ENDSTOP_STATE);
/// Id of `trsync_state`.
pub const ID_TRSYNC_STATE: u32 = message_id(FMT_TRSYNC_STATE);
/// Id of `analog_in_state`.
pub const ID_ANALOG_IN_STATE: u32 = message_id(FMT_ANALOG_IN_STATE);
/// Id of `tmcuart_response`.
pub const ID_TMCUART_RESPONSE: u32 = message_id(FMT_TMCUART_RESPONSE);
/// Id of `spi_transfer_response`.
pub const ID_SPI_TRANSFER_RESPONSE: u32 = message_id(FMT_SPI_TRANSFER_RESPONSE);
/// Id of `counter_state`.
pub const ID_COUNTER_STATE: u32 = message_id(FMT_COUNTER_STATE);
/// Id of `thermocouple_result`.
pub const ID_THERMOCOUPLE_RESULT: u32 = message_id(FMT_THERMOCOUPLE_RESULT);
/// Id of `cadence_lateness`.
pub const ID_CADENCE_LATENESS: u32 = message_id(FMT_CADENCE_LATENESS);

#[cfg(test)]
mod tests {
    use super::*;
    use links::proto::format::{message_name, Params};

    #[test]
    fn fixed_ids() {
        assert_eq!(MESSAGES[0].format, FMT_IDENTIFY_RESPONSE);
        assert_eq!(MESSAGES[0].kind, Kind::Response);
        assert_eq!(MESSAGES[1].format, FMT_IDENTIFY);
        assert_eq!(ID_IDENTIFY_RESPONSE, links::proto::ID_IDENTIFY_RESPONSE);
        assert_eq!(message_id(FMT_IDENTIFY), links::proto::ID_IDENTIFY);
    }

    #[test]
    fn formats_parse_and_names_are_unique() {
        for (i, m) in MESSAGES.iter().enumerate() {
            let n = Params::of(m.format).count();
            assert!(n <= MAX_PARAMS, "{}", m.format);
            assert!(Params::of(m.format).all(|p| p.is_ok()), "{}", m.format);
            let name = message_name(m.format);
            assert!(
                MESSAGES[i + 1..].iter().all(|o| message_name(o.format) != name),
                "duplicate {name}"
            );
        }
    }

    #[test]
    fn klipper_formats_are_exact() {
        let has = |f: &str| MESSAGES.iter().any(|m| m.format == f);
        assert!(has(
            "endstop_home oid=%c clock=%u sample_ticks=%u sample_count=%c rest_ticks=%u \
                     pin_value=%c trsync_oid=%c trigger_reason=%c"
        ));
        assert!(has(
            "query_analog_in oid=%c clock=%u sample_ticks=%u sample_count=%c \
                     rest_ticks=%u min_value=%hu max_value=%hu range_check_count=%c"
        ));
        assert!(has(
            "config_digital_out oid=%c pin=%u value=%c default_value=%c max_duration=%u"
        ));
        assert!(has("set_digital_out pin=%u value=%c"));
        assert!(has("queue_digital_out oid=%c clock=%u on_ticks=%u"));
        assert!(has("set_digital_out_pwm_cycle oid=%c cycle_ticks=%u"));
        assert!(has("config_analog_in oid=%c pin=%u"));
        assert!(has(
            "config_tmcuart oid=%c rx_pin=%u pull_up=%c tx_pin=%u bit_time=%u"
        ));
        assert!(has("tmcuart_send oid=%c write=%*s read=%c"));
        assert!(has("tmcuart_response oid=%c read=%*s"));
        assert!(has("config_spi oid=%c pin=%u cs_active_high=%c"));
        assert!(has("spi_set_bus oid=%c spi_bus=%u mode=%u rate=%u"));
        assert!(has("spi_transfer oid=%c data=%*s"));
        assert!(has("spi_send oid=%c data=%*s"));
        assert!(has("spi_transfer_response oid=%c response=%*s"));
        assert!(has("config_thermocouple oid=%c spi_oid=%c thermocouple_type=%c"));
        assert!(has(
            "query_thermocouple oid=%c clock=%u rest_ticks=%u min_value=%u max_value=%u \
                     max_invalid_count=%c"
        ));
        assert!(has("thermocouple_result oid=%c next_clock=%u value=%u fault=%c"));
        assert!(has(
            "trsync_start oid=%c report_clock=%u report_ticks=%u expire_reason=%c"
        ));
    }

    #[test]
    fn handlers_are_unique() {
        let handlers: Vec<Cmd> = MESSAGES
            .iter()
            .filter_map(|m| match m.kind {
                Kind::Command { handler, .. } => Some(handler),
                Kind::Response => None,
            })
            .collect();
        for (i, h) in handlers.iter().enumerate() {
            assert!(!handlers[i + 1..].contains(h), "{h:?} twice");
        }
    }
}
