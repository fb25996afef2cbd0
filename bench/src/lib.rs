//! Benchmarks live here; see `cadence bench`.

pub mod handoff;
pub mod plan;
