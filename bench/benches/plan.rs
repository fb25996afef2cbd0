//! Criterion bench: planning + step compression of the first lines of the 3DBenchy with the
//! reference cartesian printer (shared/data), inline and on two lane threads.
//! `CARGO_TARGET_DIR=/tmp/tgt-planner cargo bench -p bench --bench plan`

use std::path::Path;

use bench::plan::{plan_reader, PlanOptions};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};

const GCODE: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../shared/data/gcode/benchy-prusaslicer.gcode"
);
const PRINTER: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../shared/data/printers/benchy-cartesian.cfg"
);
/// Lines of the benchy planned per iteration.
const PREFIX_LINES: usize = 8000;

fn plan(c: &mut Criterion) {
    let (Ok(text), Ok(cfg)) = (std::fs::read(GCODE), sysconfig::load(Path::new(PRINTER))) else {
        eprintln!("note: {GCODE} or {PRINTER} is absent; plan bench skipped");
        return;
    };
    let prefix: Vec<u8> = {
        let mut n = 0;
        let end = text
            .iter()
            .position(|&b| {
                n += usize::from(b == b'\n');
                n == PREFIX_LINES
            })
            .unwrap_or(text.len());
        text[..end].to_vec()
    };
    let probe = plan_reader(&prefix[..], &cfg, &PlanOptions::default()).expect("benchy prefix plans");
    let mut g = c.benchmark_group("plan_benchy_prefix");
    g.throughput(Throughput::Elements(probe.steps));
    g.sample_size(10);
    for threads in [0usize, 2] {
        let opts = PlanOptions {
            threads,
            ..PlanOptions::default()
        };
        g.bench_function(format!("threads_{threads}"), |b| {
            b.iter(|| plan_reader(&prefix[..], &cfg, &opts).map(|r| r.queue_steps))
        });
    }
    g.finish();
}

criterion_group!(benches, plan);
criterion_main!(benches);
