//! Issue 6's proof: a real sliced print on the simulated printer, time-compressed 5× (the
//! lead arithmetic stays in MCU time), while a CPU hog spins on every core: no step message may
//! reach the MCU with less than 100 ms of lead. The host's histograms are printed for the record.

use std::process::{Child, Command};
use std::time::Duration;

use cadence_tests::{assert_success, benchy_prefix, cadence, scratch};

/// CPU hogs that end on their own (bounded) and are killed when dropped.
struct Hogs(Vec<Child>);

impl Hogs {
    fn start(n: usize, seconds: u32) -> Hogs {
        let script =
            format!("end=$(( $(date +%s) + {seconds} )); while [ $(date +%s) -lt $end ]; do :; done");
        Hogs(
            (0..n)
                .map(|_| {
                    Command::new("sh")
                        .args(["-c", &script])
                        .spawn()
                        .expect("start a CPU hog")
                })
                .collect(),
        )
    }
}

impl Drop for Hogs {
    fn drop(&mut self) {
        for c in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

#[test]
fn benchy_prefix_under_cpu_load_keeps_the_lead() {
    let dir = scratch("rtload");
    // The first 1800 lines (homing, then the first layers): ~55 s of print time, ~12 s of wall
    // time at 5×.
    let Some((gcode, cfg)) = benchy_prefix(&dir, 1800) else {
        return;
    };

    let cores = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(2);
    let _hogs = Hogs::start(cores, 90);
    let hist = dir.join("latency.hlog");
    let run = cadence(
        &[
            "print",
            gcode.to_str().unwrap(),
            "--config",
            cfg.to_str().unwrap(),
            "--time-scale",
            "5",
            "--histograms",
            hist.to_str().unwrap(),
        ],
        Duration::from_secs(180),
    );
    drop(_hogs);
    println!("{}", run.stdout);
    assert_success(&run);
    assert!(!run.stdout.contains("LATE"), "{}", run.stdout);
    let lead = run
        .stdout
        .lines()
        .find(|l| l.contains("lead margin (ms)"))
        .expect("lead histogram line");
    let min: f64 = lead
        .split_whitespace()
        .nth(4)
        .and_then(|v| v.parse().ok())
        .expect("min lead");
    assert!(min >= 100.0, "{lead}");
    assert!(
        std::fs::metadata(&hist).map(|m| m.len() > 0).unwrap_or(false),
        "no histogram log written"
    );
}
