//! The `cadence bench` modes as the CLI calls them: each takes its own options and the
//! [`crate::run::Common`] ones, writes text or JSON to `out` and returns the report.

pub mod handoff;
pub mod plan;
pub mod wakeup;

/// The homing budget: trigger → stop must fit in 25 ms (Klipper's multi-MCU homing rule).
pub const HOMING_BUDGET_NS: u64 = 25_000_000;
