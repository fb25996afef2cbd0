//! Why the out-of-process IO stage failed, on either side: the printer it refuses, the
//! hand-shake (READY, the MCU info, the config CRC, FINISH/DONE), the channels, or the other
//! process failing or exiting.

use rt_core::shm::ShmError;

use crate::hardware::HardwareError;
use crate::io_stage::IoStageError;
use crate::live::LiveError;
use crate::mcus::{ConfigureError, McuError};
use crate::planner_thread::PlannerError;

/// A printer with a stepper off the main MCU: the IO process serves the main MCU only.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error(
    "[{stepper}] is driven by mcu '{mcu}': the IO stage in another process (serve, --io-process, \
     --io-attach) streams steps to the main [mcu] only; print without --io-process/--io-attach"
)]
pub struct OffMainMcu {
    pub stepper: String,
    pub mcu: String,
}

/// Why a print with the IO stage in another process (either side) failed.
#[derive(Debug, thiserror::Error)]
pub enum IoProcessError {
    /// printer.cfg could not be read or describes no printer Cadence can drive.
    #[error(transparent)]
    Config(#[from] HardwareError),
    /// A stepper off the main MCU.
    #[error(transparent)]
    OffMainMcu(#[from] OffMainMcu),
    /// `--time-scale` given for real MCUs.
    #[error("--time-scale only applies to a simulated printer")]
    TimeScaleNotSimulated,
    /// `--time-scale` out of range.
    #[error("--time-scale {0}: must be in (0, 50]")]
    TimeScale(f64),
    /// printer.cfg has no `[mcu]`.
    #[error("the printer config has no [mcu]")]
    NoMcu,
    /// The logger thread did not start.
    #[error(transparent)]
    Logger(#[from] rt_core::logger::LoggerError),
    /// A shared-memory node or channel failed.
    #[error(transparent)]
    Shm(#[from] ShmError),
    /// Publishing the IO process's status failed.
    #[error("io status: {0}")]
    Status(#[source] ShmError),
    /// Sending a control message to the IO process failed.
    #[error("io control: {0}")]
    Control(#[source] ShmError),
    /// The running executable cannot be found (to start the IO process).
    #[error("cannot locate the running executable: {0}")]
    Executable(#[source] std::io::Error),
    /// The IO process did not start.
    #[error("cannot start the IO process (cadence serve --role io): {0}")]
    Spawn(#[source] std::io::Error),
    /// A thread of this side did not start (`what`: which one).
    #[error("cannot start the {what}: {source}")]
    Thread {
        what: &'static str,
        #[source]
        source: std::io::Error,
    },
    /// A thread of this side panicked (`what`: which one).
    #[error("the {what} panicked")]
    Panicked { what: &'static str },
    /// The other process failed or exited, or the relay lost it (its reason).
    #[error("{reason}")]
    Failed { reason: String },
    /// The IO process reported FAILED before READY.
    #[error("the IO process failed: {reason}")]
    FailedAtStart { reason: String },
    /// The IO process exited with a failure after the print.
    #[error("the IO process exited with {0}")]
    Exited(std::process::ExitStatus),
    /// The IO process was not ready in time.
    #[error("the IO process was not ready within {secs} s")]
    NotReady { secs: u64 },
    /// The IO process published no MCU info in time.
    #[error("mcu '{mcu}': the IO process published no MCU info within 10 s")]
    NoInfo { mcu: String },
    /// The IO process published no valid clock in time.
    #[error("the IO process published no valid clock within 10 s")]
    NoClock,
    /// The IO process did not report DONE in time.
    #[error("the IO process did not finish the print within {secs:.0} s")]
    NotFinished { secs: f64 },
    /// The dictionary the IO process sent does not parse.
    #[error("mcu '{mcu}': the IO process sent a bad data dictionary: {source}")]
    BadDictionary {
        mcu: String,
        #[source]
        source: links::dict::DictError,
    },
    /// The MCU's configuration could not be built (to compute its CRC).
    #[error("mcu '{mcu}': {source}")]
    Configure {
        mcu: String,
        #[source]
        source: Box<ConfigureError>,
    },
    /// The two processes read different printer configs.
    #[error(
        "mcu '{mcu}': the IO process configured the MCU differently (config CRC {theirs:08x}, this \
         printer config gives {ours:08x}): start both with the same printer.cfg"
    )]
    ConfigMismatch { mcu: String, theirs: u32, ours: u32 },
    /// An MCU's dictionary does not fit the info payload.
    #[error("mcu '{mcu}': its data dictionary ({bytes} bytes) is larger than an McuInfo carries")]
    DictionaryTooLarge { mcu: String, bytes: usize },
    /// More steppers than the status payload carries.
    #[error("{0} steppers: an IoStatus carries at most {max} positions", max = super::payloads::STATUS_POSITIONS)]
    TooManySteppers(usize),
    /// The IO stage thread failed to start.
    #[error("io stage: {0}")]
    IoStageStart(#[source] IoStageError),
    /// The IO stage thread did not start in time.
    #[error("io stage did not start within 10 s")]
    IoStageTimeout,
    /// The IO stage stopped the print.
    #[error(transparent)]
    IoStage(#[from] IoStageError),
    /// The IO stage ended without an error before the planner's FINISH.
    #[error("the IO stage stopped unexpectedly")]
    IoStageEnded,
    /// The planner aborted, its process is gone, or it went silent (the reason).
    #[error("{reason}")]
    Stop { reason: String },
    /// An MCU did not connect or shut down.
    #[error(transparent)]
    Mcu(#[from] McuError),
    /// The planner thread stopped the print.
    #[error(transparent)]
    Planner(Box<PlannerError>),
    /// The end of the print: positions, leads.
    #[error(transparent)]
    Live(Box<LiveError>),
    /// The histograms file could not be written.
    #[error(transparent)]
    Histograms(#[from] crate::latency::HistogramsError),
}

from_boxed!(IoProcessError, Planner, PlannerError);
from_boxed!(IoProcessError, Live, LiveError);

/// The CLI's view (the message as shown).
impl From<IoProcessError> for String {
    fn from(e: IoProcessError) -> String {
        e.to_string()
    }
}
