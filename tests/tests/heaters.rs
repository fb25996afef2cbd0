//! End to end: `cadence print` heats the simulated printer's bed and hotend (thermal models in
//! the `cadence-mcu` process, ADC reports and PWM over the real pty), waits for them as
//! Klipper does, prints, and cools; and each injected heater fault (open thermistor, heater
//! that stops heating, frozen sensor) shuts the printer down with the right message; and on
//! `cadence serve`, the heater loop runs in a service session, PID_CALIBRATE answers in the
//! G-code output and SAVE_CONFIG rewrites printer.cfg and restarts the printer. Times are
//! MCU clocks from the simulator's trace (time-scaled), never wall time; bounds are generous.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use cadence_tests::api::{start_service, Api};
use cadence_tests::{bin, run, scratch, workspace, Run};
use firmware::trace::{read_trace, TraceRecord};
use serde_json::json;

const TIMEOUT: Duration = Duration::from_secs(240);
/// MCU seconds per wall second: heat-ups of minutes take seconds.
const SCALE: &str = "5";

/// At most this many prints at once. A print mostly waits for MCU time (a few % of a core),
/// so a few run side by side; not more: a time-scaled simulator is sensitive to host load (a
/// wall pause is five times as long in MCU time).
const SLOTS: usize = 2;
static RUNNING: (std::sync::Mutex<usize>, std::sync::Condvar) =
    (std::sync::Mutex::new(0), std::sync::Condvar::new());

/// One of the [`SLOTS`], held until dropped.
struct Slot;

impl Slot {
    fn take() -> Slot {
        let (count, freed) = &RUNNING;
        let mut n = count.lock().unwrap_or_else(|e| e.into_inner());
        while *n >= SLOTS {
            n = freed.wait(n).unwrap_or_else(|e| e.into_inner());
        }
        *n += 1;
        Slot
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        let (count, freed) = &RUNNING;
        let mut n = count.lock().unwrap_or_else(|e| e.into_inner());
        *n -= 1;
        freed.notify_one();
    }
}

/// The built-in simulated printer without endstops (G28 declares the axes homed), so the
/// time-scaled prints need no homing; extrusion needs 170 °C as on Klipper.
fn config(dir: &Path) -> PathBuf {
    let text: String = sysconfig::printer::SIMULATED_PRINTER_CFG
        .lines()
        .filter(|l| !l.starts_with("endstop_pin:") && !l.starts_with("homing_speed:"))
        .map(|l| {
            if l.starts_with("min_extrude_temp:") {
                "min_extrude_temp: 170\n".to_string()
            } else {
                format!("{l}\n")
            }
        })
        .collect();
    let path = dir.join("printer.cfg");
    std::fs::write(&path, text).unwrap();
    path
}

/// `cadence print` of `gcode` on the printer.cfg in `dir` (the test printer when there is none).
fn print(dir: &Path, gcode: &str, sim_args: Option<&str>) -> (Run, PathBuf) {
    let _slot = Slot::take();
    let cfg = dir.join("printer.cfg");
    if !cfg.exists() {
        config(dir);
    }
    let g = dir.join("print.gcode");
    std::fs::write(&g, gcode).unwrap();
    let trace = dir.join("mcu.trace");
    let mut cmd = Command::new(bin("cadence"));
    cmd.args([
        "print",
        g.to_str().unwrap(),
        "--config",
        cfg.to_str().unwrap(),
        "--time-scale",
        SCALE,
        "--no-realtime",
        "--trace",
        trace.to_str().unwrap(),
    ]);
    match sim_args {
        Some(a) => cmd.env("CADENCE_SIM_ARGS_MCU", a),
        None => cmd.env_remove("CADENCE_SIM_ARGS_MCU"),
    };
    (run(&mut cmd, TIMEOUT), trace)
}

/// MCU seconds of the simulated MCU's shutdown in `trace`, if it shut down.
fn shutdown_s(trace: &Path) -> Option<f64> {
    let t = read_trace(trace).expect("trace");
    t.records.iter().find_map(|r| match *r {
        TraceRecord::Shutdown { clock, .. } => Some(clock as f64 / t.clock_freq as f64),
        _ => None,
    })
}

/// A slicer's start: heat the bed and wait, heat the hotend and wait, print, then cool.
const SLICER: &str = "\
M140 S50 ; set bed temp
M105
M190 S50 ; wait for bed temp
M104 S185 ; set extruder temp
M105
M109 S185 ; wait for extruder temp
M105
G28
G90
M83
M106 S128
G1 Z0.3 F600
G1 X50 Y50 F6000
G1 X70 Y50 E1.0 F1800
G1 X70 Y70 E1.0
G1 X50 Y70 E1.0
G1 X50 Y50 E1.0
M107
M104 S0
M140 S0
TEMPERATURE_WAIT SENSOR=extruder MAXIMUM=150
M105
";

#[test]
fn a_slicer_start_heats_waits_prints_and_cools() {
    let dir = scratch("heat-print");
    let (run, trace) = print(&dir, SLICER, None);
    assert_eq!(run.code, Some(0), "{}\n{}", run.stdout, run.stderr);
    let out = &run.stdout;
    eprintln!("{out}");
    assert_eq!(shutdown_s(&trace), None, "the MCU shut down");
    let waited = |what: &str| -> f64 {
        let line = out
            .lines()
            .find(|l| l.contains(&format!("heaters: {what} waited")))
            .unwrap_or_else(|| panic!("no {what} wait in\n{out}"));
        line.split(" waited ")
            .nth(1)
            .and_then(|r| r.split(" s ").next())
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| panic!("{line}"))
    };
    // The bed (150 W, 500 J/K) takes about 1.5 min to 50 °C; the hotend (40 W) then about
    // a minute from 25 to 185 °C.
    let (bed, hotend) = (waited("M190"), waited("M109"));
    eprintln!("heat-up (MCU time): bed to 50 °C {bed:.1} s, then hotend to 185 °C {hotend:.1} s");
    assert!((40.0..600.0).contains(&bed), "bed {bed}");
    assert!((20.0..300.0).contains(&hotend), "hotend {hotend}");
    // M105 (Klipper's `B:cur /target T0:cur /target`): cold at first; after the waits both
    // at target; at the end the hotend cooled below 150.
    let m105: Vec<&str> = out.lines().filter(|l| l.contains("M105: B:")).collect();
    assert_eq!(m105.len(), 4, "{out}");
    assert!(
        m105[0].contains("/50.0 T0:") && m105[0].ends_with("/0.0"),
        "{m105:?}"
    );
    let t = |l: &str| -> f64 {
        l.split("T0:")
            .nth(1)
            .and_then(|r| r.split(' ').next())
            .and_then(|s| s.parse().ok())
            .unwrap()
    };
    assert!(t(m105[0]) < 40.0, "{m105:?}");
    assert!(
        (t(m105[2]) - 185.0).abs() < 3.0 && m105[2].ends_with("/185.0"),
        "{m105:?}"
    );
    assert!(m105[3].ends_with("/0.0"), "{m105:?}");
    assert!(t(m105[3]) <= 150.0, "{m105:?}");
    assert!(
        out.contains("heater extruder:") && out.contains("heater heater_bed:"),
        "{out}"
    );
}

#[test]
fn extruding_cold_and_targets_out_of_range_are_refused() {
    let dir = scratch("heat-refuse");
    let (run, _) = print(&dir, "G28\nG1 Z1 F600\nG1 X10 E1 F1200\n", None);
    assert_ne!(run.code, Some(0));
    assert!(
        run.stderr.contains("print.gcode:3: Extrude below minimum temp"),
        "{}",
        run.stderr
    );
    let (run, _) = print(&dir, "M104 S300\n", None);
    assert_ne!(run.code, Some(0));
    assert!(
        run.stderr
            .contains("print.gcode:1: Requested temperature (300.0) out of range (0.0:250.0)"),
        "{}",
        run.stderr
    );
}

/// Heats the hotend to 210 °C with `fault` injected at MCU second `at`; returns the error
/// output and the MCU seconds from the injection to the shutdown (every output off).
fn fault_run(name: &str, fault: &str, at: f64) -> (String, f64) {
    let dir = scratch(name);
    let sim = format!("--heater-fault PE0={fault}@{at}");
    let (run, trace) = print(&dir, "M104 S210\nM109 S210\nG4 P100000\n", Some(&sim));
    assert_ne!(run.code, Some(0), "{}", run.stdout);
    let off = shutdown_s(&trace).unwrap_or_else(|| panic!("no MCU shutdown: {}", run.stderr));
    eprintln!(
        "{fault}@{at}: heater off (MCU shutdown) {:.1} s after the fault",
        off - at
    );
    (run.stderr, off - at)
}

#[test]
fn an_open_thermistor_shuts_down_with_adc_out_of_range() {
    let (err, after) = fault_run("heat-open", "open", 40.0);
    assert!(err.contains("ADC out of range"), "{err}");
    // Four out-of-range reports 0.3 s apart.
    assert!((0.0..5.0).contains(&after), "{after}");
}

#[test]
fn a_heater_that_stops_heating_is_a_thermal_runaway() {
    let (err, after) = fault_run("heat-noheat", "no-heat", 40.0);
    assert!(
        err.contains("Heater extruder not heating at expected rate"),
        "{err}"
    );
    // verify_heater's check_gain_time (20 s) and max_error (120) after the last gain.
    assert!((5.0..90.0).contains(&after), "{after}");
}

#[test]
fn a_frozen_sensor_is_a_thermal_runaway() {
    let (err, after) = fault_run("heat-frozen", "frozen", 40.0);
    assert!(
        err.contains("Heater extruder not heating at expected rate"),
        "{err}"
    );
    assert!((5.0..90.0).contains(&after), "{after}");
}

#[test]
fn the_example_configs_load_with_their_heaters() {
    for name in [
        "simulated-cartesian.cfg",
        "simulated-corexy.cfg",
        "simulated-toolboard.cfg",
    ] {
        let cfg = sysconfig::printer::load(&workspace().join("examples").join(name)).unwrap();
        let m = cadence::hardware::Machine::from_config(&cfg).unwrap();
        assert!(m.thermal.heater("extruder").is_some(), "{name}");
    }
}

#[test]
fn m112_shuts_every_mcu_down_with_the_heater_on() {
    let dir = scratch("heat-m112");
    let (run, trace) = print(&dir, "M104 S200\nG4 P10000\nM105\nM112\nG4 P10000\n", None);
    assert_ne!(run.code, Some(0), "{}", run.stdout);
    assert!(
        run.stderr.contains("print.gcode:4: Shutdown due to M112 command"),
        "{}",
        run.stderr
    );
    assert!(shutdown_s(&trace).is_some(), "the MCU did not shut down");
}

/// `[temperature_sensor]` (reported by M105 under its gcode_id, waited for, summarised),
/// `[fan_generic]` (SET_FAN_SPEED), `[temperature_fan]` (SET_TEMPERATURE_FAN_TARGET: at
/// 25 °C with target 20 it runs at full speed, with target 40 it stops) and
/// `[controller_fan]` (on while the print runs) on the simulated printer, whose spare analog
/// inputs read room temperature.
#[test]
fn sensors_and_the_other_fans_are_driven() {
    let dir = scratch("heat-fans");
    let cfg = config(&dir);
    let mut text = std::fs::read_to_string(&cfg).unwrap();
    text.push_str(
        "\n[temperature_sensor chamber]\nsensor_type: Generic 3950\nsensor_pin: PF2\ngcode_id: C\n\
         \n[temperature_fan exhaust]\npin: PE4\nsensor_type: Generic 3950\nsensor_pin: PF3\n\
         min_temp: 0\nmax_temp: 80\ncontrol: watermark\ntarget_temp: 20\ngcode_id: X\n\
         \n[controller_fan board]\npin: PE5\n\
         \n[fan_generic aux]\npin: PE6\n",
    );
    std::fs::write(&cfg, text).unwrap();
    // TEMPERATURE_WAIT holds until the sensor reads; M190 gives the fans time to follow.
    let gcode = "TEMPERATURE_WAIT SENSOR=\"temperature_sensor chamber\" MINIMUM=20 MAXIMUM=30\n\
                 M105\nSET_FAN_SPEED FAN=aux SPEED=0.5\n\
                 SET_TEMPERATURE_FAN_TARGET TEMPERATURE_FAN=exhaust TARGET=40\nM190 S30\nM105\n";
    let (run, trace) = print(&dir, gcode, None);
    assert_eq!(run.code, Some(0), "{}\n{}", run.stdout, run.stderr);
    assert_eq!(shutdown_s(&trace), None, "the MCU shut down");
    let out = &run.stdout;
    let m105: Vec<&str> = out.lines().filter(|l| l.contains("M105: B:")).collect();
    assert_eq!(m105.len(), 2, "{out}");
    assert!(
        m105[0].contains(" C:25.0 /0.0 T0:") && m105[0].ends_with(" X:25.0 /20.0"),
        "{m105:?}"
    );
    assert!(m105[1].ends_with(" X:25.0 /40.0"), "{m105:?}");
    for line in [
        "temperature_sensor chamber: 25.0 °C",
        "temperature_fan exhaust: 0 %, sensor 25.0 °C, target 40.0 °C",
        "fan_generic aux: 50 %",
        "controller_fan board: 100 %",
        "heaters: TEMPERATURE_WAIT waited",
    ] {
        assert!(out.contains(line), "no '{line}' in\n{out}");
    }
    // Refused as Klipper words it.
    let (run, _) = print(&dir, "SET_FAN_SPEED FAN=nope SPEED=1\n", None);
    assert!(
        run.stderr.contains("The value 'nope' is not valid for FAN"),
        "{}",
        run.stderr
    );
    let (run, _) = print(
        &dir,
        "SET_TEMPERATURE_FAN_TARGET TEMPERATURE_FAN=exhaust TARGET=90\n",
        None,
    );
    assert!(
        run.stderr
            .contains("Requested temperature (90.0) out of range (0.0:80.0)"),
        "{}",
        run.stderr
    );
}

// `cadence serve`: a service session heats, calibrates and saves its config.

#[test]
fn a_service_session_heats_calibrates_and_saves_its_config() {
    let _slot = Slot::take();
    let dir = scratch("heat-serve");
    let cfg = config(&dir);
    let socket = dir.join("klippy.sock");
    let args = [
        "--time-scale".as_ref(),
        "5".as_ref(),
        "--config".as_ref(),
        cfg.as_os_str(),
    ];
    let _service = start_service(&dir, &socket, &args);
    let mut api = Api::connect(&socket, Duration::from_secs(240));
    api.wait_state("ready");
    let list = api.ok("objects/list", json!({}));
    for name in [
        "heaters",
        "extruder",
        "heater_bed",
        "fan",
        "heater_fan hotend_fan",
    ] {
        assert!(
            list["objects"].as_array().expect("list").contains(&json!(name)),
            "{list}"
        );
    }

    // A target over the API heats the hotend in the session's heater loop.
    api.ok("gcode/script", json!({"script": "M104 S60"}));
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let e = api.status("extruder");
        if e["target"] == json!(60.0) && e["temperature"].as_f64().unwrap_or(0.0) > 35.0 {
            assert!(
                e["power"].as_f64().is_some() && e["can_extrude"].is_boolean(),
                "{e}"
            );
            break;
        }
        assert!(Instant::now() < deadline, "the hotend did not heat: {e}");
        std::thread::sleep(Duration::from_millis(100));
    }
    assert_eq!(api.status("heater_fan hotend_fan")["speed"], json!(1.0));

    // PID_CALIBRATE answers in the G-code output; SAVE_CONFIG writes and restarts.
    api.ok("gcode/subscribe_output", json!({"response_template": {}}));
    api.ok(
        "gcode/script",
        json!({"script": "PID_CALIBRATE HEATER=extruder TARGET=200"}),
    );
    let said = |api: &Api, what: &str| api.notes.iter().any(|n| n.to_string().contains(what));
    let deadline = Instant::now() + Duration::from_secs(30);
    while !said(&api, "PID parameters: pid_Kp=") {
        assert!(Instant::now() < deadline, "no PID result in {:?}", api.notes);
        let _ = api.ok("info", json!({}));
        std::thread::sleep(Duration::from_millis(50));
    }
    // The result waits for SAVE_CONFIG, as the configfile object says.
    let q = api.ok("objects/query", json!({"objects": {"configfile": null}}));
    let configfile = &q["status"]["configfile"];
    assert_eq!(configfile["save_config_pending"], json!(true), "{configfile}");
    assert_eq!(
        configfile["save_config_pending_items"]["extruder"]["control"],
        json!("pid"),
        "{configfile}"
    );
    api.ok("gcode/script", json!({"script": "SAVE_CONFIG"}));
    let text = std::fs::read_to_string(&cfg).expect("config");
    assert!(
        text.contains("#*# [extruder]\n#*# control = pid\n#*# pid_kp = "),
        "{text}"
    );
    assert!(text.contains("\n#pid_Kp: 22.2\n"), "{text}");
    let kp = text
        .split("#*# pid_kp = ")
        .nth(1)
        .and_then(|r| r.lines().next())
        .expect("pid_kp")
        .to_string();
    // The service restarts after answering: the reopened printer reads the saved gains and
    // is a new session (cold targets).
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let info = api.ok("info", json!({}));
        let q = api.ok("objects/query", json!({"objects": {"configfile": ["settings"]}}));
        if info["state"] == "ready"
            && q["status"]["configfile"]["settings"]["extruder"]["pid_kp"] == json!(kp)
        {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "never reopened with pid_kp {kp}: {info} {q}"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    assert_eq!(api.status("extruder")["target"], json!(0.0));
    let _ = std::fs::remove_dir_all(&dir);
}
