//! The IO stage in a process of its own: [`server`] is `cadence serve --role io` (it owns the
//! MCU connections and runs the IO stage for one print), [`planner_side`] is the planner's end
//! (`print --io-process` / `--io-attach NAME`). What crosses between them besides the step
//! channels is in [`payloads`] (MCU info, clock snapshots, status, control).

mod error;
pub mod payloads;
pub mod planner_side;
pub mod server;

pub use error::{IoProcessError, OffMainMcu};
