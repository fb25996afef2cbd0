//! The status objects the API socket serves (`objects/list`, `objects/query`,
//! `objects/subscribe`), with the names and fields of Klipper's Status Reference where Cadence
//! has the value, built from one [`Snapshot`] of the service; plus Cadence's own `latency`.

use std::path::Path;

use serde_json::{json, Map, Value};
use sysconfig::printer::PrinterConfig;

use crate::events::{PrinterState, Status};
use crate::printer::Latency;

use super::sdcard::{PrintInfo, PrintState};
use super::ServiceState;

/// What the printer's configuration says, read once per opened config.
#[derive(Debug, Clone)]
pub struct ConfigFacts {
    /// `configfile.config`: every section's options as written.
    pub config: Value,
    /// `configfile.settings`: the same with lower-case names (values as text).
    pub settings: Value,
    pub axis_minimum: [f64; 4],
    pub axis_maximum: [f64; 4],
    pub max_velocity: f64,
    pub max_accel: f64,
    pub minimum_cruise_ratio: f64,
    pub square_corner_velocity: f64,
    pub steppers: Vec<String>,
    pub has_extruder: bool,
    /// `[virtual_sdcard] path` (`~` expanded).
    pub sdcard: Option<std::path::PathBuf>,
    /// The thermal status objects (`extruder`, `heater_bed`, `fan`, `heater_fan NAME`,
    /// `temperature_sensor NAME`, …) and the `heaters` lists.
    pub thermal: ThermalFacts,
}

/// The thermal objects printer.cfg declares (the heater loop fills their values).
#[derive(Debug, Clone, Default)]
pub struct ThermalFacts {
    /// Object names, in `objects/list` order.
    pub objects: Vec<String>,
    pub available_heaters: Vec<String>,
    pub available_sensors: Vec<String>,
    /// Each extruder's `min_extrude_temp` (`can_extrude`), by name.
    pub min_extrude_temp: Vec<(String, f64)>,
}

impl ThermalFacts {
    fn new(cfg: &PrinterConfig) -> ThermalFacts {
        let th = &cfg.thermal;
        let mut heaters: Vec<String> = Vec::new();
        heaters.extend(cfg.extruders().map(|e| e.name.clone()));
        if cfg.heater_bed.is_some() {
            heaters.push("heater_bed".into());
        }
        heaters.extend(
            th.heater_generic
                .iter()
                .map(|h| format!("heater_generic {}", h.name)),
        );
        let mut sensors = heaters.clone();
        sensors.extend(
            th.temperature_sensors
                .iter()
                .map(|s| format!("temperature_sensor {}", s.name)),
        );
        sensors.extend(
            th.temperature_fans
                .iter()
                .map(|f| format!("temperature_fan {}", f.name)),
        );
        let mut objects = vec!["heaters".to_string()];
        objects.extend(sensors.iter().cloned());
        if th.fan.is_some() {
            objects.push("fan".into());
        }
        objects.extend(th.heater_fans.iter().map(|f| format!("heater_fan {}", f.name)));
        objects.extend(
            th.controller_fans
                .iter()
                .map(|f| format!("controller_fan {}", f.name)),
        );
        objects.extend(th.fan_generic.iter().map(|(n, _)| format!("fan_generic {n}")));
        ThermalFacts {
            objects,
            available_heaters: heaters,
            available_sensors: sensors,
            min_extrude_temp: cfg
                .extruders()
                .map(|e| (e.name.clone(), e.heater.min_extrude_temp))
                .collect(),
        }
    }
}

impl ConfigFacts {
    /// Reads the raw sections of `ini_path` (or of the built-in simulated printer's text) and
    /// the typed values of `cfg`.
    pub fn new(cfg: &PrinterConfig, ini_path: Option<&Path>) -> ConfigFacts {
        let ini = match ini_path {
            Some(p) => sysconfig::ini::load(p).ok(),
            None => sysconfig::ini::parse_str(
                sysconfig::printer::SIMULATED_PRINTER_CFG,
                Path::new(sysconfig::printer::SIMULATED_PRINTER_NAME),
            )
            .ok(),
        };
        let mut config = Map::new();
        let mut settings = Map::new();
        for section in ini.iter().flat_map(|f| f.sections()) {
            let mut raw = Map::new();
            let mut low = Map::new();
            for (k, v) in section.options() {
                raw.insert(k.to_string(), Value::from(v.text.clone()));
                low.insert(k.to_lowercase(), Value::from(v.text.clone()));
            }
            config.insert(section.name().to_string(), Value::Object(raw));
            settings.insert(section.name().to_lowercase(), Value::Object(low));
        }
        let mut axis_minimum = [0.0; 4];
        let mut axis_maximum = [0.0; 4];
        for (i, axis) in ["stepper_x", "stepper_y", "stepper_z"].iter().enumerate() {
            if let Some(s) = cfg.stepper(axis) {
                axis_minimum[i] = s.position_min;
                axis_maximum[i] = s.position_max;
            }
        }
        let sdcard = settings
            .get("virtual_sdcard")
            .and_then(|s| s.get("path"))
            .and_then(Value::as_str)
            .map(|p| match (p.strip_prefix("~/"), std::env::var_os("HOME")) {
                (Some(rest), Some(home)) => Path::new(&home).join(rest),
                _ => Path::new(p).to_path_buf(),
            });
        ConfigFacts {
            sdcard,
            config: Value::Object(config),
            settings: Value::Object(settings),
            axis_minimum,
            axis_maximum,
            max_velocity: cfg.printer.max_velocity,
            max_accel: cfg.printer.max_accel,
            minimum_cruise_ratio: cfg.printer.minimum_cruise_ratio,
            square_corner_velocity: cfg.printer.square_corner_velocity,
            steppers: cfg.steppers.iter().map(|s| s.name.clone()).collect(),
            has_extruder: cfg.extruder.is_some(),
            thermal: ThermalFacts::new(cfg),
        }
    }
}

/// Everything the objects are built from at one moment.
#[derive(Debug)]
pub struct Snapshot<'a> {
    pub state: ServiceState,
    pub state_message: &'a str,
    /// The open printer's status (`None` while starting or after a failed start).
    pub status: Option<Status>,
    pub latency: Option<Latency>,
    pub config: Option<&'a ConfigFacts>,
    pub print: &'a PrintInfo,
    /// Process CPU seconds, load average, available memory (kB).
    pub system: SystemFacts,
}

/// `system_stats`.
#[derive(Debug, Clone, Copy, Default)]
pub struct SystemFacts {
    pub sysload: f64,
    pub cputime: f64,
    pub memavail: u64,
}

impl SystemFacts {
    /// Reads /proc (zeros where it cannot be read).
    pub fn read() -> SystemFacts {
        let sysload = std::fs::read_to_string("/proc/loadavg")
            .ok()
            .and_then(|s| s.split_whitespace().next().and_then(|v| v.parse().ok()))
            .unwrap_or(0.0);
        let memavail = std::fs::read_to_string("/proc/meminfo")
            .ok()
            .and_then(|s| {
                s.lines()
                    .find(|l| l.starts_with("MemAvailable:"))
                    .and_then(|l| l.split_whitespace().nth(1).and_then(|v| v.parse().ok()))
            })
            .unwrap_or(0);
        // utime and stime, fields 14 and 15 of /proc/self/stat, in clock ticks (100 Hz on
        // Linux's user ABI); the command name (field 2) may hold spaces, so count after ')'.
        let cputime = std::fs::read_to_string("/proc/self/stat")
            .ok()
            .and_then(|s| {
                let after = s.rsplit_once(')')?.1;
                let f: Vec<&str> = after.split_whitespace().collect();
                let utime: f64 = f.get(11)?.parse().ok()?;
                let stime: f64 = f.get(12)?.parse().ok()?;
                Some((utime + stime) / 100.0)
            })
            .unwrap_or(0.0);
        SystemFacts {
            sysload,
            cputime,
            memavail,
        }
    }
}

/// Klipper's `bed_mesh` object.
fn bed_mesh(m: &crate::events::BedMeshStatus) -> Value {
    let profiles: Map<String, Value> = m.profiles.iter().map(|p| (p.clone(), json!({}))).collect();
    json!({"profile_name": m.profile_name, "mesh_min": m.mesh_min, "mesh_max": m.mesh_max,
           "probed_matrix": m.probed_matrix, "mesh_matrix": m.mesh_matrix, "profiles": profiles})
}

/// The names `objects/list` reports for a printer with these MCUs and configuration.
pub fn names(mcus: &[String], config: Option<&ConfigFacts>) -> Vec<String> {
    let mut names: Vec<String> = [
        "webhooks",
        "configfile",
        "toolhead",
        "gcode_move",
        "print_stats",
        "virtual_sdcard",
        "pause_resume",
        "display_status",
        "idle_timeout",
        "system_stats",
        "motion_report",
        "query_endstops",
        "latency",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    names.extend(config.iter().flat_map(|c| c.thermal.objects.iter().cloned()));
    if config.is_some_and(|c| c.config.get("bed_mesh").is_some()) {
        names.push("bed_mesh".to_string());
    }
    for m in mcus {
        names.push(if m == "mcu" {
            "mcu".to_string()
        } else {
            format!("mcu {m}")
        });
    }
    names
}

/// Klipper's `save_config_pending` and `save_config_pending_items` (section → option → value;
/// a section SAVE_CONFIG will remove has no items).
fn pending_items(changes: &sysconfig::autosave::Changes) -> (bool, Map<String, Value>) {
    let mut items = Map::new();
    for (section, change) in changes.items() {
        if let sysconfig::autosave::SectionChange::Set(opts) = change {
            let opts: Map<String, Value> = opts
                .iter()
                .map(|(k, v)| (k.clone(), Value::String(v.clone())))
                .collect();
            items.insert(section.clone(), Value::Object(opts));
        }
    }
    (!changes.is_empty(), items)
}

/// Every object's status at this snapshot, by name.
pub fn all(s: &Snapshot<'_>) -> Map<String, Value> {
    let mut out = Map::new();
    out.insert(
        "webhooks".into(),
        json!({"state": s.state.name(), "state_message": s.state_message}),
    );
    let (config, settings) = match s.config {
        Some(c) => (c.config.clone(), c.settings.clone()),
        None => (json!({}), json!({})),
    };
    let status = s.status.as_ref();
    let (pending, items) = status.map_or((false, Map::new()), |st| pending_items(&st.save_config_pending));
    out.insert(
        "configfile".into(),
        json!({"config": config, "settings": settings, "save_config_pending": pending,
               "save_config_pending_items": items, "warnings": []}),
    );
    let position = status.map(|st| st.position).unwrap_or([0.0; 4]);
    let homed_axes: String = status
        .map(|st| {
            ["x", "y", "z"]
                .iter()
                .zip(st.homed)
                .filter(|(_, h)| *h)
                .map(|(a, _)| *a)
                .collect()
        })
        .unwrap_or_default();
    let printing = matches!(status.map(|st| &st.state), Some(PrinterState::Printing));
    out.insert("toolhead".into(), toolhead(s, position, homed_axes));
    if let Some(m) = status.and_then(|st| st.bed_mesh.as_ref()) {
        out.insert("bed_mesh".into(), bed_mesh(m));
    }
    out.insert(
        "gcode_move".into(),
        json!({"position": position, "gcode_position": position,
               "homing_origin": [0.0, 0.0, 0.0, 0.0]}),
    );
    print_objects(&mut out, s.print, printing);
    out.insert(
        "system_stats".into(),
        json!({"sysload": s.system.sysload, "cputime": s.system.cputime,
               "memavail": s.system.memavail}),
    );
    out.insert(
        "motion_report".into(),
        json!({"live_position": position,
               "steppers": s.config.map(|c| c.steppers.clone()).unwrap_or_default(),
               "trapq": ["toolhead"]}),
    );
    out.insert("query_endstops".into(), json!({"last_query": {}}));
    mcu_objects(&mut out, status.map(|st| st.mcus.as_slice()).unwrap_or(&[]));
    out.insert("latency".into(), latency(s.latency.as_ref()));
    if let Some(c) = s.config {
        thermal(&mut out, &c.thermal, status);
    }
    out
}

/// The `toolhead` object: position, homed axes, times and the configured limits.
fn toolhead(s: &Snapshot<'_>, position: [f64; 4], homed_axes: String) -> Value {
    let status = s.status.as_ref();
    let print_time = status.map(|st| st.print_time).unwrap_or(0.0);
    let mut toolhead = json!({
        "homed_axes": homed_axes,
        "position": position,
        "print_time": status.map(|st| st.planned_until.max(st.print_time)).unwrap_or(0.0),
        "estimated_print_time": print_time,
        "extruder": if s.config.is_some_and(|c| c.has_extruder) { "extruder" } else { "" },
    });
    if let (Some(c), Some(obj)) = (s.config, toolhead.as_object_mut()) {
        obj.insert("axis_minimum".into(), json!(c.axis_minimum));
        obj.insert("axis_maximum".into(), json!(c.axis_maximum));
        obj.insert("max_velocity".into(), json!(c.max_velocity));
        obj.insert("max_accel".into(), json!(c.max_accel));
        obj.insert("minimum_cruise_ratio".into(), json!(c.minimum_cruise_ratio));
        obj.insert("square_corner_velocity".into(), json!(c.square_corner_velocity));
    }
    toolhead
}

/// The objects of the print job: `print_stats`, `virtual_sdcard`, `pause_resume`,
/// `display_status` and `idle_timeout` (`printing`: the printer is printing).
fn print_objects(out: &mut Map<String, Value>, pr: &PrintInfo, printing: bool) {
    out.insert(
        "print_stats".into(),
        json!({"filename": pr.filename, "total_duration": pr.total_duration(),
               "print_duration": pr.print_duration(), "filament_used": 0.0,
               "state": pr.state.name(), "message": pr.message,
               "info": {"total_layer": null, "current_layer": null}}),
    );
    out.insert(
        "virtual_sdcard".into(),
        json!({"file_path": pr.file_path.as_ref().map(|p| p.display().to_string()),
               "progress": pr.progress(), "is_active": pr.is_active(),
               "file_position": pr.file_position, "file_size": pr.file_size}),
    );
    out.insert(
        "pause_resume".into(),
        json!({"is_paused": pr.state == PrintState::Paused}),
    );
    out.insert(
        "display_status".into(),
        json!({"progress": pr.m73_progress.unwrap_or_else(|| pr.progress()),
               "message": pr.display_message}),
    );
    out.insert(
        "idle_timeout".into(),
        json!({"state": if printing || pr.is_active() { "Printing" } else { "Ready" },
               "printing_time": if pr.is_active() { pr.print_duration() } else { 0.0 }}),
    );
}

/// One `mcu` / `mcu NAME` object per MCU with its link statistics.
fn mcu_objects(out: &mut Map<String, Value>, mcus: &[(String, links::mcu::LinkStats)]) {
    for (name, stats) in mcus {
        let key = if name == "mcu" {
            "mcu".to_string()
        } else {
            format!("mcu {name}")
        };
        let q = &stats.queue;
        out.insert(
            key,
            json!({"last_stats": {
                "mcu_awake": stats.mcu_awake, "mcu_task_avg": stats.mcu_task_avg,
                "mcu_task_stddev": stats.mcu_task_stddev, "bytes_write": q.bytes_write,
                "bytes_read": q.bytes_read, "bytes_retransmit": q.bytes_retransmit,
                "bytes_invalid": q.bytes_invalid, "send_seq": q.send_seq,
                "receive_seq": q.receive_seq, "retransmit_seq": q.retransmits,
                "srtt": q.srtt, "rttvar": q.rttvar, "rto": q.rto,
                "ready_bytes": q.ready_bytes, "freq": stats.clock_freq}}),
        );
    }
}

/// The thermal objects with Klipper's fields: heaters (`temperature`, `target`, `power`; the
/// extruder's `can_extrude`), fans (`speed`, `rpm`; a temperature fan's `temperature` and
/// `target`), temperature sensors (`temperature`, `measured_min_temp`, `measured_max_temp`)
/// and `heaters`. Before the heater loop's first reading the values are 0.
fn thermal(out: &mut Map<String, Value>, facts: &ThermalFacts, status: Option<&Status>) {
    let num = |v: f64| if v.is_finite() { v } else { 0.0 };
    out.insert(
        "heaters".into(),
        json!({"available_heaters": facts.available_heaters,
               "available_sensors": facts.available_sensors, "available_monitors": []}),
    );
    for name in &facts.objects {
        if name == "heaters" {
            continue;
        }
        let (kind, bare) = name.split_once(' ').unwrap_or((name.as_str(), name.as_str()));
        let is_extruder = planner::extruders::extruder_index(kind).is_some();
        let value = match kind {
            _ if is_extruder || kind == "heater_bed" || kind == "heater_generic" => {
                let h = status.and_then(|st| st.heaters.iter().find(|h| h.name == bare));
                let (t, target, power) =
                    h.map_or((0.0, 0.0, 0.0), |h| (num(h.temperature), h.target, h.power));
                let mut v = json!({"temperature": t, "target": target, "power": power});
                if let Some((_, min)) = facts.min_extrude_temp.iter().find(|(n, _)| n == kind) {
                    v["can_extrude"] = json!(t >= *min);
                }
                v
            }
            "temperature_sensor" => {
                let sensor = status.and_then(|st| st.sensors.iter().find(|x| x.name == bare));
                let (t, lo, hi) = sensor.map_or((0.0, 0.0, 0.0), |x| {
                    (
                        num(x.temperature),
                        num(x.measured_min_temp),
                        num(x.measured_max_temp),
                    )
                });
                json!({"temperature": t, "measured_min_temp": lo, "measured_max_temp": hi})
            }
            _ => {
                let fan = status.and_then(|st| st.fans.iter().find(|f| f.kind == kind && f.name == bare));
                let mut v = json!({"speed": fan.map_or(0.0, |f| f.speed), "rpm": fan.and_then(|f| f.rpm)});
                if kind == "temperature_fan" {
                    v["temperature"] = json!(num(fan.and_then(|f| f.temperature).unwrap_or(0.0)));
                    v["target"] = json!(num(fan.and_then(|f| f.target).unwrap_or(0.0)));
                }
                v
            }
        };
        out.insert(name.clone(), value);
    }
}

/// Cadence's `latency` object: lead margin (ms) and the hand-off and planner wake-up (µs)
/// histogram summaries of the session.
fn latency(l: Option<&Latency>) -> Value {
    let Some(l) = l else {
        return json!({});
    };
    let ms = |t: u64| l.lead_ms(t);
    let lead = &l.lead_margin;
    let us = |h: &rt_core::hist::Summary| {
        json!({"count": h.count, "p50": h.p50 as f64 / 1e3, "p99": h.p99 as f64 / 1e3,
               "p999": h.p999 as f64 / 1e3, "max": h.max as f64 / 1e3})
    };
    json!({
        "lead_margin_ms": {"count": lead.count, "violations": lead.negative,
            "min": ms(lead.min), "p0_1": ms(lead.p0_1), "p1": ms(lead.p1), "p50": ms(lead.p50)},
        "handoff_us": us(&l.handoff),
        "wake_planner_us": us(&l.wake_planner),
    })
}

/// The fields of `status` a query asked for: `None` → every field, else the listed ones that
/// exist. Unknown objects give `{}` as Klipper does.
pub fn select(all: &Map<String, Value>, name: &str, fields: Option<&[String]>) -> Map<String, Value> {
    let Some(Value::Object(obj)) = all.get(name) else {
        return Map::new();
    };
    match fields {
        None => obj.clone(),
        Some(list) => list
            .iter()
            .map(|f| (f.clone(), obj.get(f).cloned().unwrap_or(Value::Null)))
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::events::{FanStatus, HeaterStatus, SensorStatus};

    /// The thermal objects carry Klipper's fields, from the config's sections and the status.
    #[test]
    fn thermal_objects_have_klippers_fields() {
        let text = format!(
            "{}\n[temperature_sensor chamber]\nsensor_type: Generic 3950\nsensor_pin: PF2\n\
             [temperature_fan exhaust]\npin: PE4\nsensor_type: Generic 3950\nsensor_pin: PF3\n\
             min_temp: 0\nmax_temp: 80\ncontrol: watermark\n",
            sysconfig::printer::SIMULATED_PRINTER_CFG
        );
        let cfg = sysconfig::parse_str(&text, Path::new("printer.cfg")).unwrap();
        let facts = ConfigFacts::new(&cfg, None);
        let names = names(&["mcu".to_string()], Some(&facts));
        for n in [
            "heaters",
            "extruder",
            "heater_bed",
            "fan",
            "heater_fan hotend_fan",
            "temperature_sensor chamber",
            "temperature_fan exhaust",
            "mcu",
        ] {
            assert!(names.iter().any(|x| x == n), "{n} not in {names:?}");
        }
        let mut status = crate::events::Status {
            state: PrinterState::Ready,
            position: [0.0; 4],
            homed: [false; 3],
            planned_until: 0.0,
            print_time: 0.0,
            mcus: Vec::new(),
            events_dropped: 0,
            save_config_pending: Default::default(),
            bed_mesh: None,
            heaters: vec![HeaterStatus {
                name: "extruder".into(),
                temperature: 200.0,
                target: 210.0,
                power: 0.5,
            }],
            fans: vec![FanStatus {
                name: "exhaust".into(),
                kind: "temperature_fan",
                speed: 1.0,
                temperature: Some(25.0),
                target: Some(20.0),
                rpm: None,
            }],
            sensors: vec![SensorStatus {
                name: "chamber".into(),
                temperature: 24.0,
                measured_min_temp: 23.0,
                measured_max_temp: 26.0,
            }],
        };
        let mesh = crate::events::BedMeshStatus {
            profile_name: "default".into(),
            mesh_min: [10.0, 10.0],
            mesh_max: [190.0, 190.0],
            probed_matrix: vec![vec![0.1, 0.2]; 2],
            mesh_matrix: vec![vec![0.1, 0.15, 0.2]; 3],
            profiles: vec!["default".into()],
        };
        assert_eq!(
            bed_mesh(&mesh),
            json!({"profile_name": "default", "mesh_min": [10.0, 10.0], "mesh_max": [190.0, 190.0],
                   "probed_matrix": [[0.1, 0.2], [0.1, 0.2]],
                   "mesh_matrix": [[0.1, 0.15, 0.2], [0.1, 0.15, 0.2], [0.1, 0.15, 0.2]],
                   "profiles": {"default": {}}})
        );
        let mut out = Map::new();
        thermal(&mut out, &facts.thermal, Some(&status));
        assert_eq!(
            out["extruder"],
            json!({"temperature": 200.0, "target": 210.0, "power": 0.5, "can_extrude": true})
        );
        assert_eq!(
            out["heater_bed"],
            json!({"temperature": 0.0, "target": 0.0, "power": 0.0})
        );
        assert_eq!(
            out["temperature_fan exhaust"],
            json!({"speed": 1.0, "rpm": null, "temperature": 25.0, "target": 20.0})
        );
        assert_eq!(
            out["temperature_sensor chamber"],
            json!({"temperature": 24.0, "measured_min_temp": 23.0, "measured_max_temp": 26.0})
        );
        assert_eq!(out["fan"], json!({"speed": 0.0, "rpm": null}));
        assert_eq!(
            out["heaters"]["available_sensors"],
            json!([
                "extruder",
                "heater_bed",
                "temperature_sensor chamber",
                "temperature_fan exhaust"
            ])
        );
        status.heaters[0].temperature = f64::NAN;
        thermal(&mut out, &facts.thermal, Some(&status));
        assert_eq!(out["extruder"]["temperature"], json!(0.0));
    }

    #[test]
    fn pending_save_config_items_are_klippers_shape() {
        let mut changes = sysconfig::autosave::Changes::default();
        assert_eq!(pending_items(&changes), (false, Map::new()));
        changes.set("extruder", "pid_Kp", "22.200");
        changes.set("extruder", "control", "pid");
        changes.remove_section("bed_mesh default");
        let (pending, items) = pending_items(&changes);
        assert!(pending);
        assert_eq!(
            Value::Object(items),
            json!({"extruder": {"pid_kp": "22.200", "control": "pid"}})
        );
    }
}
