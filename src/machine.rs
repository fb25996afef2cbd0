//! The printer as the host drives it: which steppers exist, on which MCU and oid, with which
//! pins, and the planner configuration derived from printer.cfg.

use planner::pipeline::{PipelineConfig, StepperSpec};
use planner::toolhead::ToolheadConfig;
use sysconfig::printer::{PinRef, PrinterConfig};

/// One stepper as the host addresses it on its MCU.
#[derive(Debug, Clone)]
pub struct StepperOut {
    /// Config section name, e.g. `stepper_x`, `extruder`.
    pub name: String,
    /// Index into the planner's steppers (and the MCU object id: oids are allocated in order).
    pub oid: u8,
    /// Axis index 0..=3 (X, Y, Z, E).
    pub axis: usize,
    pub step_pin: PinRef,
    pub dir_pin: PinRef,
    pub step_dist: f64,
}

/// Everything derived from a printer.cfg that `print` needs.
#[derive(Debug, Clone)]
pub struct Machine {
    pub steppers: Vec<StepperOut>,
    pub toolhead: ToolheadConfig,
    pub home_position: [f64; 3],
}

impl Machine {
    /// Derives the machine from a validated config. Single-MCU printers only for now.
    pub fn from_config(cfg: &PrinterConfig) -> Result<Machine, String> {
        use sysconfig::printer::Kinematics;
        if !matches!(cfg.printer.kinematics, Kinematics::Cartesian) {
            return Err(format!(
                "{}: [printer] kinematics: only 'cartesian' is supported by this version",
                cfg.source.display()
            ));
        }
        let mut steppers = Vec::new();
        let mut limits = [(0.0, 0.0); 3];
        let mut home = [0.0; 3];
        for (axis, axis_name) in ["x", "y", "z"].iter().enumerate() {
            let name = format!("stepper_{axis_name}");
            let s = cfg.steppers.iter().find(|s| s.name == name).ok_or_else(|| {
                format!(
                    "{}: section [{name}] is required for cartesian kinematics",
                    cfg.source.display()
                )
            })?;
            limits[axis] = (s.position_min, s.position_max);
            home[axis] = s.position_endstop.unwrap_or(s.position_min);
            steppers.push(StepperOut {
                name: name.clone(),
                oid: axis as u8,
                axis,
                step_pin: s.step_pin.clone(),
                dir_pin: s.dir_pin.clone(),
                step_dist: s.step_dist(),
            });
        }
        let p = &cfg.printer;
        let mut toolhead = ToolheadConfig {
            max_velocity: p.max_velocity,
            max_accel: p.max_accel,
            minimum_cruise_ratio: p.minimum_cruise_ratio,
            square_corner_velocity: p.square_corner_velocity,
            max_z_velocity: p.max_z_velocity,
            max_z_accel: p.max_z_accel,
            max_extrude_only_velocity: p.max_velocity,
            max_extrude_only_accel: p.max_accel,
            max_extrude_only_distance: 50.0,
            axis_limits: limits,
        };
        if let Some(e) = &cfg.extruder {
            toolhead.max_extrude_only_velocity = e.max_extrude_only_velocity;
            toolhead.max_extrude_only_accel = e.max_extrude_only_accel;
            toolhead.max_extrude_only_distance = e.max_extrude_only_distance;
            steppers.push(StepperOut {
                name: "extruder".to_string(),
                oid: 3,
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
                        "{}: [{}] pin '{}:{}': only the main [mcu] is supported by this version",
                        cfg.source.display(),
                        s.name,
                        pin.mcu,
                        pin.pin
                    ));
                }
            }
        }
        Ok(Machine {
            steppers,
            toolhead,
            home_position: home,
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
