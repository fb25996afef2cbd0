//! What the planner's integration tests share: the benchy G-code and the reference cartesian
//! printer it was measured with.

use planner::pipeline::{PipelineConfig, StepperSpec};
use planner::toolhead::ToolheadConfig;

/// shared/data/gcode/benchy-prusaslicer.gcode (beside the checkout; tests skip without it).
pub const BENCHY: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../shared/data/gcode/benchy-prusaslicer.gcode"
);

/// benchy-cartesian.cfg: 80 steps/mm X/Y, 400 Z, 3200/33.5 E; Klipper's extruder defaults for a
/// 0.5 mm nozzle and 3.5 mm filament (extrude-only limits = max × 4·nozzle² / filament area).
pub fn benchy_cartesian() -> PipelineConfig {
    let area = std::f64::consts::PI * 1.75 * 1.75;
    let ratio = 4.0 * 0.5 * 0.5 / area;
    let stepper = |name: &str, axis, step_dist| StepperSpec {
        name: name.into(),
        axis,
        step_dist,
        extruder: None,
    };
    PipelineConfig {
        toolhead: ToolheadConfig {
            max_velocity: 500.0,
            max_accel: 3000.0,
            minimum_cruise_ratio: 0.5,
            square_corner_velocity: 5.0,
            max_z_velocity: 25.0,
            max_z_accel: 30.0,
            max_extrude_only_velocity: 500.0 * ratio,
            max_extrude_only_accel: 3000.0 * ratio,
            max_extrude_only_distance: 500.0,
            axis_limits: [(0.0, 200.0), (0.0, 200.0), (0.0, 200.0)],
        },
        steppers: vec![
            stepper("stepper_x", 0, 40.0 / 3200.0),
            stepper("stepper_y", 1, 40.0 / 3200.0),
            stepper("stepper_z", 2, 8.0 / 3200.0),
            stepper("extruder", 3, 33.5 / 3200.0),
        ],
        clock_freq: 50e6,
        max_error_s: 25e-6,
        home_position: [0.0, 0.0, 0.5],
    }
}
