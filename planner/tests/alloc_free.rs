//! The planner loop allocates nothing in steady state (issue #6): the 3DBenchy's first lines,
//! with heater, fan, velocity-limit and unsupported commands mixed in, go through the
//! `GcodeReader` → `Pipeline::apply` → `Pipeline::generate` loop of a live print (inline lanes,
//! the live default) with rt-core's counting allocator installed; after a warm-up the test thread
//! must make no allocation or reallocation at all.
//!
//! The counter is per thread: it sees this test's thread only, which is the whole planner here
//! (inline lanes, no worker threads). This file holds one test so that nothing else runs while
//! allocation sites are captured. Skipped when the G-code file is absent.

mod common;
use common::{benchy_cartesian, BENCHY};
use planner::gcode::GcodeReader;
use planner::pipeline::{Pipeline, PipelineOptions};
use planner::stepgen::StepCmd;
use rt_core::alloc_count::{AllocCounter, AllocSites, CountingAlloc};

#[global_allocator]
static ALLOC: CountingAlloc = CountingAlloc;

/// Lines of the file planned.
const LINES: usize = 2000;
/// Lines planned before counting starts.
const WARM_UP: usize = 800;

/// Commands the planner answers with something other than motion, each inserted every
/// `INSERT_EVERY` file lines (in turn), before and after the warm-up.
const INSERTED: [&str; 15] = [
    "M106 S128",
    "M104 S215",
    "M140 S60 ; bed",
    "SET_VELOCITY_LIMIT ACCEL=2500 SQUARE_CORNER_VELOCITY=5",
    "set_velocity_limit velocity=400 accel=3000",
    "M73 P10 R5",
    "M107",
    "M204 S3000",
    "M220 S100",
    "N12 M106 S255*86",
    "EXCLUDE_OBJECT_START NAME=3DBenchy.stl_id_0_copy_0",
    "G4 P0",
    "M106 S100 (fan on) ; part cooling",
    "M117 Layer 3",
    "M114",
];
const INSERT_EVERY: usize = 7;

/// The first `LINES` lines with [`INSERTED`] mixed in.
fn gcode() -> Option<Vec<u8>> {
    let Ok(text) = std::fs::read_to_string(BENCHY) else {
        eprintln!("note: {BENCHY} is absent; allocation test skipped");
        return None;
    };
    let mut out = Vec::new();
    for (i, line) in text.lines().take(LINES).enumerate() {
        out.extend_from_slice(line.as_bytes());
        out.push(b'\n');
        if i % INSERT_EVERY == 0 {
            out.extend_from_slice(INSERTED[(i / INSERT_EVERY) % INSERTED.len()].as_bytes());
            out.push(b'\n');
        }
    }
    Some(out)
}

#[test]
fn planner_loop_allocates_nothing_after_warm_up() {
    let Some(text) = gcode() else {
        return;
    };
    let warm_up_bytes = text
        .split_inclusive(|&b| b == b'\n')
        .take(WARM_UP)
        .map(<[u8]>::len)
        .sum::<usize>();
    // The unknown commands mixed in (M73, EXCLUDE_OBJECT_START) take the warn-and-skip path
    // (`[gcode] unknown_commands: warn`), which must not allocate either.
    let opts = PipelineOptions {
        unknown_commands_are_errors: false,
        ..PipelineOptions::default()
    };
    let mut p = Pipeline::with_options(benchy_cartesian(), 0.25, opts).expect("config");
    let mut out: Vec<(usize, StepCmd)> = Vec::with_capacity(1 << 16);
    let mut reader = GcodeReader::new(&text[..]);
    let step = |reader: &mut GcodeReader<&[u8]>, p: &mut Pipeline, out: &mut Vec<(usize, StepCmd)>| {
        let Some(line) = reader.next() else {
            return false;
        };
        let line = line.unwrap_or_else(|e| panic!("{e}"));
        p.apply(&line).unwrap_or_else(|e| panic!("{e}"));
        p.generate(out);
        out.clear();
        true
    };
    // Warm-up: every buffer reaches its working size.
    let mut consumed = 0;
    let mut applied = 0usize;
    while consumed < WARM_UP {
        if !step(&mut reader, &mut p, &mut out) {
            break;
        }
        consumed = reader.line_no();
        applied += 1;
    }
    assert!(warm_up_bytes > 0 && applied > 100, "warm-up too short");

    AllocSites::start();
    let before = AllocCounter::snapshot();
    let mut measured = 0usize;
    while step(&mut reader, &mut p, &mut out) {
        measured += 1;
    }
    let used = AllocCounter::snapshot().since(before);
    let sites = AllocSites::take();
    let stats = p.stats();
    assert!(measured > 1000, "only {measured} lines measured");
    assert!(stats.moves > 500, "only {} moves planned", stats.moves);
    if used.allocations() != 0 {
        for (n, bytes, stack) in AllocSites::report(&sites, 14) {
            eprintln!("{n} allocations, {bytes} bytes:\n{stack}\n");
        }
        panic!("the planner loop allocated over {measured} lines after warm-up: {used:?} (sites above)");
    }
    p.finish(&mut out);
}
