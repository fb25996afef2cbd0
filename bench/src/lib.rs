//! Benchmarks live here; see `cadence bench`.
