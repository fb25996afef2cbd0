//! Why a TMC driver's command, bus set-up or register traffic failed, in the words the printer
//! shows (several as Klipper words them).

use links::dict::DictError;
use links::mcu::LinkError;
use sysconfig::printer::tmc::FieldError;

/// Why a TMC command (`SET_TMC_CURRENT`, `SET_TMC_FIELD`, `DUMP_TMC`, `INIT_TMC`), the drivers'
/// bus objects or a register read or write failed.
#[derive(Debug, thiserror::Error)]
pub enum TmcError {
    /// A register the driver model does not have.
    #[error("Unknown register name '{reg}'")]
    UnknownRegister { reg: String },
    /// A field the driver model does not have.
    #[error(transparent)]
    Field(#[from] FieldError),
    /// The MCU's dictionary cannot encode a bus command.
    #[error(transparent)]
    Encode(#[from] DictError),
    /// A bus pin the MCU does not have (`[tmc2209 stepper_x] uart_pin: …`).
    #[error("[{section}] {option}: {source}")]
    Pin {
        section: String,
        option: &'static str,
        #[source]
        source: DictError,
    },
    /// The MCU link failed or did not answer.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// Every try of a register read failed (`bus`: `uart` or `spi`).
    #[error("Unable to read tmc {bus} '{stepper}' register {reg}")]
    Read {
        bus: &'static str,
        stepper: String,
        reg: String,
    },
    /// Every try of a register write failed.
    #[error("Unable to write tmc {bus} '{stepper}' register {reg}")]
    Write {
        bus: &'static str,
        stepper: String,
        reg: String,
    },
    /// `STEPPER=` names a stepper without a TMC driver.
    #[error("Unknown STEPPER '{stepper}': no TMC driver configured for it")]
    UnknownStepper { stepper: String },
    /// The driver's MCU is not connected.
    #[error("mcu '{mcu}' of [{section}] is not connected")]
    NotConnected { mcu: String, section: String },
    /// The bus objects' oids do not fit a byte.
    #[error("too many objects")]
    TooManyObjects,
    /// A command without a parameter it needs.
    #[error("Error on '{raw}': missing {key}")]
    Missing { raw: String, key: &'static str },
    /// A parameter that is not a number.
    #[error("Error on '{raw}': unable to parse '{value}' as {what}")]
    Unparsable {
        raw: String,
        value: String,
        what: &'static str,
    },
    /// `VELOCITY=` below 0.
    #[error("Error on '{raw}': VELOCITY must be at least 0")]
    NegativeVelocity { raw: String },
    /// `SET_TMC_FIELD` with neither or both of `VALUE=` and `VELOCITY=`.
    #[error("Specify either VALUE or VELOCITY")]
    ValueOrVelocity,
    /// `CURRENT=`/`HOLDCURRENT=` outside the driver's range.
    #[error("Error on '{raw}': {key} must be above 0 and at most {max} (got {value})")]
    Current {
        raw: String,
        key: &'static str,
        max: f64,
        value: f64,
    },
}
