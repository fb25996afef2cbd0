//! Issue 6, "no allocation in RT loops", end to end: `cadence` installs a counting global
//! allocator; a live print of a real sliced file on the simulated printer must show zero heap
//! allocations after warm-up on the planner thread (G-code, planning and step compression all
//! run there) and on the IO stage thread, over a non-trivial number of step batches.
//!
//! Warm-up: the planner counts from the first time flow control holds it back (the pipeline has
//! buffered its high-water mark of print time: every buffer has seen a full window), the IO
//! stage from its 64th batch. Each also reports how many step batches it handled after that
//! point, and the test requires plenty, so a 0 cannot come from an empty window.

use std::time::Duration;

use cadence_tests::{assert_success, benchy_prefix, cadence, scratch};

/// "`<allocations>` (`<batches>` batches)" after `label` in the summary line.
fn figures(line: &str, label: &str) -> (u64, u64) {
    let rest = line
        .split_once(label)
        .unwrap_or_else(|| panic!("no '{label}' in: {line}"))
        .1;
    let mut words = rest.split_whitespace();
    let allocs = words.next().and_then(|w| w.parse().ok());
    let batches = words.next().and_then(|w| w.trim_start_matches('(').parse().ok());
    match (allocs, batches) {
        (Some(a), Some(b)) => (a, b),
        _ => panic!("cannot read '{label}' figures in: {line}"),
    }
}

#[test]
fn benchy_prefix_allocates_nothing_after_warm_up() {
    let dir = scratch("print-alloc");
    // Homing, the start sequence (temperatures, fan, messages), then the first layers: mixed
    // travel, perimeters and infill; ~270 s of print time, ~690 step batches, ~28 s of wall
    // time at 10×.
    let Some((gcode, cfg)) = benchy_prefix(&dir, 4000) else {
        return;
    };

    let run = cadence(
        &[
            "print",
            gcode.to_str().unwrap(),
            "--config",
            cfg.to_str().unwrap(),
            "--time-scale",
            "10",
        ],
        Duration::from_secs(180),
    );
    assert_success(&run);
    let line = run
        .stdout
        .lines()
        .find(|l| l.contains("allocations after warm-up"))
        .unwrap_or_else(|| panic!("no allocation line in:\n{}", run.stdout));
    println!("{line}");
    let (planner, planner_batches) = figures(line, "planner ");
    let (io, io_batches) = figures(line, "io stage ");
    assert!(
        planner_batches >= 300 && io_batches >= 300,
        "too few batches after warm-up for the check to mean anything: {line}"
    );
    assert_eq!(
        (planner, io),
        (0, 0),
        "heap allocations after warm-up (planner, io stage): {line}\n\
         (find them with CADENCE_ALLOC_SITES=<path> cadence print ...)"
    );
}
