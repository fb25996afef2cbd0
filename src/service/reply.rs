//! Why the service answered a request with an error: the `message` of Klipper's
//! `WebRequestError` on the API socket, the `!! message` line on the G-code pseudo-terminal.
//! Klipper's words where it has them.

use crate::printer::PrinterError;

use super::sdcard::SdError;

/// Why a request (an API method, or a G-code script the worker ran) failed.
#[derive(Debug, thiserror::Error)]
pub enum ReplyError {
    /// A parameter the method needs is missing.
    #[error("Missing Argument [{0}]")]
    MissingArgument(&'static str),
    /// A parameter of the wrong JSON type.
    #[error("Invalid Argument Type [{0}]")]
    InvalidArgumentType(&'static str),
    /// `objects/query`: a field list that is not a list of names.
    #[error("Invalid argument")]
    InvalidArgument,
    /// The message is not a request.
    #[error(transparent)]
    Request(#[from] super::framing::RequestError),
    /// A method no one registered.
    #[error("webhooks: No registered callback for path '{0}'")]
    NoCallback(String),
    /// The printer is not ready (starting, shut down, failed to start): its state message.
    #[error("{message}")]
    NotReady { message: String },
    /// The printer refused the command or its session ended.
    #[error(transparent)]
    Printer(#[from] PrinterError),
    /// An sdcard command was refused.
    #[error(transparent)]
    Sd(#[from] SdError),
    /// `RESUME` while no print is paused.
    #[error("Print is not paused, resume aborted")]
    NotPaused,
    /// `M26` without a byte position.
    #[error("M26: S<byte position> expected")]
    M26Position,
}
