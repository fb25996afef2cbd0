//! The toolhead: turns target positions into [`Move`]s with trapezoidal speed profiles, using a
//! lookahead queue to choose junction speeds (see [`lookahead`] for the math).
//!
//! Limits applied per move (Klipper's rules):
//! - speed ≤ `max_velocity`, acceleration `max_accel` (X/Y/Z moves);
//! - a move with Z scales the Z limits by `move_d / |ΔZ|`;
//! - extrude-only moves, moves with only Z and E, and retractions use the extrude-only limits
//!   scaled by `1 / |ΔE / move_d|`, and may not exceed `max_extrude_only_distance`;
//! - junction speeds from `square_corner_velocity` (junction deviation), the extruder's
//!   instantaneous corner velocity (1 mm/s), and a full stop at every junction with an
//!   extrude-only move.
//!
//! Output: moves become final when the lookahead proves their speeds can no longer change (a
//! lazy pass every 0.25 s of queued move time), when more than 2 s of moves are queued (the
//! front part is then finalized assuming a stop after the last queued move, which is always
//! safe), or on [`Toolhead::flush`]. [`Toolhead::take_moves`] drains them in order.

mod homing; // homing: stop part-way through a move
pub mod lookahead;
pub mod moves;

use std::collections::VecDeque;

use lookahead::{Falling, Queued};
pub use moves::{Move, Phases};

/// Queued move time between lazy lookahead passes (s).
const LOOKAHEAD_FLUSH_TIME: f64 = 0.25;
/// Queued move time above which the front of the queue is finalized anyway (s).
const MAX_QUEUED_TIME: f64 = 2.0;
/// Queued move time kept after such a forced partial flush (s).
const KEEP_QUEUED_TIME: f64 = 1.0;
/// Acceleration of an extrude-only move before the extruder's limits apply (mm/s²).
const UNLIMITED_ACCEL: f64 = 99_999_999.9;
/// Coordinates beyond this (mm) are rejected as absurd.
const ABSURD_COORD: f64 = 1e9;
/// Moves shorter than this in X/Y/Z are extrude-only (mm); shorter extrude-only moves are
/// ignored.
const MIN_XYZ_MOVE: f64 = 1e-9;
/// Extrusion per mm of X/Y/Z travel beyond which a move is refused as absurd (the real limit,
/// Klipper's max_extrude_cross_section, needs nozzle data the toolhead does not have).
const MAX_EXTRUDE_RATIO: f64 = 100.0;
/// Longest dwell accepted (s).
pub const MAX_DWELL: f64 = 1e6;
/// Klipper's default `instantaneous_corner_velocity` of the extruder (mm/s).
pub const DEFAULT_INSTANT_CORNER_VELOCITY: f64 = 1.0;

/// Kinematic limits of the toolhead (from `[printer]`, `[extruder]` and the stepper ranges).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ToolheadConfig {
    pub max_velocity: f64,
    pub max_accel: f64,
    /// Share of an accelerate-then-decelerate stretch kept at cruise speed (default 0.5).
    pub minimum_cruise_ratio: f64,
    /// Speed through a 90° corner (default 5 mm/s).
    pub square_corner_velocity: f64,
    pub max_z_velocity: f64,
    pub max_z_accel: f64,
    pub max_extrude_only_velocity: f64,
    pub max_extrude_only_accel: f64,
    pub max_extrude_only_distance: f64,
    /// position_min / position_max of X, Y, Z.
    pub axis_limits: [(f64, f64); 3],
}

impl Default for ToolheadConfig {
    fn default() -> Self {
        ToolheadConfig {
            max_velocity: 300.0,
            max_accel: 3000.0,
            minimum_cruise_ratio: 0.5,
            square_corner_velocity: 5.0,
            max_z_velocity: 25.0,
            max_z_accel: 100.0,
            max_extrude_only_velocity: 50.0,
            max_extrude_only_accel: 300.0,
            max_extrude_only_distance: 50.0,
            axis_limits: [(0.0, 200.0); 3],
        }
    }
}

impl ToolheadConfig {
    /// Checks every number is finite and in range; the message names the option.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let positive = [
            ("max_velocity", self.max_velocity),
            ("max_accel", self.max_accel),
            ("max_z_velocity", self.max_z_velocity),
            ("max_z_accel", self.max_z_accel),
            ("max_extrude_only_velocity", self.max_extrude_only_velocity),
            ("max_extrude_only_accel", self.max_extrude_only_accel),
            ("max_extrude_only_distance", self.max_extrude_only_distance),
        ];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(ConfigError(format!("{name} = {v}: must be a positive number")));
            }
        }
        if !(self.minimum_cruise_ratio.is_finite() && (0.0..1.0).contains(&self.minimum_cruise_ratio)) {
            return Err(ConfigError(format!(
                "minimum_cruise_ratio = {}: must be in [0, 1)",
                self.minimum_cruise_ratio
            )));
        }
        if !(self.square_corner_velocity.is_finite() && self.square_corner_velocity >= 0.0) {
            return Err(ConfigError(format!(
                "square_corner_velocity = {}: must be ≥ 0",
                self.square_corner_velocity
            )));
        }
        for (axis, (lo, hi)) in self.axis_limits.iter().enumerate() {
            if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
                return Err(ConfigError(format!(
                    "{} limits [{lo}, {hi}]: need finite position_min ≤ position_max",
                    AXIS_NAMES[axis]
                )));
            }
        }
        Ok(())
    }
}

/// Axis letters by index.
pub const AXIS_NAMES: [char; 4] = ['X', 'Y', 'Z', 'E'];

/// An invalid [`ToolheadConfig`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("toolhead config: {0}")]
pub struct ConfigError(pub String);

/// Why a move was refused (the toolhead is unchanged).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MoveError {
    #[error("Move out of range: X={x:.3} Y={y:.3} Z={z:.3} [E={e:.3}]")]
    OutOfRange { x: f64, y: f64, z: f64, e: f64 },
    #[error("invalid target position {0:?}")]
    BadPosition([f64; 4]),
    #[error("invalid speed {0} mm/s")]
    BadSpeed(f64),
    #[error("Extrude only move too long ({dist:.3} mm vs max_extrude_only_distance {max:.3} mm)")]
    ExtrudeOnlyTooLong { dist: f64, max: f64 },
    #[error("Move exceeds maximum extrusion ({ratio:.1} mm of filament per mm, max {max})")]
    ExtrudeRatio { ratio: f64, max: f64 },
    #[error("invalid dwell {0} s (0 ..= {MAX_DWELL})")]
    BadDwell(f64),
    #[error("move limits are not finite (check the toolhead config)")]
    BadLimits,
}

/// The toolhead's planner state: commanded position, lookahead queue, final moves.
#[derive(Debug)]
pub struct Toolhead {
    cfg: ToolheadConfig,
    junction_deviation: f64,
    accel_to_decel: f64,
    instant_corner_v: f64,
    commanded: [f64; 4],
    queue: VecDeque<Queued>,
    falling: Vec<Falling>,
    ready: VecDeque<Move>,
    print_time: f64,
    flush_countdown: f64,
    queued_time: f64,
    moves_total: u64,
    /// Largest x² + y² of a move's end (delta printers), ∞ when unlimited.
    max_xy2: f64,
}

impl Toolhead {
    /// A toolhead at rest at position 0 whose first move starts at `start_print_time`.
    pub fn new(cfg: ToolheadConfig, start_print_time: f64) -> Toolhead {
        let scv = cfg.square_corner_velocity;
        Toolhead {
            cfg,
            junction_deviation: scv * scv * (std::f64::consts::SQRT_2 - 1.0) / cfg.max_accel,
            accel_to_decel: cfg.max_accel * (1.0 - cfg.minimum_cruise_ratio),
            instant_corner_v: DEFAULT_INSTANT_CORNER_VELOCITY,
            commanded: [0.0; 4],
            queue: VecDeque::with_capacity(1024),
            falling: Vec::with_capacity(256),
            ready: VecDeque::with_capacity(1024),
            print_time: if start_print_time.is_finite() {
                start_print_time
            } else {
                0.0
            },
            flush_countdown: LOOKAHEAD_FLUSH_TIME,
            queued_time: 0.0,
            moves_total: 0,
            max_xy2: f64::INFINITY,
        }
    }

    pub fn config(&self) -> &ToolheadConfig {
        &self.cfg
    }

    /// The extruder's instantaneous corner velocity (mm/s; default 1).
    pub fn set_instantaneous_corner_velocity(&mut self, v: f64) {
        if v.is_finite() && v >= 0.0 {
            self.instant_corner_v = v;
        }
    }

    /// Changes the velocity limits for moves queued from now on (SET_VELOCITY_LIMIT, M204):
    /// `None` keeps a value. The new values are validated like the config's; on error nothing
    /// changes.
    pub fn set_limits(
        &mut self,
        max_velocity: Option<f64>,
        max_accel: Option<f64>,
        square_corner_velocity: Option<f64>,
        minimum_cruise_ratio: Option<f64>,
    ) -> Result<(), ConfigError> {
        let mut cfg = self.cfg;
        cfg.max_velocity = max_velocity.unwrap_or(cfg.max_velocity);
        cfg.max_accel = max_accel.unwrap_or(cfg.max_accel);
        cfg.square_corner_velocity = square_corner_velocity.unwrap_or(cfg.square_corner_velocity);
        cfg.minimum_cruise_ratio = minimum_cruise_ratio.unwrap_or(cfg.minimum_cruise_ratio);
        cfg.validate()?;
        let scv = cfg.square_corner_velocity;
        self.junction_deviation = scv * scv * (std::f64::consts::SQRT_2 - 1.0) / cfg.max_accel;
        self.accel_to_decel = cfg.max_accel * (1.0 - cfg.minimum_cruise_ratio);
        self.cfg = cfg;
        Ok(())
    }

    /// Limits moves to a circle of `radius` around X = Y = 0 (delta printers); `None` lifts it.
    pub fn set_xy_radius_limit(&mut self, radius: Option<f64>) {
        self.max_xy2 = match radius {
            Some(r) if r.is_finite() && r >= 0.0 => r * r,
            _ => f64::INFINITY,
        };
    }

    /// Commanded position (the end of the last accepted move).
    pub fn position(&self) -> [f64; 4] {
        self.commanded
    }

    /// End print time of the last final move (including dwells).
    pub fn print_time(&self) -> f64 {
        self.print_time
    }

    /// Moves accepted so far (zero-length moves excluded).
    pub fn moves_total(&self) -> u64 {
        self.moves_total
    }

    /// Moves waiting in the lookahead queue (not final yet).
    pub fn queued_moves(&self) -> usize {
        self.queue.len()
    }

    /// Queues a move to `end` (X, Y, Z, E in mm) at up to `speed_mm_s`.
    pub fn move_to(&mut self, end: [f64; 4], speed_mm_s: f64) -> Result<(), MoveError> {
        if end.iter().any(|v| !v.is_finite() || v.abs() > ABSURD_COORD) {
            return Err(MoveError::BadPosition(end));
        }
        if !(speed_mm_s.is_finite() && speed_mm_s > 0.0) {
            return Err(MoveError::BadSpeed(speed_mm_s));
        }
        let start = self.commanded;
        let mut d = [0.0; 4];
        for i in 0..4 {
            d[i] = end[i] - start[i];
        }
        let xyz_d = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        let cfg = self.cfg;
        let (kinematic, end_pos, move_d, velocity, accel) = if xyz_d < MIN_XYZ_MOVE {
            d[0] = 0.0;
            d[1] = 0.0;
            d[2] = 0.0;
            (
                false,
                [start[0], start[1], start[2], end[3]],
                d[3].abs(),
                speed_mm_s,
                UNLIMITED_ACCEL,
            )
        } else {
            for i in 0..3 {
                let (lo, hi) = cfg.axis_limits[i];
                if d[i] != 0.0 && !(lo..=hi).contains(&end[i]) {
                    return Err(MoveError::OutOfRange {
                        x: end[0],
                        y: end[1],
                        z: end[2],
                        e: end[3],
                    });
                }
            }
            if (d[0] != 0.0 || d[1] != 0.0) && end[0] * end[0] + end[1] * end[1] > self.max_xy2 {
                return Err(MoveError::OutOfRange {
                    x: end[0],
                    y: end[1],
                    z: end[2],
                    e: end[3],
                });
            }
            (true, end, xyz_d, speed_mm_s.min(cfg.max_velocity), cfg.max_accel)
        };
        if move_d < MIN_XYZ_MOVE {
            return Ok(());
        }
        if kinematic && d[3].abs() > MAX_EXTRUDE_RATIO * move_d && d[3].abs() > 1.0 {
            return Err(MoveError::ExtrudeRatio {
                ratio: d[3].abs() / move_d,
                max: MAX_EXTRUDE_RATIO,
            });
        }
        let inv_d = 1.0 / move_d;
        let axes_r = [d[0] * inv_d, d[1] * inv_d, d[2] * inv_d, d[3] * inv_d];
        let mut q = Queued {
            mv: Move {
                print_time: 0.0,
                start_pos: start,
                end_pos,
                axes_r,
                move_d,
                start_v: 0.0,
                cruise_v: 0.0,
                end_v: 0.0,
                accel,
                accel_t: 0.0,
                cruise_t: 0.0,
                decel_t: 0.0,
            },
            kinematic,
            max_start_v2: 0.0,
            max_cruise_v2: velocity * velocity,
            delta_v2: 2.0 * move_d * accel,
            max_smoothed_v2: 0.0,
            smooth_delta_v2: 2.0 * move_d * self.accel_to_decel.min(accel),
            min_move_t: move_d / velocity,
            start_v2: 0.0,
            cruise_v2: 0.0,
            end_v2: 0.0,
        };
        if kinematic && d[2] != 0.0 {
            let z_ratio = move_d / d[2].abs();
            q.limit_speed(cfg.max_z_velocity * z_ratio, cfg.max_z_accel * z_ratio);
        }
        if d[3] != 0.0 && ((d[0] == 0.0 && d[1] == 0.0) || axes_r[3] < 0.0) {
            if d[3].abs() > cfg.max_extrude_only_distance {
                return Err(MoveError::ExtrudeOnlyTooLong {
                    dist: d[3].abs(),
                    max: cfg.max_extrude_only_distance,
                });
            }
            let inv_r = 1.0 / axes_r[3].abs();
            q.limit_speed(
                cfg.max_extrude_only_velocity * inv_r,
                cfg.max_extrude_only_accel * inv_r,
            );
        }
        let limits = [
            q.max_cruise_v2,
            q.delta_v2,
            q.smooth_delta_v2,
            q.min_move_t,
            q.mv.accel,
        ];
        if limits.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
            return Err(MoveError::BadLimits);
        }
        if let Some(prev) = self.queue.back() {
            lookahead::calc_junction(prev, &mut q, self.junction_deviation, self.instant_corner_v);
        }
        self.commanded = end_pos;
        self.moves_total += 1;
        self.flush_countdown -= q.min_move_t;
        self.queued_time += q.min_move_t;
        self.queue.push_back(q);
        if self.flush_countdown <= 0.0 {
            self.lazy_flush();
        }
        Ok(())
    }

    /// Finalizes every queued move, the last one ending at rest.
    pub fn flush(&mut self) {
        self.flush_countdown = LOOKAHEAD_FLUSH_TIME;
        let n = lookahead::plan(self.queue.make_contiguous(), &mut self.falling, false);
        self.commit(n, false);
    }

    /// Waits `seconds` (0 ..= [`MAX_DWELL`]) after the last move (flushes the lookahead first).
    pub fn dwell(&mut self, seconds: f64) -> Result<(), MoveError> {
        if !(seconds.is_finite() && (0.0..=MAX_DWELL).contains(&seconds)) {
            return Err(MoveError::BadDwell(seconds));
        }
        self.flush();
        self.print_time += seconds;
        Ok(())
    }

    /// Redefines the commanded position without moving (flushes the lookahead first).
    /// Non-finite components are ignored.
    pub fn set_position(&mut self, pos: [f64; 4]) {
        self.flush();
        for (c, p) in self.commanded.iter_mut().zip(pos) {
            if p.is_finite() {
                *c = p;
            }
        }
    }

    /// Appends the final moves, in order, to `out`.
    pub fn take_moves(&mut self, out: &mut Vec<Move>) {
        out.extend(self.ready.drain(..));
    }

    /// The lazy pass, then a forced partial flush if too much is still queued.
    fn lazy_flush(&mut self) {
        self.flush_countdown = LOOKAHEAD_FLUSH_TIME;
        let n = lookahead::plan(self.queue.make_contiguous(), &mut self.falling, true);
        self.commit(n, false);
        if self.queued_time > MAX_QUEUED_TIME && self.queue.len() > 1 {
            lookahead::plan(self.queue.make_contiguous(), &mut self.falling, false);
            let mut keep_t = 0.0;
            let mut keep = 0;
            for q in self.queue.iter().rev() {
                if keep > 0 && keep_t + q.min_move_t > KEEP_QUEUED_TIME {
                    break;
                }
                keep_t += q.min_move_t;
                keep += 1;
            }
            let n = self.queue.len() - keep;
            self.commit(n, true);
        }
    }

    /// Turns the first `n` queued moves (speeds already assigned by a pass) into final moves.
    fn commit(&mut self, n: usize, forced: bool) {
        let mut last_end_v2 = None;
        for _ in 0..n {
            let Some(q) = self.queue.pop_front() else { break };
            self.queued_time -= q.min_move_t;
            let mv = finalize(&q, self.print_time);
            self.print_time = mv.end_time();
            last_end_v2 = Some(q.end_v2);
            self.ready.push_back(mv);
        }
        if self.queue.is_empty() {
            self.queued_time = 0.0;
        }
        // The next pass must start the new front move exactly at the speed the last final
        // move ended with.
        if let (Some(end_v2), Some(head)) = (last_end_v2, self.queue.front_mut()) {
            head.max_start_v2 = head.max_start_v2.min(end_v2);
            if forced {
                head.max_smoothed_v2 = head.max_start_v2;
            }
        }
    }
}

/// Durations of the accel / cruise / decel phases from the chosen speeds (each phase's time is
/// its distance over its mean speed).
fn finalize(q: &Queued, print_time: f64) -> Move {
    let mut mv = q.mv;
    let half_inv_accel = 0.5 / mv.accel;
    let accel_d = ((q.cruise_v2 - q.start_v2) * half_inv_accel).max(0.0);
    let decel_d = ((q.cruise_v2 - q.end_v2) * half_inv_accel).max(0.0);
    let cruise_d = (mv.move_d - accel_d - decel_d).max(0.0);
    mv.start_v = q.start_v2.max(0.0).sqrt();
    mv.cruise_v = q.cruise_v2.max(0.0).sqrt();
    mv.end_v = q.end_v2.max(0.0).sqrt();
    let mean = |a: f64, b: f64| 0.5 * (a + b);
    mv.accel_t = if accel_d > 0.0 {
        accel_d / mean(mv.start_v, mv.cruise_v)
    } else {
        0.0
    };
    mv.cruise_t = if cruise_d > 0.0 && mv.cruise_v > 0.0 {
        cruise_d / mv.cruise_v
    } else {
        0.0
    };
    mv.decel_t = if decel_d > 0.0 {
        decel_d / mean(mv.end_v, mv.cruise_v)
    } else {
        0.0
    };
    debug_assert!(mv.duration().is_finite() && mv.duration() > 0.0, "{q:?}");
    mv.print_time = print_time;
    mv
}

#[cfg(test)]
mod tests;
