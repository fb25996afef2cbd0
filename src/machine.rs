//! The printer as the host drives it: which steppers exist, on which MCU and oid, with which
//! pins, and the planner configuration derived from printer.cfg.

use planner::pipeline::{PipelineConfig, PipelineOptions, StepperSpec};
use planner::toolhead::ToolheadConfig;
use sysconfig::printer::{PinRef, PrinterConfig};

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
    pub step_dist: f64,
}

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
}

/// Everything derived from a printer.cfg that `print` needs.
#[derive(Debug, Clone)]
pub struct Machine {
    pub steppers: Vec<StepperOut>,
    pub endstops: Vec<EndstopOut>,
    pub toolhead: ToolheadConfig,
    pub home_position: [f64; 3],
    /// Kinematics and pressure advance for the planner.
    pub options: PipelineOptions,
}

impl Machine {
    /// Derives the machine from a validated config. Single-MCU printers only for now.
    pub fn from_config(cfg: &PrinterConfig) -> Result<Machine, String> {
        // Toolhead limits, kinematics and home position come from one shared derivation.
        let (planning, kinematics) = sysconfig::planning::pipeline_config(cfg, 1.0, 25e-6)
            .map_err(|e| format!("{}: {e}", cfg.source.display()))?;
        let mut steppers = Vec::new();
        let mut endstops = Vec::new();
        for (axis, s) in cfg.steppers.iter().enumerate().take(3) {
            let name = s.name.clone();
            if let (Some(pin), Some(position_endstop)) = (&s.endstop_pin, s.position_endstop) {
                endstops.push(EndstopOut {
                    stepper: name.clone(),
                    axis,
                    pin: pin.clone(),
                    oid: 0,
                    position_endstop,
                    position_min: s.position_min,
                    position_max: s.position_max,
                    homing_speed: s.homing_speed,
                    second_homing_speed: s.second_homing_speed,
                    homing_retract_dist: s.homing_retract_dist,
                    homing_positive_dir: s.homing_positive_dir,
                });
            }
            steppers.push(StepperOut {
                name,
                mcu: s.step_pin.mcu.clone(),
                oid: 0,
                axis,
                step_pin: s.step_pin.clone(),
                dir_pin: s.dir_pin.clone(),
                step_dist: s.step_dist(),
            });
        }
        let toolhead = planning.toolhead;
        let home = planning.home_position;
        if let Some(e) = &cfg.extruder {
            steppers.push(StepperOut {
                name: "extruder".to_string(),
                mcu: e.step_pin.mcu.clone(),
                oid: 0,
                axis: 3,
                step_pin: e.step_pin.clone(),
                dir_pin: e.dir_pin.clone(),
                step_dist: e.step_dist(),
            });
        }
        for s in &steppers {
            for pin in [&s.step_pin, &s.dir_pin] {
                if pin.mcu != "mcu" {
                    return Err(format!(
                        "{}: [{}] pin '{}:{}': steppers can only be driven by the main [mcu] in this version",
                        cfg.source.display(),
                        s.name,
                        pin.mcu,
                        pin.pin
                    ));
                }
            }
        }
        // Object ids: per MCU, steppers first, then endstops (the trsync comes last).
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
        let options = sysconfig::planning::pipeline_options(cfg, kinematics);
        Ok(Machine {
            steppers,
            endstops,
            toolhead,
            home_position: home,
            options,
        })
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
                })
                .collect(),
            clock_freq,
            max_error_s,
            home_position: self.home_position,
        }
    }
}

impl Machine {
    /// Arguments that put a simulated MCU into the printer's shared simulated world: the axes
    /// its steppers move (starting mid-travel) and the endstops wired to its pins.
    pub fn sim_world_args(&self, mcu: &str, world: &str) -> Vec<String> {
        let mut args = Vec::new();
        let axis_names = ["x", "y", "z", "e"];
        for s in self.steppers.iter().filter(|s| s.mcu == mcu && s.axis < 3) {
            let (min, max) = self.toolhead.axis_limits[s.axis];
            let steps_per_mm = if s.dir_pin.invert {
                -1.0 / s.step_dist
            } else {
                1.0 / s.step_dist
            };
            args.push("--axis".to_string());
            // The carriage starts 10% of the travel away from its endstop (homing stays short).
            let start = match self.endstops.iter().find(|e| e.axis == s.axis) {
                Some(e) if e.homing_positive_dir => e.position_endstop - 0.1 * (max - min),
                Some(e) => e.position_endstop + 0.1 * (max - min),
                None => (min + max) / 2.0,
            };
            args.push(format!(
                "{}={},{},{}",
                axis_names[s.axis], s.step_pin.pin, steps_per_mm, start
            ));
        }
        for e in self.endstops.iter().filter(|e| e.pin.mcu == mcu) {
            let side = if e.homing_positive_dir { "max" } else { "min" };
            args.push("--endstop".to_string());
            args.push(format!(
                "{}={},{},{side}",
                e.pin.pin, axis_names[e.axis], e.position_endstop
            ));
        }
        if !args.is_empty() {
            args.push("--world".to_string());
            args.push(world.to_string());
        }
        args
    }
}
