//! End to end: `[probe] activate_gcode` / `deactivate_gcode` run around each probing session
//! (a G28 homing Z on `probe:z_virtual_endstop`, PROBE), not around other commands
//! (QUERY_PROBE, X/Y homing), on the simulated two-MCU printer of examples/simulated-probe.cfg
//! (20 mm axes); a script that moves the toolhead stops the print with Klipper's message.

use std::path::{Path, PathBuf};
use std::time::Duration;

use cadence_tests::{assert_success, print_traced, retry_homing_timeouts, run, scratch, workspace, Run};

const TIMEOUT: Duration = Duration::from_secs(180);

/// examples/simulated-probe.cfg with 20 mm axes, `[respond]`, and the probe's `scripts`.
fn config(dir: &Path, scripts: &str) -> PathBuf {
    let text =
        std::fs::read_to_string(workspace().join("examples").join("simulated-probe.cfg")).expect("example");
    let mut out = String::new();
    for line in text.lines() {
        let l = line.split('#').next().unwrap_or_default().trim();
        let line = match l {
            "position_max: 220" | "position_max: 200" => "position_max: 20".to_string(),
            "homing_speed: 50" => "homing_speed: 10".to_string(),
            "[probe]" => format!("[probe]\n{scripts}"),
            _ => line.to_string(),
        };
        out.push_str(&line);
        out.push('\n');
    }
    out.push_str("\n[respond]\n");
    let path = dir.join("printer.cfg");
    std::fs::write(&path, out).expect("write config");
    path
}

fn print(dir: &Path, cfg: &Path, gcode: &str) -> Run {
    let g = dir.join("probe.gcode");
    std::fs::write(&g, gcode).expect("write gcode");
    let trace = dir.join("main.trace");
    retry_homing_timeouts(|| run(&mut print_traced(&g, cfg, &trace), TIMEOUT), |r| r)
}

#[test]
fn the_scripts_run_around_each_probing_session() {
    let dir = scratch("probe-scripts");
    let cfg = config(
        &dir,
        "activate_gcode:\n  RESPOND MSG=\"probe on\"\n  G4 P10\ndeactivate_gcode:\n  RESPOND MSG=\"probe off\"\n",
    );
    let run = print(
        &dir,
        &cfg,
        "RESPOND MSG=start\nG28 X Y\nRESPOND MSG=xy\nG28 Z\nRESPOND MSG=homed\nG1 Z5 F600\nPROBE\n\
         RESPOND MSG=probed\nQUERY_PROBE\nRESPOND MSG=end\n",
    );
    assert_success(&run);
    let said: Vec<&str> = run
        .stderr
        .lines()
        .filter_map(|l| l.split_once("echo: ").map(|(_, said)| said))
        .collect();
    assert_eq!(
        said,
        [
            "start",
            "xy",
            "probe on",
            "probe off",
            "homed",
            "probe on",
            "probe off",
            "probed",
            "end"
        ],
        "{}",
        run.stderr
    );
}

#[test]
fn a_script_that_moves_the_toolhead_stops_the_print() {
    let dir = scratch("probe-scripts-move");
    let cfg = config(&dir, "activate_gcode:\n  G91\n  G1 X2 F600\n  G90\n");
    let run = print(&dir, &cfg, "G28 X Y\nG28 Z\n");
    assert_eq!(run.code, Some(1), "{}\n{}", run.stdout, run.stderr);
    assert!(
        run.stderr
            .contains("probe.gcode:2: Toolhead moved during probe activate_gcode script"),
        "{}",
        run.stderr
    );
}
