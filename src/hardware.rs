//! The printer's hardware as the host drives it (not the planner's `planner::machine`, the
//! G-code state machine): which steppers exist, on which MCU and oid, with which pins, and the
//! planner configuration derived from printer.cfg.

use planner::pipeline::{ExtruderLink, Pipeline, PipelineConfig, PipelineOptions, StepperSpec};
use planner::toolhead::ToolheadConfig;
use sysconfig::printer::{BlTouchSection, MotorSection, PinRef, PrinterConfig, ProbeSection, PROBE_PIN_MCU};

/// One stepper as the host addresses it on its MCU.
#[derive(Debug, Clone)]
pub struct StepperOut {
    /// Config section name, e.g. `stepper_x`, `extruder`.
    pub name: String,
    /// The MCU that drives it.
    pub mcu: String,
    /// Object id on that MCU.
    pub oid: u8,
    /// Axis index 0..=3 (X, Y, Z, E).
    pub axis: usize,
    pub step_pin: PinRef,
    pub dir_pin: PinRef,
    /// Driver enable pin (configured as a digital output, active while printing).
    pub enable_pin: Option<PinRef>,
    /// Minimum step pulse width in seconds (Klipper's default: 2 µs).
    pub step_pulse_duration: f64,
    pub step_dist: f64,
    /// An extruder stepper's start (see [`planner::pipeline::ExtruderLink`]).
    pub extruder: Option<ExtruderLink>,
}

impl StepperOut {
    /// The stepper of section `name` moving `axis`, on its step pin's MCU (object id assigned
    /// later).
    fn new(name: String, axis: usize, motor: &MotorSection) -> StepperOut {
        StepperOut {
            name,
            mcu: motor.step_pin.mcu.clone(),
            oid: 0,
            axis,
            step_pin: motor.step_pin.clone(),
            dir_pin: motor.dir_pin.clone(),
            enable_pin: motor.enable_pin.clone(),
            step_pulse_duration: motor.step_pulse_duration.unwrap_or(DEFAULT_STEP_PULSE_DURATION),
            step_dist: motor.step_dist(),
            extruder: None,
        }
    }
}

/// World axis names of the rails that move one toolhead axis alone.
const AXIS_NAMES: [&str; 3] = ["x", "y", "z"];

/// Klipper's default `step_pulse_duration`.
pub const DEFAULT_STEP_PULSE_DURATION: f64 = 2e-6;

/// One axis endstop as the host addresses it on its MCU, with the axis' homing settings.
#[derive(Debug, Clone)]
pub struct EndstopOut {
    /// The stepper section it belongs to, e.g. `stepper_z`.
    pub stepper: String,
    /// Axis index 0..=2.
    pub axis: usize,
    pub pin: PinRef,
    /// Object id on the endstop's MCU (after that MCU's steppers).
    pub oid: u8,
    pub position_endstop: f64,
    pub position_min: f64,
    pub position_max: f64,
    pub homing_speed: f64,
    pub second_homing_speed: f64,
    pub homing_retract_dist: f64,
    pub homing_positive_dir: bool,
    /// The pin is the `[probe]`'s (the simulator triggers it at `[simulator] bed_surface_z`).
    pub probe: bool,
    /// Sensorless: the pin is the diag pin of this driver (index in [`Machine::tmc`]), whose
    /// virtual endstop the axis homes on.
    pub sensorless: Option<usize>,
    /// A further motor's own endstop (`[stepper_z1] endstop_pin`): that motor's index in
    /// [`Machine::steppers`], which alone stops on it (the rail's homing options apply).
    /// `None`: the rail's endstop, which stops the rail's other motors.
    pub motor: Option<usize>,
}

/// The `[probe]`: its endstop (on its MCU) and its settings.
#[derive(Debug, Clone)]
pub struct ProbeOut {
    /// The probe pin as an endstop of Z: `stepper` is `probe`, `position_endstop` the
    /// `z_offset`, `homing_speed` the probing speed.
    pub endstop: EndstopOut,
    /// It is also Z's endstop (`probe:z_virtual_endstop`): one MCU object serves both.
    pub z_virtual_endstop: bool,
    /// Z the probing move heads for (`z_position`, default `[stepper_z] position_min`).
    pub z_position: f64,
    pub cfg: ProbeSection,
}

/// A `[bltouch]`'s servo output (a soft-PWM digital out on its MCU) and its settings; the
/// probe it is, is the machine's [`ProbeOut`].
#[derive(Debug, Clone)]
pub struct BlTouchOut {
    pub control_pin: PinRef,
    /// Object id of the control output on its MCU (after that MCU's steppers and endstops).
    pub oid: u8,
    pub cfg: BlTouchSection,
    /// Its command timing and session state, kept across G-code commands.
    pub state: std::sync::Arc<std::sync::Mutex<crate::homing::bltouch::BlTouchState>>,
}

/// Everything derived from a printer.cfg that `print` needs.
#[derive(Debug, Clone)]
pub struct Machine {
    pub steppers: Vec<StepperOut>,
    pub endstops: Vec<EndstopOut>,
    pub probe: Option<ProbeOut>,
    /// `[bltouch]`: the probe's servo.
    pub bltouch: Option<BlTouchOut>,
    /// `[smart_effector]`: its control output and probing settings.
    pub smart_effector: Option<crate::homing::smart_effector::SmartEffectorOut>,
    /// The steppers' TMC drivers.
    pub tmc: Vec<crate::tmc::TmcOut>,
    /// `[z_tilt]`.
    pub z_tilt: Option<sysconfig::printer::ZTiltSection>,
    /// `[quad_gantry_level]` (its `z_positions` are the four corners).
    pub quad_gantry_level: Option<sysconfig::printer::ZTiltSection>,
    /// `[screws_tilt_adjust]`.
    pub screws_tilt_adjust: Option<sysconfig::printer::ScrewsSection>,
    /// `[bed_screws]`.
    pub bed_screws: Option<sysconfig::printer::ScrewsSection>,
    /// `[bed_mesh]`: its settings, profiles and the mesh in use.
    pub bed_mesh: Option<crate::homing::bed_mesh::BedMeshOut>,
    /// `[simulator] bed_surface_z`: where simulated probe pins trigger.
    pub sim_bed_surface_z: f64,
    /// `[simulator]`'s bed shape (tilt and warp), for the simulated probe.
    pub sim_bed: sysconfig::printer::SimulatorSection,
    pub toolhead: ToolheadConfig,
    pub home_position: [f64; 3],
    /// Kinematics and pressure advance for the planner.
    pub options: PipelineOptions,
    /// Some MCU is a real board (not `serial: simulator`): heat asked of it is warned about.
    pub real_board: bool,
    /// `[gcode_macro]` sections, run by the G-code feed, and the `[homing_override]` script.
    pub macros: Vec<planner::gcode::macros::MacroDef>,
    /// Heaters, temperature sensors and fans.
    pub thermal: crate::heaters::objects::Thermal,
    /// How G28 runs (`[safe_z_home]`, `[homing_override]`).
    pub homing: crate::homing::procedure::HomingProcedure,
    /// `[respond]`'s default prefix, when the printer has the section.
    pub respond_prefix: Option<String>,
    /// `[delayed_gcode]`, `[save_variables]`, `[idle_timeout]`, `[display_status]`,
    /// `[force_move]` (their scripts are among `macros`).
    pub host: planner::gcode::host::HostConfig,
    /// The printer.cfg it came from (SAVE_CONFIG rewrites it).
    pub config_path: std::path::PathBuf,
}

/// Why a printer.cfg describes no printer the host can drive; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum HardwareError {
    /// printer.cfg could not be read or is invalid (file, line, section, option).
    #[error("{0}")]
    Config(#[from] sysconfig::ConfigError),
    /// The built-in simulated printer's config did not load.
    #[error("built-in printer: {0}")]
    Builtin(sysconfig::ConfigError),
    /// The planner's configuration could not be derived (e.g. unsupported kinematics).
    #[error("{file}: {why}")]
    Planning { file: std::path::PathBuf, why: String },
    /// A `[probe]` the printer cannot have.
    #[error("{file}: {why}")]
    Probe { file: std::path::PathBuf, why: String },
    /// Heaters, sensors or fans the host cannot drive (unknown sensor type, bad reference).
    #[error("{file}: {source}")]
    Thermal {
        file: std::path::PathBuf,
        #[source]
        source: crate::heaters::objects::ThermalError,
    },
}

/// A pin an MCU's dictionary does not have (`what`: the section and option, or the pin).
#[derive(Debug, thiserror::Error)]
#[error("{what}: {source}")]
pub struct PinError {
    pub what: String,
    #[source]
    pub source: links::dict::DictError,
}

/// Why the G-code feed's macros and host objects could not be set up.
#[derive(Debug, thiserror::Error)]
pub enum MacrosError {
    /// A `[gcode_macro]` does not compile.
    #[error(transparent)]
    Macro(Box<planner::gcode::macros::MacroError>),
    /// The `[save_variables]` file could not be read or created.
    #[error("[save_variables] filename {}: {source}", .path.display())]
    VariablesFile {
        path: std::path::PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The `[save_variables]` file's contents.
    #[error("[save_variables] {}: {source}", .path.display())]
    Variables {
        path: std::path::PathBuf,
        #[source]
        source: planner::gcode::host::HostError,
    },
}

from_boxed!(MacrosError, Macro, planner::gcode::macros::MacroError);

impl From<MacrosError> for String {
    fn from(e: MacrosError) -> String {
        e.to_string()
    }
}

impl From<HardwareError> for String {
    fn from(e: HardwareError) -> String {
        e.to_string()
    }
}

/// The steppers of the X, Y and Z rails (a rail's further motors, `stepper_z1`…, after
/// them: they move with it and stop on its endstop, or on their own) and the endstops (the
/// rails', then the further motors' own), objects not yet numbered.
fn rails(cfg: &PrinterConfig, tmc: &[crate::tmc::TmcOut]) -> (Vec<StepperOut>, Vec<EndstopOut>) {
    let mut steppers = Vec::new();
    let mut endstops = Vec::new();
    for (axis, s) in cfg.steppers.iter().enumerate().take(3) {
        let name = s.name.clone();
        if let (Some(pin), Some(position_endstop)) = (&s.endstop_pin, s.position_endstop) {
            // `probe:z_virtual_endstop`: the probe's own pin.
            let probe_pin = cfg.probe.as_ref().filter(|_| pin.mcu == PROBE_PIN_MCU);
            // `tmc2209_stepper_x:virtual_endstop`: the driver's diag pin.
            let sensorless = tmc.iter().position(|t| t.cfg.chip() == pin.mcu);
            let diag_pin = sensorless.and_then(|i| tmc[i].cfg.diag_pin.clone());
            endstops.push(EndstopOut {
                stepper: name.clone(),
                axis,
                pin: match (probe_pin, diag_pin) {
                    (Some(p), _) => p.pin.clone(),
                    (None, Some(d)) => d,
                    (None, None) => pin.clone(),
                },
                probe: probe_pin.is_some(),
                sensorless,
                oid: 0,
                position_endstop,
                position_min: s.position_min,
                position_max: s.position_max,
                homing_speed: s.homing_speed,
                second_homing_speed: s.second_homing_speed,
                homing_retract_dist: s.homing_retract_dist,
                homing_positive_dir: s.homing_positive_dir,
                motor: None,
            });
        }
        steppers.push(StepperOut::new(name, axis, &s.motor));
    }
    for s in &cfg.extra_steppers {
        // Its own endstop takes the rail endstop's homing options (sysconfig made sure the
        // rail has one).
        let rail = endstops
            .iter()
            .find(|e| e.axis == s.rail && e.motor.is_none())
            .cloned();
        if let (Some(pin), Some(rail)) = (&s.endstop_pin, rail) {
            endstops.push(EndstopOut {
                stepper: s.name.clone(),
                pin: pin.clone(),
                motor: Some(steppers.len()),
                probe: false,
                sensorless: None,
                ..rail
            });
        }
        steppers.push(StepperOut::new(s.name.clone(), s.rail, &s.motor));
    }
    (steppers, endstops)
}

/// Numbers the objects per MCU, steppers first, then endstops (the trsync comes last); the
/// next free oid of each MCU. A stepper lives on its step pin's MCU, any configured one
/// (sysconfig checked that the MCU exists and that the dir pin is on the same one).
fn number_objects(
    steppers: &mut [StepperOut],
    endstops: &mut [EndstopOut],
) -> std::collections::HashMap<String, u8> {
    let mut next: std::collections::HashMap<String, u8> = std::collections::HashMap::new();
    for s in steppers.iter_mut() {
        let n = next.entry(s.mcu.clone()).or_insert(0);
        s.oid = *n;
        *n += 1;
    }
    for e in endstops.iter_mut() {
        let n = next.entry(e.pin.mcu.clone()).or_insert(0);
        e.oid = *n;
        *n += 1;
    }
    next
}

impl Machine {
    /// Derives the machine from a validated config: steppers and endstops on any of its MCUs.
    pub fn from_config(cfg: &PrinterConfig) -> Result<Machine, HardwareError> {
        // Toolhead limits, kinematics and home position come from one shared derivation.
        let (planning, kinematics) =
            sysconfig::planning::pipeline_config(cfg, 1.0, 25e-6).map_err(|e| HardwareError::Planning {
                file: cfg.source.clone(),
                why: e.to_string(),
            })?;
        let tmc = crate::tmc::drivers(cfg);
        let (mut steppers, mut endstops) = rails(cfg, &tmc);
        let toolhead = planning.toolhead;
        let home = planning.home_position;
        for (name, motor, link) in sysconfig::planning::extruder_steppers(cfg) {
            let mut s = StepperOut::new(name, 3, motor);
            s.extruder = link;
            steppers.push(s);
        }
        let mut next = number_objects(&mut steppers, &mut endstops);
        let probe = match &cfg.probe {
            Some(p) => Some(probe_out(p, cfg, &endstops, &mut next)?),
            None => None,
        };
        // The BLTouch's servo output: the next oid on its MCU, after the endstops.
        let bltouch = cfg.bltouch.as_ref().map(|b| {
            let n = next.entry(b.control_pin.mcu.clone()).or_insert(0);
            *n += 1;
            BlTouchOut {
                control_pin: b.control_pin.clone(),
                oid: *n - 1,
                cfg: b.clone(),
                state: Default::default(),
            }
        });
        // A Smart Effector's control output: the next oid on its MCU, after the endstops.
        let smart_effector = cfg.smart_effector.as_ref().map(|e| {
            crate::homing::smart_effector::SmartEffectorOut::new(e, |mcu| {
                let n = next.entry(mcu.to_string()).or_insert(0);
                *n += 1;
                *n - 1
            })
        });
        let options = sysconfig::planning::pipeline_options(cfg, kinematics);
        let thermal =
            crate::heaters::objects::Thermal::from_config(cfg).map_err(|source| HardwareError::Thermal {
                file: cfg.source.clone(),
                source,
            })?;
        let z_on_probe = probe.as_ref().is_some_and(|p| p.z_virtual_endstop);
        Ok(Machine {
            steppers,
            endstops,
            probe,
            bltouch,
            smart_effector,
            tmc,
            bed_mesh: cfg.bed_mesh.clone().map(crate::homing::bed_mesh::BedMeshOut::new),
            z_tilt: cfg.z_tilt.clone(),
            quad_gantry_level: cfg.quad_gantry_level.clone(),
            screws_tilt_adjust: cfg.screws_tilt_adjust.clone(),
            bed_screws: cfg.bed_screws.clone(),
            sim_bed_surface_z: cfg.simulator.bed_surface_z,
            sim_bed: cfg.simulator.clone(),
            toolhead,
            home_position: home,
            options,
            real_board: cfg.mcus.iter().any(|m| !m.is_simulated()),
            macros: cfg
                .macros
                .iter()
                .chain(cfg.homing_override.as_ref().map(|o| &o.script))
                .chain(
                    cfg.probe
                        .iter()
                        .flat_map(|p| p.activate_gcode.iter().chain(&p.deactivate_gcode)),
                )
                .chain(&cfg.host.scripts)
                .cloned()
                .collect(),
            homing: crate::homing::procedure::HomingProcedure {
                safe_z_home: cfg.safe_z_home.clone(),
                homing_override: cfg.homing_override.clone(),
                probe_scripts: crate::homing::procedure::ProbeScripts {
                    activate: cfg.probe.as_ref().is_some_and(|p| p.activate_gcode.is_some()),
                    deactivate: cfg.probe.as_ref().is_some_and(|p| p.deactivate_gcode.is_some()),
                    z_on_probe,
                },
            },
            thermal,
            respond_prefix: cfg.respond.clone(),
            host: cfg.host.host.clone(),
            config_path: cfg.source.clone(),
        })
    }

    /// The G-code feed's macros and host objects for a print starting at print time `start`:
    /// `[gcode_macro]`s, `[respond]`, and the `[save_variables]` file read (created empty when
    /// absent, as Klipper does).
    pub fn macros(&self, start: f64) -> Result<planner::gcode::macros::Macros, MacrosError> {
        let mut macros = planner::gcode::macros::Macros::new(self.macros.clone())?
            .with_respond(self.respond_prefix.clone())
            .with_host(&self.host, start);
        if let Some(path) = macros.host().variables_file().cloned() {
            let text = match std::fs::read_to_string(&path) {
                Ok(t) => t,
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                    std::fs::write(&path, "").map_err(|source| MacrosError::VariablesFile {
                        path: path.clone(),
                        source,
                    })?;
                    String::new()
                }
                Err(source) => return Err(MacrosError::VariablesFile { path, source }),
            };
            macros
                .host_mut()
                .load_variables(&text)
                .map_err(|source| MacrosError::Variables { path, source })?;
        }
        Ok(macros)
    }

    /// The planner configuration for MCU clocks at `clock_freq` ticks per print second.
    pub fn pipeline_config(&self, clock_freq: f64, max_error_s: f64) -> PipelineConfig {
        PipelineConfig {
            toolhead: self.toolhead,
            steppers: self
                .steppers
                .iter()
                .map(|s| StepperSpec {
                    name: s.name.clone(),
                    axis: s.axis,
                    step_dist: s.step_dist,
                    extruder: s.extruder,
                })
                .collect(),
            clock_freq,
            max_error_s,
            home_position: self.home_position,
        }
    }
}

/// The printer config at `path`, or the built-in simulated printer without one.
pub fn load_config(path: Option<&std::path::Path>) -> Result<PrinterConfig, HardwareError> {
    match path {
        Some(path) => Ok(sysconfig::printer::load(path)?),
        None => sysconfig::printer::builtin_simulated().map_err(HardwareError::Builtin),
    }
}

/// Print time (s) of batch mode's first move: `print --batch` writes its streams from it, and
/// `decode --check` plans again from it.
pub const BATCH_START_S: f64 = 0.25;

impl Machine {
    /// The planner of batch mode (every MCU clock counted from print time 0 at `clock_freq`),
    /// generating and compressing steps on `threads` threads.
    pub fn batch_pipeline(
        &self,
        clock_freq: f64,
        max_error_s: f64,
        threads: usize,
    ) -> Result<Pipeline, planner::machine::PlanError> {
        let options = PipelineOptions {
            threads,
            ..self.options
        };
        Pipeline::with_options(
            self.pipeline_config(clock_freq, max_error_s),
            BATCH_START_S,
            options,
        )
    }

    /// The endstop objects on MCU `mcu`, in oid order: the axis endstops, then the probe
    /// unless it is Z's endstop too.
    pub fn mcu_endstops(&self, mcu: &str) -> Vec<&EndstopOut> {
        let probe = self
            .probe
            .as_ref()
            .filter(|p| !p.z_virtual_endstop)
            .map(|p| &p.endstop);
        self.endstops
            .iter()
            .chain(probe)
            .filter(|e| e.pin.mcu == mcu)
            .collect()
    }

    /// The Smart Effector's control output on MCU `mcu` and its oid (it follows the endstops).
    pub fn mcu_smart_effector(&self, mcu: &str) -> Option<(&PinRef, u8)> {
        let (pin, oid) = self.smart_effector.as_ref()?.control.as_ref()?;
        (pin.mcu == mcu).then_some((pin, *oid))
    }

    /// The BLTouch servo output on MCU `mcu` (its object follows the endstops).
    pub fn mcu_bltouch(&self, mcu: &str) -> Option<&BlTouchOut> {
        self.bltouch.as_ref().filter(|b| b.control_pin.mcu == mcu)
    }

    /// The simulated toolhead's start coordinate of axis `axis` (0..=2): 10% of the travel
    /// away from its endstop (homing stays short), mid-travel without one.
    fn sim_start(&self, axis: usize) -> f64 {
        let (min, max) = self.toolhead.axis_limits[axis];
        match self.endstops.iter().find(|e| e.axis == axis) {
            Some(e) if e.homing_positive_dir => self.sim_trigger(e) - 0.1 * (max - min),
            Some(e) => self.sim_trigger(e) + 0.1 * (max - min),
            None => (min + max) / 2.0,
        }
    }

    /// The world axis of each rail 0..=2: its name and its start position (mm).
    fn sim_rails(&self) -> [(String, f64); 3] {
        let kin = &self.options.kinematics;
        let start = [0, 1, 2].map(|a| self.sim_start(a));
        let pos = [start[0], start[1], start[2], 0.0];
        let mut coupled = 0u8;
        [0, 1, 2].map(|rail| {
            let coeffs = kin
                .stepper(rail, 1.0)
                .ok()
                .and_then(|k| k.linear_coeffs().copied());
            match coeffs {
                // A delta tower (not linear): the old one-axis model, the carriage.
                None => (AXIS_NAMES[rail].to_string(), start[rail]),
                Some(c) if c[rail] == 1.0 && c.iter().filter(|&&v| v != 0.0).count() == 1 => {
                    (AXIS_NAMES[rail].to_string(), start[rail])
                }
                Some(c) => {
                    let name = char::from(b'a' + coupled).to_string();
                    coupled += 1;
                    (name, c.iter().zip(pos).map(|(k, p)| k * p).sum())
                }
            }
        })
    }

    /// The world coordinate an endstop of toolhead axis `axis` reads: the forward kinematics
    /// of the rails (a delta's endstop reads its tower's carriage).
    fn sim_coord(&self, axis: usize, rails: &[(String, f64); 3]) -> firmware::sim::world::Coord {
        use planner::kinematics::Kinematics;
        let kin = &self.options.kinematics;
        if matches!(kin, Kinematics::Delta(_)) {
            return firmware::sim::world::Coord::axis(&rails[axis].0);
        }
        let terms = (0..3)
            .filter_map(|rail| {
                let mut unit = [0.0; 3];
                unit[rail] = 1.0;
                let k = kin.forward(unit)[axis];
                (k != 0.0).then(|| (k, rails[rail].0.clone()))
            })
            .collect();
        firmware::sim::world::Coord { terms }
    }

    /// The simulated world's axis coordinate at which endstop `e` triggers: the bed surface for
    /// the probe, else `position_endstop`.
    /// A Z motor's switch sits `[simulator] z_endstop_offsets` (that motor's entry) higher.
    fn sim_trigger(&self, e: &EndstopOut) -> f64 {
        if e.probe {
            return self.sim_bed_surface_z;
        }
        let offset = match e.axis {
            2 => {
                let motor = e.motor.map_or(0, |i| self.rail_motor_index(i));
                self.sim_bed.z_endstop_offsets.get(motor).copied().unwrap_or(0.0)
            }
            _ => 0.0,
        };
        e.position_endstop + offset
    }

    /// Stepper `i`'s place among its rail's motors (0: the rail's own, 1: `stepper_z1`…).
    fn rail_motor_index(&self, i: usize) -> usize {
        let axis = self.steppers.get(i).map_or(usize::MAX, |s| s.axis);
        self.steppers[..i.min(self.steppers.len())]
            .iter()
            .filter(|o| o.axis == axis)
            .count()
    }

    /// The world axis stepper `i` of rail `s.axis` drives: the rail's (`z`), or a further
    /// motor's own end of the carriage (`z1`, `z2`…).
    fn sim_motor_axis(&self, i: usize, rails: &[(String, f64); 3]) -> String {
        let axis = self.steppers.get(i).map_or(0, |s| s.axis.min(2));
        match self.rail_motor_index(i) {
            0 => rails[axis].0.clone(),
            n => format!("{}{n}", rails[axis].0),
        }
    }

    /// Arguments that put a simulated MCU into the printer's shared simulated world: the world
    /// axes its steppers move (the toolhead starting 10% of each axis' travel from its endstop)
    /// and the endstops wired to its pins, each reading its axis' coordinate.
    ///
    /// World axes are the rails: a stepper that moves one toolhead axis alone drives that axis
    /// (`x`, `y`, `z`), and a rail's further motors (`stepper_z1`…) each drive their own end of
    /// the carriage (`z1`, `z2`…; the rail's endstop reads the first motor's end); the
    /// steppers of a corexy / corexz printer, which move two axes, drive `a` and `b` (in rail
    /// order), and an endstop reads the forward kinematics of them (corexy
    /// X: `0.5*a+0.5*b`). A delta's towers drive `x`, `y`, `z` and each endstop reads its tower's
    /// carriage.
    pub fn sim_world_args(&self, mcu: &str, world: &str) -> Vec<String> {
        let rails = self.sim_rails();
        let mut args = self.sim_axis_args(mcu, &rails);
        // The TMC drivers on this MCU's buses; one an axis homes on stalls where its endstop
        // would trigger, and raises DIAG on its diag pin (on this MCU).
        let endstops = &self.endstops;
        args.extend(crate::tmc::sim_args(&self.tmc, mcu, |d| {
            let e = endstops.iter().find(|e| {
                e.sensorless
                    .is_some_and(|i| self.tmc[i].cfg.stepper == d.cfg.stepper)
            })?;
            if e.pin.mcu != mcu {
                return None;
            }
            let side = if e.homing_positive_dir { "max" } else { "min" };
            let diag0 = if d.cfg.diag_field == Some("diag0_stall") {
                "diag0:"
            } else {
                ""
            };
            Some(format!(
                "{diag0}{},{},{},{side}",
                e.pin.pin,
                self.sim_coord(e.axis, &rails),
                self.sim_trigger(e)
            ))
        }));
        for e in self.mcu_endstops(mcu) {
            if e.sensorless.is_none() {
                self.sim_endstop_args(mcu, e, &rails, &mut args);
            }
        }
        // A Smart Effector's programming input, decoding the control pin.
        if let Some((pin, _)) = self.mcu_smart_effector(mcu) {
            let active_low = if pin.invert { "!" } else { "" };
            args.push("--smart-effector".to_string());
            args.push(format!("{active_low}{}", pin.pin));
        }
        if !args.is_empty() {
            args.push("--world".to_string());
            args.push(world.to_string());
        }
        args
    }

    /// `--axis` for each stepper of `mcu`: the world axis (rail end) it drives, its step pin,
    /// steps per mm and start.
    fn sim_axis_args(&self, mcu: &str, rails: &[(String, f64); 3]) -> Vec<String> {
        let mut args = Vec::new();
        for (i, s) in self.steppers.iter().enumerate() {
            if s.mcu != mcu || s.axis >= 3 {
                continue;
            }
            let steps_per_mm = if s.dir_pin.invert {
                -1.0 / s.step_dist
            } else {
                1.0 / s.step_dist
            };
            let start = rails[s.axis].1;
            // A rail's further motors each drive their own end of the carriage: `z1`, `z2`…
            let nth = self.rail_motor_index(i);
            let name = self.sim_motor_axis(i, rails);
            // A tilted simulated gantry: each Z motor's end starts that much higher.
            let tilt = match s.axis {
                2 => self.sim_bed.gantry_tilt.get(nth).copied().unwrap_or(0.0),
                _ => 0.0,
            };
            args.push("--axis".to_string());
            args.push(format!(
                "{name}={},{steps_per_mm},{}",
                s.step_pin.pin,
                start + tilt
            ));
        }
        args
    }

    /// The arguments of endstop `e` on `mcu` (not a driver's virtual endstop): the shaped bed
    /// and the gantry under a probe, then the BLTouch or the plain endstop reading its axis.
    fn sim_endstop_args(
        &self,
        mcu: &str,
        e: &EndstopOut,
        rails: &[(String, f64); 3],
        args: &mut Vec<String>,
    ) {
        // A tilted or warped simulated bed under the probe.
        if let Some(p) = self
            .probe
            .as_ref()
            .filter(|_| e.probe && self.sim_bed.bed_is_shaped())
        {
            let b = &self.sim_bed;
            args.push("--bed-surface".to_string());
            args.push(format!(
                "{}={},{},{},{},{},{},{},{}",
                e.pin.pin,
                self.sim_coord(0, rails),
                self.sim_coord(1, rails),
                p.cfg.x_offset,
                p.cfg.y_offset,
                b.bed_tilt[0],
                b.bed_tilt[1],
                b.bed_warp,
                b.bed_warp_period
            ));
        }
        if e.probe {
            self.sim_gantry_args(e, rails, args);
        }
        // A BLTouch with its servo on the same MCU: the simulated probe, deployed and
        // stowed by the servo pulses, its pin touching the bed surface.
        if let Some(b) = self.mcu_bltouch(mcu).filter(|_| e.probe) {
            let active_low = if e.pin.invert { "!" } else { "" };
            args.push("--bltouch".to_string());
            args.push(format!(
                "{active_low}{}={},{},{}",
                e.pin.pin,
                b.control_pin.pin,
                self.sim_coord(e.axis, rails),
                self.sim_trigger(e)
            ));
            return;
        }
        let side = if e.homing_positive_dir { "max" } else { "min" };
        // `!`: the pin reads 0 when triggered, as the config's inverted endstop expects.
        let active_low = if e.pin.invert { "!" } else { "" };
        // A further motor's own endstop reads that motor's end of the carriage.
        let coord = match e.motor {
            Some(i) => firmware::sim::world::Coord::axis(&self.sim_motor_axis(i, rails)),
            None => self.sim_coord(e.axis, rails),
        };
        args.push("--endstop".to_string());
        args.push(format!(
            "{active_low}{}={coord},{},{side}",
            e.pin.pin,
            self.sim_trigger(e)
        ));
    }

    /// `--gantry` for probe `e` on a gantry lifted by several Z motors (`[z_tilt]
    /// z_positions`, the corners of `[quad_gantry_level]`).
    fn sim_gantry_args(&self, e: &EndstopOut, rails: &[(String, f64); 3], args: &mut Vec<String>) {
        let gantry = (self.z_tilt.as_ref())
            .or(self.quad_gantry_level.as_ref())
            .filter(|z| (2..=4).contains(&z.z_positions.len()));
        let Some(zt) = gantry else {
            return;
        };
        let p = self
            .probe
            .as_ref()
            .map_or([0.0, 0.0], |p| [p.cfg.x_offset, p.cfg.y_offset]);
        let z = &rails[2].0;
        let motors: Vec<String> = zt
            .z_positions
            .iter()
            .enumerate()
            .map(|(n, xy)| match n {
                0 => format!("{z}:{}:{}", xy[0], xy[1]),
                n => format!("{z}{n}:{}:{}", xy[0], xy[1]),
            })
            .collect();
        args.push("--gantry".to_string());
        args.push(format!(
            "{}={},{},{},{},{}",
            e.pin.pin,
            self.sim_coord(0, rails),
            self.sim_coord(1, rails),
            p[0],
            p[1],
            motors.join(",")
        ));
    }
}

/// The probe as an endstop of Z: shares the object of Z's endstop with
/// `probe:z_virtual_endstop`, else takes the next oid on its MCU.
fn probe_out(
    p: &ProbeSection,
    cfg: &PrinterConfig,
    endstops: &[EndstopOut],
    next: &mut std::collections::HashMap<String, u8>,
) -> Result<ProbeOut, HardwareError> {
    // Z's range: `[stepper_z]`'s, or a delta's (minimum_z_position .. the lowest tower top),
    // where probing is refused when asked for (delta homing is not supported yet).
    let (z_min, z_max) = match cfg.steppers.get(2).filter(|s| s.name == "stepper_z") {
        Some(z) => (z.position_min, z.position_max),
        None => match &cfg.delta {
            Some(d) => (
                d.minimum_z_position,
                cfg.steppers
                    .iter()
                    .map(|s| s.position_max)
                    .fold(f64::INFINITY, f64::min),
            ),
            None => {
                return Err(HardwareError::Probe {
                    file: cfg.source.clone(),
                    why: "[probe] needs a [stepper_z] or delta kinematics".to_string(),
                })
            }
        },
    };
    let shared = endstops.iter().find(|e| e.axis == 2 && e.probe);
    let oid = match shared {
        Some(e) => e.oid,
        None => {
            let n = next.entry(p.pin.mcu.clone()).or_insert(0);
            *n += 1;
            *n - 1
        }
    };
    Ok(ProbeOut {
        endstop: EndstopOut {
            stepper: "probe".to_string(),
            axis: 2,
            pin: p.pin.clone(),
            oid,
            position_endstop: p.z_offset,
            position_min: z_min,
            position_max: z_max,
            homing_speed: p.speed,
            second_homing_speed: p.speed,
            homing_retract_dist: p.sample_retract_dist,
            homing_positive_dir: false,
            probe: true,
            sensorless: None,
            motor: None,
        },
        z_virtual_endstop: shared.is_some(),
        z_position: p.z_position.unwrap_or(z_min),
        cfg: p.clone(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn machine(text: &str) -> Machine {
        let cfg = sysconfig::parse_str(text, std::path::Path::new("printer.cfg")).unwrap();
        Machine::from_config(&cfg).unwrap()
    }

    #[test]
    fn probe_virtual_endstop_shares_z_endstop_object() {
        let m = machine(include_str!("../examples/simulated-probe.cfg"));
        let z = m.endstops.iter().find(|e| e.axis == 2).unwrap();
        assert_eq!((z.pin.mcu.as_str(), z.pin.pin.as_str()), ("probe_mcu", "PA4"));
        assert!(z.probe && z.pin.pullup);
        assert_eq!((z.position_endstop, z.oid), (1.5, 0));
        let p = m.probe.as_ref().unwrap();
        assert!(p.z_virtual_endstop);
        assert_eq!(
            (p.endstop.oid, p.z_position, p.endstop.homing_speed),
            (0, 0.0, 5.0)
        );
        assert_eq!(m.mcu_endstops("probe_mcu").len(), 1);
        // The probe triggers at the simulated bed surface (0); Z starts 20 mm above it.
        let args = m.sim_world_args("probe_mcu", "w").join(" ");
        assert_eq!(args, "--endstop PA4=z,0,min --world w");
        let args = m.sim_world_args("mcu", "w").join(" ");
        assert!(args.contains("--axis z=PC0,400,20 "), "{args}");
    }

    #[test]
    fn sensorless_endstops_read_the_drivers_diag_pins_and_the_drivers_are_simulated() {
        let text = std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/examples/simulated-sensorless.cfg"
        ))
        .unwrap();
        let m = machine(&text);
        let x = m.endstops.iter().find(|e| e.axis == 0).unwrap();
        assert_eq!(
            (x.pin.pin.as_str(), x.pin.pullup, x.sensorless),
            ("PE7", true, Some(0))
        );
        assert_eq!(m.tmc.iter().map(|t| t.bus).collect::<Vec<_>>(), [0, 0, 1, 2]);
        assert_eq!(crate::tmc::bus_count(&m.tmc, "mcu"), 3);
        let args = m.sim_world_args("mcu", "w").join(" ");
        assert!(
            args.contains("--tmc tmc2209@PE6:0=PE7,x,0,min --tmc tmc2209@PE6:1=PE8,y,0,min"),
            "{args}"
        );
        assert!(
            args.contains("--tmc tmc2130@PE9:0 --tmc tmc2208@PE13:0"),
            "{args}"
        );
        assert!(
            !args.contains("--endstop PE7") && args.contains("--endstop PC3=z,0,min"),
            "{args}"
        );
    }

    #[test]
    fn bltouch_servo_follows_the_endstops_and_is_simulated() {
        let text = include_str!("../examples/simulated-probe.cfg").replace(
            "[probe]\npin: ^probe_mcu:PA4",
            "[bltouch]\nsensor_pin: ^probe_mcu:PA4\ncontrol_pin: probe_mcu:PA5",
        );
        let m = machine(&text);
        let b = m.bltouch.as_ref().unwrap();
        assert_eq!((b.control_pin.mcu.as_str(), b.oid), ("probe_mcu", 1));
        assert!(m.mcu_bltouch("mcu").is_none());
        let args = m.sim_world_args("probe_mcu", "w").join(" ");
        assert_eq!(args, "--bltouch PA4=PA5,z,0 --world w");
    }

    #[test]
    fn smart_effector_control_follows_the_endstops_and_is_simulated() {
        let text = include_str!("../examples/simulated-probe.cfg").replace(
            "[probe]\npin: ^probe_mcu:PA4",
            "[smart_effector]\ncontrol_pin: !probe_mcu:PA5\nprobe_accel: 30\npin: ^probe_mcu:PA4",
        );
        let m = machine(&text);
        let e = m.smart_effector.as_ref().unwrap();
        assert_eq!(e.settings().probe_accel, 30.0);
        assert_eq!(
            m.mcu_smart_effector("probe_mcu").map(|(p, oid)| (p.invert, oid)),
            Some((true, 1))
        );
        assert!(m.mcu_smart_effector("mcu").is_none());
        let args = m.sim_world_args("probe_mcu", "w").join(" ");
        assert_eq!(args, "--endstop PA4=z,0,min --smart-effector !PA5 --world w");
        // Without control_pin: no output, nothing simulated.
        let m = machine(&text.replace("control_pin: !probe_mcu:PA5\n", ""));
        assert!(m.mcu_smart_effector("probe_mcu").is_none());
        assert_eq!(
            m.sim_world_args("probe_mcu", "w").join(" "),
            "--endstop PA4=z,0,min --world w"
        );
    }

    #[test]
    fn separate_probe_takes_the_next_oid() {
        let text = include_str!("../examples/simulated-multi-mcu.cfg").replace(
            "time_scale: 1.0",
            "time_scale: 1.0\nbed_surface_z: 1.25\n[probe]\npin: probe_mcu:PA4\nz_offset: 1\nz_position: -1",
        );
        let m = machine(&text);
        let p = m.probe.as_ref().unwrap();
        assert!(!p.z_virtual_endstop);
        assert_eq!(
            (p.endstop.oid, p.z_position, p.endstop.position_endstop),
            (1, -1.0, 1.0)
        );
        let oids: Vec<u8> = m.mcu_endstops("probe_mcu").iter().map(|e| e.oid).collect();
        assert_eq!(oids, [0, 1]);
        let args = m.sim_world_args("probe_mcu", "w").join(" ");
        assert_eq!(args, "--endstop PA3=z,0,min --endstop PA4=z,1.25,min --world w");
    }

    #[test]
    fn steppers_on_a_toolboard_get_its_oids_and_move_its_world_axes() {
        let m = machine(include_str!("../examples/simulated-toolboard.cfg"));
        let on = |mcu: &str| -> Vec<(&str, u8)> {
            m.steppers
                .iter()
                .filter(|s| s.mcu == mcu)
                .map(|s| (s.name.as_str(), s.oid))
                .collect()
        };
        assert_eq!(on("mcu"), [("stepper_x", 0), ("stepper_y", 1)]);
        assert_eq!(on("toolboard"), [("stepper_z", 0), ("extruder", 1)]);
        let oids: Vec<u8> = m.mcu_endstops("mcu").iter().map(|e| e.oid).collect();
        assert_eq!(oids, [2, 3, 4]);
        assert!(m.mcu_endstops("toolboard").is_empty());
        // The toolboard's process moves Z in the shared world; the main one reads its endstop.
        let tool = m.sim_world_args("toolboard", "w").join(" ");
        assert_eq!(tool, "--axis z=PA0,400,20 --world w");
        let main = m.sim_world_args("mcu", "w").join(" ");
        assert!(main.contains("--endstop PC3=z,0,min"), "{main}");
        assert!(!main.contains("--axis z"), "{main}");
    }

    #[test]
    fn corexy_and_corexz_motors_drive_a_and_b_and_endstops_read_the_forward_kinematics() {
        // X and Y start at 22 (10% of 220 from the endstops at 0), Z at 20: a = x + y = 44,
        // b = x − y = 0.
        let text = include_str!("../examples/simulated-corexy.cfg");
        let args = machine(text).sim_world_args("mcu", "w").join(" ");
        assert_eq!(
            args,
            "--axis a=PA0,80,44 --axis b=PB0,80,0 --axis z=PC0,400,20 \
             --endstop PA3=0.5*a+0.5*b,0,min --endstop PB3=0.5*a-0.5*b,0,min \
             --endstop PC3=z,0,min --world w"
        );
        // Corexz: a = x + z = 42, b = x − z = 2; y direct.
        let args = machine(&text.replace("kinematics: corexy", "kinematics: corexz"))
            .sim_world_args("mcu", "w")
            .join(" ");
        assert_eq!(
            args,
            "--axis a=PA0,80,42 --axis y=PB0,80,22 --axis b=PC0,400,2 \
             --endstop PA3=0.5*a+0.5*b,0,min --endstop PB3=y,0,min \
             --endstop PC3=0.5*a-0.5*b,0,min --world w"
        );
        // The simulator reads every coordinate back.
        for c in ["0.5*a+0.5*b", "0.5*a-0.5*b", "y"] {
            assert!(firmware::sim::world::Coord::parse(c).is_ok(), "{c}");
        }
    }

    #[test]
    fn further_motors_of_a_rail_move_with_it_and_drive_their_own_world_axes() {
        let mut text = include_str!("../examples/simulated-cartesian.cfg").to_string();
        for (n, port) in [(1, 'G'), (2, 'H')] {
            text.push_str(&format!(
                "\n[stepper_z{n}]\nstep_pin: P{port}0\ndir_pin: !P{port}1\nenable_pin: !P{port}2\n\
                 microsteps: 16\nrotation_distance: 8\n"
            ));
        }
        text.push_str("\n[stepper_x1]\nstep_pin: PJ0\ndir_pin: PJ1\nmicrosteps: 16\nrotation_distance: 40\n");
        let m = machine(&text);
        let names: Vec<(&str, usize, u8)> = m
            .steppers
            .iter()
            .map(|s| (s.name.as_str(), s.axis, s.oid))
            .collect();
        assert_eq!(
            names,
            [
                ("stepper_x", 0, 0),
                ("stepper_y", 1, 1),
                ("stepper_z", 2, 2),
                ("stepper_x1", 0, 3),
                ("stepper_z1", 2, 4),
                ("stepper_z2", 2, 5),
                ("extruder", 3, 6)
            ]
        );
        // Homing Z stops all three Z motors; X both X motors.
        assert_eq!(crate::homing::axis_steppers(&m, 2), [2, 4, 5]);
        assert_eq!(crate::homing::axis_steppers(&m, 0), [0, 3]);
        let spec: Vec<usize> = m
            .pipeline_config(1e6, 25e-6)
            .steppers
            .iter()
            .map(|s| s.axis)
            .collect();
        assert_eq!(spec, [0, 1, 2, 0, 2, 2, 3]);
        // Each motor drives its own end of the carriage (an inverted dir pin counts down); the
        // endstops read the first motor's.
        let args = m.sim_world_args("mcu", "w").join(" ");
        assert_eq!(
            args,
            "--axis x=PA0,80,22 --axis y=PB0,80,22 --axis z=PC0,400,20 --axis x1=PJ0,80,22 \
             --axis z1=PG0,-400,20 --axis z2=PH0,-400,20 --endstop PA3=x,0,min --endstop PB3=y,0,min \
             --endstop PC3=z,0,min --world w"
        );
    }

    #[test]
    fn a_further_motors_own_endstop_reads_its_end_of_the_carriage() {
        let text = include_str!("../examples/simulated-cartesian.cfg").replace(
            "time_scale: 1.0",
            "time_scale: 1.0\ngantry_tilt: 0, 0.5\nz_endstop_offsets: 0, 0.25",
        ) + "\n[mcu zboard]\nserial: simulator\n\
             [stepper_z1]\nstep_pin: PG0\ndir_pin: PG1\nmicrosteps: 16\nrotation_distance: 8\nendstop_pin: ^!PG3\n\
             [stepper_z2]\nstep_pin: PH0\ndir_pin: PH1\nmicrosteps: 16\nrotation_distance: 8\n\
             [stepper_z3]\nstep_pin: PK0\ndir_pin: PK1\nmicrosteps: 16\nrotation_distance: 8\n\
             endstop_pin: zboard:PA3\n";
        let m = machine(&text);
        let own: Vec<(&str, Option<usize>, &str, u8)> = m
            .endstops
            .iter()
            .map(|e| (e.stepper.as_str(), e.motor, e.pin.mcu.as_str(), e.oid))
            .collect();
        // The rails' endstops, then the further motors' own (stepper_z2 has none), numbered
        // after the steppers of their MCU; each takes [stepper_z]'s homing options.
        assert_eq!(
            own,
            [
                ("stepper_x", None, "mcu", 7),
                ("stepper_y", None, "mcu", 8),
                ("stepper_z", None, "mcu", 9),
                ("stepper_z1", Some(3), "mcu", 10),
                ("stepper_z3", Some(5), "zboard", 0)
            ]
        );
        assert!(m.endstops[3..]
            .iter()
            .all(|e| e.axis == 2 && e.position_endstop == 0.0 && e.homing_speed == 10.0));
        // z1's switch 0.25 mm up on its own end (which starts 0.5 mm up), z3's on the other MCU.
        let args = m.sim_world_args("mcu", "w").join(" ");
        assert!(args.contains("--axis z1=PG0,400,20.5 "), "{args}");
        assert!(
            args.ends_with("--endstop PC3=z,0,min --endstop !PG3=z1,0.25,min --world w"),
            "{args}"
        );
        let args = m.sim_world_args("zboard", "w").join(" ");
        assert_eq!(args, "--endstop PA3=z3,0,min --world w");
    }

    #[test]
    fn the_dual_z_example_gives_stepper_z1_its_own_switch() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/simulated-dual-z.cfg");
        let cfg = sysconfig::printer::load(&path).unwrap();
        let args = Machine::from_config(&cfg)
            .unwrap()
            .sim_world_args("mcu", "w")
            .join(" ");
        assert!(args.contains("--axis z1=PG0,-400,21 "), "{args}");
        assert!(args.contains("--endstop PG3=z1,0.1,min"), "{args}");
    }

    #[test]
    fn a_probe_on_a_delta_takes_the_delta_z_range() {
        let text = "[mcu]\nserial: simulator\n\
            [printer]\nkinematics: delta\nmax_velocity: 300\nmax_accel: 3000\ndelta_radius: 140\n\
            minimum_z_position: -5\n\
            [stepper_a]\nstep_pin: PA0\ndir_pin: PA1\nmicrosteps: 16\nrotation_distance: 40\nendstop_pin: PA2\n\
            position_endstop: 250\narm_length: 270\n\
            [stepper_b]\nstep_pin: PA3\ndir_pin: PA4\nmicrosteps: 16\nrotation_distance: 40\nendstop_pin: PA5\n\
            position_endstop: 251\n\
            [stepper_c]\nstep_pin: PA6\ndir_pin: PA7\nmicrosteps: 16\nrotation_distance: 40\nendstop_pin: PB0\n\
            position_endstop: 249\n\
            [probe]\npin: PB1\nz_offset: 1\n";
        let m = machine(text);
        let p = m.probe.as_ref().unwrap();
        assert_eq!(
            (p.z_position, p.endstop.position_min, p.endstop.position_max),
            (-5.0, -5.0, 249.0)
        );
        assert_eq!((p.endstop.oid, p.z_virtual_endstop), (6, false));
    }

    #[test]
    fn a_stepper_split_over_two_mcus_is_refused() {
        let text = include_str!("../examples/simulated-toolboard.cfg")
            .replace("dir_pin: toolboard:PA1", "dir_pin: PC1");
        let err = sysconfig::parse_str(&text, std::path::Path::new("printer.cfg"))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("stepper_z") && err.contains("dir_pin") && err.contains("toolboard"),
            "{err}"
        );
    }
}
