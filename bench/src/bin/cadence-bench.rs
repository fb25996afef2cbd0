//! `cadence-bench handoff [--samples N] [--gap-us G] [--fifo P] [--no-process]`: hand-off
//! latency histograms (see `bench::handoff`). `--child ...` is the consumer process it spawns.
//! `cadence-bench plan GCODE PRINTER_CFG [--threads N]`: planning + compression figures (see
//! `bench::plan`; the same as `cadence bench plan` with one-byte message ids).

use std::time::Duration;

use bench::handoff::{ipc_consume, run_all, HandoffOpts};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match run(&args) {
        Ok(()) => {}
        Err(e) => {
            eprintln!("cadence-bench: {e}");
            std::process::exit(1);
        }
    }
}

fn num<T: std::str::FromStr>(args: &[String], i: usize, what: &str) -> Result<T, String> {
    args.get(i)
        .and_then(|s| s.parse().ok())
        .ok_or_else(|| format!("{what}: expected a number"))
}

fn run(args: &[String]) -> Result<(), String> {
    if args.first().map(String::as_str) == Some("plan") {
        return plan(&args[1..]);
    }
    if args.first().map(String::as_str) != Some("handoff") {
        return Err(
            "usage: cadence-bench handoff [--samples N] [--gap-us G] [--fifo P] [--no-process]".into(),
        );
    }
    if args.get(1).map(String::as_str) == Some("--child") {
        let service = args.get(2).ok_or("--child: service name")?;
        let n: u64 = num(args, 3, "--child samples")?;
        let poll = args.get(4).map(String::as_str) == Some("poll");
        let core: usize = num(args, 5, "--child core")?;
        rt_core::os::apply_rt(&rt_core::os::RtSpec {
            core: Some(core),
            ..rt_core::os::RtSpec::new("bench-child")
        });
        let h = ipc_consume(service, n, poll)?;
        println!("{}", h.summary().format_latency());
        return Ok(());
    }
    let mut o = HandoffOpts::default();
    let mut process = true;
    let mut i = 1;
    while i < args.len() {
        match args[i].as_str() {
            "--samples" => o.samples = num(args, i + 1, "--samples")?,
            "--gap-us" => o.gap = Duration::from_micros(num(args, i + 1, "--gap-us")?),
            "--fifo" => o.fifo = Some(num(args, i + 1, "--fifo")?),
            "--no-process" => {
                process = false;
                i += 1;
                continue;
            }
            other => return Err(format!("unknown option {other}")),
        }
        i += 2;
    }
    let exe = std::env::current_exe().map_err(|e| e.to_string())?;
    println!(
        "handoff: {} samples, gap {:?}, cores {:?}, fifo {:?}",
        o.samples, o.gap, o.cores, o.fifo
    );
    for line in run_all(&o, process.then_some(exe.as_path())) {
        println!("  {line}");
    }
    for line in rt_core::os::rt_report() {
        println!("  {line}");
    }
    Ok(())
}

/// `plan GCODE CFG [--threads N]`.
fn plan(args: &[String]) -> Result<(), String> {
    let usage = "usage: cadence-bench plan GCODE PRINTER_CFG [--threads N]";
    let (Some(gcode), Some(cfg)) = (args.first(), args.get(1)) else {
        return Err(usage.into());
    };
    let mut opts = bench::plan::PlanOptions::default();
    match args.get(2).map(String::as_str) {
        None => {}
        Some("--threads") => opts.threads = num(args, 3, "--threads")?,
        Some(other) => return Err(format!("unknown option {other}; {usage}")),
    }
    let cfg = sysconfig::printer::load(std::path::Path::new(cfg)).map_err(|e| e.to_string())?;
    let report = bench::plan::plan_file(std::path::Path::new(gcode), &cfg, &opts)?;
    println!("{report}");
    Ok(())
}
