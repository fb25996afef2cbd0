//! `cargo run --release -p bench --example plan_file -- FILE.gcode PRINTER.cfg [THREADS]`
use std::path::Path;

fn main() -> Result<(), String> {
    let args: Vec<String> = std::env::args().collect();
    let (Some(g), Some(c)) = (args.get(1), args.get(2)) else {
        return Err("usage: plan_file FILE.gcode PRINTER.cfg [THREADS]".into());
    };
    let threads = args.get(3).and_then(|t| t.parse().ok()).unwrap_or(2);
    let cfg = sysconfig::load(Path::new(c)).map_err(|e| e.to_string())?;
    let opts = bench::plan::PlanOptions {
        threads,
        ..Default::default()
    };
    let r = bench::plan::plan_file(Path::new(g), &cfg, &opts)?;
    println!("{r}");
    Ok(())
}
