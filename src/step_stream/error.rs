//! Why building or feeding a step stream failed: a missing step command in an MCU's
//! dictionary, a stepper whose MCU is not connected, a clock fit not there yet, or the sink
//! (live link, shared-memory hand-off, batch file) refusing a message.

use links::dict::DictError;
use links::mcu::LinkError;
use planner::machine::PlanError;

/// Why a step stream could not be built or could not take a step command.
#[derive(Debug, thiserror::Error)]
pub enum StreamError {
    /// The MCU's data dictionary lacks a step command (or an argument does not fit it).
    #[error(transparent)]
    Dictionary(#[from] DictError),
    /// The same, while building the stream of the named MCU.
    #[error("mcu '{mcu}': {source}")]
    McuDictionary {
        mcu: String,
        #[source]
        source: DictError,
    },
    /// More driver enable pins than object ids left on the MCU.
    #[error("mcu '{mcu}': too many objects")]
    TooManyObjects { mcu: String },
    /// A stepper whose MCU is not among the connected ones.
    #[error("[{stepper}]: its MCU '{mcu}' is not connected for this print")]
    NotConnected { stepper: String, mcu: String },
    /// A step command for a stepper index the streams do not have (a bug).
    #[error("internal error: step command for unknown stepper index {0}")]
    UnknownStepper(usize),
    /// Fewer sinks than streams (a bug).
    #[error("internal error: no sink for step stream {0}")]
    NoSink(usize),
    /// An MCU other than the main one has no clock-sync fit yet.
    #[error("mcu '{mcu}': no clock estimate yet")]
    NoClock { mcu: String },
    /// The planner refused a clock map.
    #[error(transparent)]
    Plan(#[from] PlanError),
    /// A message longer than a block (a bug).
    #[error("internal error: message too long for a block")]
    BlockTooLong,
    /// The batch output could not be written.
    #[error("writing the batch output: {0}")]
    Write(#[source] std::io::Error),
    /// The live MCU link refused the message.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// The shared-memory hand-off to the IO stage failed.
    #[error("planner → io hand-off: {0}")]
    Handoff(#[source] rt_core::shm::ShmError),
}

/// The older string-typed layers' view (the message as shown).
impl From<StreamError> for String {
    fn from(e: StreamError) -> String {
        e.to_string()
    }
}
