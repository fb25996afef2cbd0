//! printer.cfg → the planner's configuration (toolhead limits, kinematics, steppers, pressure
//! advance). One place, used by the host and the benchmarks.

use planner::kinematics::{DeltaGeometry, Kinematics};
use planner::pipeline::{ExtruderLink, PipelineConfig, PipelineOptions, StepperSpec};
use planner::pressure_advance::PressureAdvance;
use planner::toolhead::ToolheadConfig;

use crate::printer::{MotorSection, PrinterConfig, UnknownCommands};

/// The planner configuration of a validated printer config: kinematics, steppers in the
/// kinematics' order (then the rails' further motors, then the extruder), limits, home position; for MCU clocks at `clock_freq`
/// ticks per print second and a step compression bound of `max_error_s`.
pub fn pipeline_config(
    cfg: &PrinterConfig,
    clock_freq: f64,
    max_error_s: f64,
) -> Result<(PipelineConfig, Kinematics), String> {
    use crate::printer::Kinematics as K;
    let kin = match cfg.printer.kinematics {
        K::Cartesian => Kinematics::Cartesian,
        K::CoreXY => Kinematics::CoreXY,
        K::CoreXZ => Kinematics::CoreXZ,
        K::Delta => {
            let d = cfg
                .delta
                .as_ref()
                .ok_or("delta kinematics without delta geometry")?;
            Kinematics::Delta(DeltaGeometry {
                radius: d.delta_radius,
                arm_length: d.arm_length,
                angles: d.angles,
            })
        }
        other => return Err(format!("kinematics '{}' is not supported", other.name())),
    };
    let mut steppers = Vec::new();
    let mut limits = [(0.0, 0.0); 3];
    let mut home = [0.0; 3];
    for (axis, s) in cfg.steppers.iter().enumerate().take(3) {
        limits[axis] = (s.position_min, s.position_max);
        home[axis] = s.position_endstop.unwrap_or(s.position_min);
        steppers.push(StepperSpec {
            name: s.name.clone(),
            axis,
            step_dist: s.step_dist(),
            extruder: None,
        });
    }
    // Further motors of a rail follow its motion (`[stepper_z1]` moves as `[stepper_z]`).
    for s in &cfg.extra_steppers {
        steppers.push(StepperSpec {
            name: s.name.clone(),
            axis: s.rail,
            step_dist: s.motor.step_dist(),
            extruder: None,
        });
    }
    if let (Kinematics::Delta(g), Some(d)) = (kin, &cfg.delta) {
        // Each position_endstop is the nozzle height at the centre when that carriage homes.
        let carriages: Vec<f64> = (0..3)
            .map(|i| {
                let e = cfg
                    .steppers
                    .get(i)
                    .and_then(|s| s.position_endstop)
                    .unwrap_or(0.0);
                e + (g.arm_length[i].powi(2) - g.radius.powi(2)).max(0.0).sqrt()
            })
            .collect();
        home = kin.forward([carriages[0], carriages[1], carriages[2]]);
        let max_z = limits.iter().map(|l| l.1).fold(f64::INFINITY, f64::min);
        let r = d.print_radius;
        limits = [(-r, r), (-r, r), (d.minimum_z_position, max_z)];
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
    }
    for (name, motor, link) in extruder_steppers(cfg) {
        steppers.push(StepperSpec {
            name,
            axis: 3,
            step_dist: motor.step_dist(),
            extruder: link,
        });
    }
    let pc = PipelineConfig {
        toolhead,
        steppers,
        clock_freq,
        max_error_s,
        home_position: home,
    };
    Ok((pc, kin))
}

/// Every extruder stepper in the planner's order: `[extruder]`, `[extruder1]`…, then each
/// `[extruder_stepper NAME]` (named NAME): its name, motor, and how it starts (`None` for the
/// one extruder of a printer without further extruders or extruder steppers).
pub fn extruder_steppers(cfg: &PrinterConfig) -> Vec<(String, &MotorSection, Option<ExtruderLink>)> {
    let several = !cfg.extra_extruders.is_empty() || !cfg.extruder_steppers.is_empty();
    let link = |queue, advance, smooth_time, motor: &MotorSection| {
        several.then_some(ExtruderLink {
            queue,
            pressure_advance: PressureAdvance { advance, smooth_time },
            rotation_distance: motor.rotation_distance,
        })
    };
    let own = cfg.extruders().enumerate().map(|(i, e)| {
        let l = link(
            Some(i),
            e.pressure_advance,
            e.pressure_advance_smooth_time,
            &e.motor,
        );
        (e.name.clone(), &e.motor, l)
    });
    let extra = cfg.extruder_steppers.iter().map(|s| {
        let queue = s.extruder.as_deref().and_then(planner::extruders::extruder_index);
        let l = link(
            queue,
            s.pressure_advance,
            s.pressure_advance_smooth_time,
            &s.motor,
        );
        (s.name.clone(), &s.motor, l)
    });
    own.chain(extra).collect()
}

/// Pipeline options derived from the config: kinematics, the extruder's pressure advance, what
/// an unknown G-code command does, firmware retraction, the arc resolution and the input shaper
/// (planning on the caller's thread; set `threads` for worker threads).
pub fn pipeline_options(cfg: &PrinterConfig, kinematics: Kinematics) -> PipelineOptions {
    // Pressure advance 0 is no pressure advance (the plain extruder path).
    let pressure_advance = cfg
        .extruder
        .as_ref()
        .filter(|e| e.pressure_advance > 0.0)
        .map(|e| PressureAdvance {
            advance: e.pressure_advance,
            smooth_time: e.pressure_advance_smooth_time,
        });
    PipelineOptions {
        kinematics,
        pressure_advance,
        unknown_commands_are_errors: cfg.gcode.unknown_commands == UnknownCommands::Error,
        retraction: cfg.firmware_retraction,
        arc_resolution: cfg.gcode_arcs.resolution,
        input_shaper: cfg.input_shaper,
        exclude_object: cfg.exclude_object,
        extruders: cfg.extruders().count().max(1),
        ..PipelineOptions::default()
    }
}
