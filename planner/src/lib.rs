//! Motion planning: pure computation from G-code text to compressed MCU step commands.
//!
//! Layers (each depends only on the ones above it):
//! - [`gcode`]: streaming G-code parser over any `BufRead` (never loads the whole file).
//! - [`toolhead`]: moves with trapezoidal velocity profiles, junction speeds and the lookahead
//!   queue (Klipper's planning rules: junction deviation from `square_corner_velocity`,
//!   `minimum_cruise_ratio`, Z and extrude-only limits).
//! - [`machine`]: modal G-code state (G90/G91, M82/M83, G92, feedrate, homed axes) applied to a
//!   toolhead.
//! - [`bed_mesh`]: bed levelling maths: probed mesh interpolation (Lagrange, bicubic), fade and
//!   the split of moves along the mesh (Klipper's `[bed_mesh]`).
//! - [`kinematics`]: which stepper moves how when the toolhead moves (cartesian, corexy, corexz,
//!   delta).
//! - [`pressure_advance`]: the extruder with pressure advance (iterative step solver).
//! - [`shaper`]: input shapers (`[input_shaper]`): the pulse trains X and Y are convolved with.
//! - [`shaped`]: step generation for steppers that follow a shaped axis (piecewise quadratic,
//!   closed-form crossings).
//! - [`stepgen`]: each stepper's ideal step times, in closed form for linear kinematics.
//! - [`compress`]: greedy packing of step times into `queue_step` (interval, count, add)
//!   commands within the maximum step error.
//! - [`checker`]: replays commands like the MCU does and proves every step is within its window.
//! - [`pipeline`]: the top level the `cadence` binary drives.
//!
//! Guarantees: no panics on any input (G-code bytes, configuration numbers); no IO besides
//! reading the `BufRead` handed to [`gcode::GcodeReader`]; after warm-up the step path reuses
//! its buffers (no allocation per step). Each stepper's step generation and compression is
//! independent state; [`pipeline::PipelineOptions::threads`] runs them on worker threads and the
//! caller's (std threads and channels, pure computation).

pub mod bed_mesh;
pub mod checker;
pub mod compress;
pub mod extruders;
pub mod force_move;
pub mod gcode;
pub mod kinematics;
pub mod machine;
pub mod pipeline;
pub mod pressure_advance;
pub mod shaped;
pub mod shaper;
pub mod stepgen;
pub mod toolhead;
