//! Kinematics: where each stepper is (in mm of its own travel) for a toolhead position, and back.
//!
//! Every kinematics supported so far is *linear*: a stepper's position is a fixed linear
//! combination of X, Y, Z, E (cartesian `x`, corexy `a = x + y`, `b = x − y`, the extruder
//! `e`). Along a straight move the stepper then moves at a constant share of the move's speed,
//! so its step times have closed forms ([`crate::stepgen`]).
//!
//! Delta is not linear: carriage i sits on a vertical tower at (tx_i, ty_i) and holds the
//! effector with a rod of length L_i, so its height is h_i = z + √(L_i² − (x − tx_i)² −
//! (y − ty_i)²) (inverse). The forward map intersects the three spheres of radius L_i around
//! (tx_i, ty_i, h_i) and takes the lower intersection (trilateration). Towers stand at `radius`
//! from the centre at the configured angles (Klipper: 210°, 330°, 90°). Step generation uses its
//! iterative solver for these steppers.

use crate::toolhead::Move;

/// How a stepper's position follows the toolhead.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum StepperMap {
    /// stepper = Σ coeffs\[i\] · pos\[i\] over X, Y, Z, E.
    Linear([f64; 4]),
    /// A delta carriage: height = z + √(arm2 − (x − tower.0)² − (y − tower.1)²).
    Delta { tower: (f64, f64), arm2: f64 },
}

/// A linear delta printer's geometry.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DeltaGeometry {
    /// Horizontal distance from the centre to each tower's carriage joint (mm).
    pub radius: f64,
    /// Diagonal rod length of towers A, B, C (mm).
    pub arm_length: [f64; 3],
    /// Tower angles in degrees (Klipper's defaults: 210, 330, 90).
    pub angles: [f64; 3],
}

impl DeltaGeometry {
    /// Tower positions (x, y).
    pub fn towers(&self) -> [(f64, f64); 3] {
        self.angles.map(|a| {
            let r = a.to_radians();
            (self.radius * r.cos(), self.radius * r.sin())
        })
    }

    /// Largest distance from the centre the effector may reach: min(radius, shortest arm −
    /// radius), as Klipper's default print radius.
    pub fn max_xy_radius(&self) -> f64 {
        let min_arm = self.arm_length.iter().copied().fold(f64::INFINITY, f64::min);
        self.radius.min(min_arm - self.radius)
    }

    /// Checks the numbers make a printer.
    pub fn validate(&self) -> Result<(), String> {
        let finite =
            self.radius.is_finite() && self.arm_length.iter().chain(&self.angles).all(|v| v.is_finite());
        if !finite || self.radius <= 0.0 {
            return Err(format!("delta radius {} must be a positive number", self.radius));
        }
        if self.arm_length.iter().any(|&l| l <= self.radius) {
            return Err(format!(
                "delta arm lengths {:?} must exceed the radius {}",
                self.arm_length, self.radius
            ));
        }
        let t = self.towers();
        let area = (t[1].0 - t[0].0) * (t[2].1 - t[0].1) - (t[2].0 - t[0].0) * (t[1].1 - t[0].1);
        if area.abs() < 1e-6 * self.radius * self.radius {
            return Err(format!(
                "delta tower angles {:?} put the towers in a line",
                self.angles
            ));
        }
        Ok(())
    }
}

/// One stepper's kinematics: its map and its step distance (mm per step).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepperKin {
    pub map: StepperMap,
    pub step_dist: f64,
}

impl StepperKin {
    /// A stepper driving one axis directly (cartesian X/Y/Z, or the extruder for axis 3).
    pub fn axis(axis: usize, step_dist: f64) -> StepperKin {
        let mut c = [0.0; 4];
        if let Some(v) = c.get_mut(axis) {
            *v = 1.0;
        }
        StepperKin {
            map: StepperMap::Linear(c),
            step_dist,
        }
    }

    /// Inverse kinematics: the stepper's position (mm) for toolhead position `pos`.
    #[inline]
    pub fn position(&self, pos: &[f64; 4]) -> f64 {
        match &self.map {
            StepperMap::Linear(c) => c[0] * pos[0] + c[1] * pos[1] + c[2] * pos[2] + c[3] * pos[3],
            StepperMap::Delta { tower, arm2 } => {
                let (dx, dy) = (pos[0] - tower.0, pos[1] - tower.1);
                pos[2] + (arm2 - dx * dx - dy * dy).max(0.0).sqrt()
            }
        }
    }

    /// The stepper's position (mm) `t_rel` seconds into `mv`.
    pub fn position_at(&self, mv: &Move, t_rel: f64) -> f64 {
        match &self.map {
            StepperMap::Linear(c) => {
                let x0 = self.position(&mv.start_pos);
                let r = c[0] * mv.axes_r[0] + c[1] * mv.axes_r[1] + c[2] * mv.axes_r[2] + c[3] * mv.axes_r[3];
                x0 + r * mv.distance_at(t_rel)
            }
            StepperMap::Delta { .. } => self.position(&mv.position_at(t_rel)),
        }
    }

    /// The coefficients when the map is linear (enables closed-form step times).
    #[inline]
    pub fn linear_coeffs(&self) -> Option<&[f64; 4]> {
        match &self.map {
            StepperMap::Linear(c) => Some(c),
            StepperMap::Delta { .. } => None,
        }
    }
}

/// The printer's kinematics.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum Kinematics {
    #[default]
    Cartesian,
    /// a = x + y (stepper index 0), b = x − y (index 1), z direct.
    CoreXY,
    /// a = x + z (index 0), y direct (index 1), b = x − z (index 2).
    CoreXZ,
    /// Towers A, B, C (indices 0..=2).
    Delta(DeltaGeometry),
}

/// A stepper that the kinematics does not have.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("kinematics {kin:?} has no stepper for axis index {axis} (0..=3 = X, Y, Z, E)")]
pub struct KinError {
    pub kin: Kinematics,
    pub axis: usize,
}

impl Kinematics {
    /// The kinematics of the stepper driving rail `axis` (0..=2), or the extruder (3).
    pub fn stepper(&self, axis: usize, step_dist: f64) -> Result<StepperKin, KinError> {
        let lin = |c: [f64; 4]| {
            Ok(StepperKin {
                map: StepperMap::Linear(c),
                step_dist,
            })
        };
        match (self, axis) {
            (_, 3) | (Kinematics::Cartesian, 0..=2) => Ok(StepperKin::axis(axis, step_dist)),
            (Kinematics::CoreXY, 0) => lin([1.0, 1.0, 0.0, 0.0]),
            (Kinematics::CoreXY, 1) => lin([1.0, -1.0, 0.0, 0.0]),
            (Kinematics::CoreXY, 2) => Ok(StepperKin::axis(2, step_dist)),
            (Kinematics::CoreXZ, 0) => lin([1.0, 0.0, 1.0, 0.0]),
            (Kinematics::CoreXZ, 1) => Ok(StepperKin::axis(1, step_dist)),
            (Kinematics::CoreXZ, 2) => lin([1.0, 0.0, -1.0, 0.0]),
            (Kinematics::Delta(g), 0..=2) => Ok(StepperKin {
                map: StepperMap::Delta {
                    tower: g.towers()[axis],
                    arm2: g.arm_length[axis] * g.arm_length[axis],
                },
                step_dist,
            }),
            _ => Err(KinError { kin: *self, axis }),
        }
    }

    /// Forward kinematics: toolhead X, Y, Z from the three rail positions (mm).
    pub fn forward(&self, rails: [f64; 3]) -> [f64; 3] {
        let [a, b, c] = rails;
        match self {
            Kinematics::Cartesian => rails,
            Kinematics::CoreXY => [0.5 * (a + b), 0.5 * (a - b), c],
            Kinematics::CoreXZ => [0.5 * (a + c), b, 0.5 * (a - c)],
            Kinematics::Delta(g) => delta_forward(g, rails),
        }
    }

    /// Inverse kinematics: rail positions (mm) for toolhead X, Y, Z.
    pub fn inverse(&self, pos: [f64; 3]) -> [f64; 3] {
        let [x, y, z] = pos;
        match self {
            Kinematics::Cartesian => pos,
            Kinematics::CoreXY => [x + y, x - y, z],
            Kinematics::CoreXZ => [x + z, y, x - z],
            Kinematics::Delta(g) => {
                let t = g.towers();
                [0, 1, 2].map(|i| {
                    let (dx, dy) = (x - t[i].0, y - t[i].1);
                    z + (g.arm_length[i] * g.arm_length[i] - dx * dx - dy * dy)
                        .max(0.0)
                        .sqrt()
                })
            }
        }
    }
}

/// Trilateration: the effector under three carriages at heights `h`.
fn delta_forward(g: &DeltaGeometry, h: [f64; 3]) -> [f64; 3] {
    let t = g.towers();
    let p = [0, 1, 2].map(|i| [t[i].0, t[i].1, h[i]]);
    let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let scale = |a: [f64; 3], k: f64| [a[0] * k, a[1] * k, a[2] * k];
    let p21 = sub(p[1], p[0]);
    let d = dot(p21, p21).sqrt();
    let ex = scale(p21, 1.0 / d);
    let p31 = sub(p[2], p[0]);
    let i = dot(ex, p31);
    let ey_raw = sub(p31, scale(ex, i));
    let ey = scale(ey_raw, 1.0 / dot(ey_raw, ey_raw).sqrt());
    let ez = [
        ex[1] * ey[2] - ex[2] * ey[1],
        ex[2] * ey[0] - ex[0] * ey[2],
        ex[0] * ey[1] - ex[1] * ey[0],
    ];
    let j = dot(ey, p31);
    let [r1, r2, r3] = g.arm_length.map(|l| l * l);
    let x = (r1 - r2 + d * d) / (2.0 * d);
    let y = (r1 - r3 + i * i + j * j - 2.0 * i * x) / (2.0 * j);
    let zz = (r1 - x * x - y * y).max(0.0).sqrt();
    // ez points up or down depending on the tower order: take the lower of the two solutions.
    let a = [0, 1, 2].map(|k| p[0][k] + x * ex[k] + y * ey[k] + zz * ez[k]);
    let b = [0, 1, 2].map(|k| p[0][k] + x * ex[k] + y * ey[k] - zz * ez[k]);
    if a[2] < b[2] {
        a
    } else {
        b
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cartesian_maps_axes() {
        let k = Kinematics::Cartesian;
        let y = k.stepper(1, 0.0125).unwrap();
        assert_eq!(y.position(&[1.0, 2.0, 3.0, 4.0]), 2.0);
        let e = k.stepper(3, 0.01).unwrap();
        assert_eq!(e.position(&[1.0, 2.0, 3.0, 4.0]), 4.0);
        assert!(k.stepper(4, 0.01).is_err());
        assert_eq!(k.forward(k.inverse([1.0, 2.0, 3.0])), [1.0, 2.0, 3.0]);
    }

    #[test]
    fn core_kinematics_round_trip() {
        for k in [Kinematics::Cartesian, Kinematics::CoreXY, Kinematics::CoreXZ] {
            let p = [12.5, -3.25, 7.0];
            let rails = k.inverse(p);
            let back = k.forward(rails);
            for i in 0..3 {
                assert!((back[i] - p[i]).abs() < 1e-12, "{k:?}");
                let s = k.stepper(i, 0.01).unwrap();
                assert!(
                    (s.position(&[p[0], p[1], p[2], 1.0]) - rails[i]).abs() < 1e-12,
                    "{k:?} {i}"
                );
            }
        }
    }

    fn delta() -> DeltaGeometry {
        DeltaGeometry {
            radius: 140.0,
            arm_length: [270.0, 271.0, 269.5],
            angles: [210.0, 330.0, 90.0],
        }
    }

    #[test]
    fn delta_round_trips() {
        let k = Kinematics::Delta(delta());
        assert!(delta().validate().is_ok());
        for p in [
            [0.0, 0.0, 0.0],
            [50.0, -30.0, 12.0],
            [-100.0, 20.0, 250.0],
            [0.0, 129.0, 5.0],
        ] {
            let rails = k.inverse(p);
            let back = k.forward(rails);
            for i in 0..3 {
                assert!((back[i] - p[i]).abs() < 1e-9, "{p:?} → {rails:?} → {back:?}");
                let s = k.stepper(i, 0.01).unwrap();
                assert!((s.position(&[p[0], p[1], p[2], 0.0]) - rails[i]).abs() < 1e-12);
            }
        }
        let mut bad = delta();
        bad.arm_length[1] = 100.0;
        assert!(bad.validate().is_err());
        bad = delta();
        bad.angles = [90.0, 90.0, 270.0];
        assert!(bad.validate().is_err());
        assert_eq!(delta().max_xy_radius(), 129.5);
    }

    #[test]
    fn position_along_a_move() {
        let mv = Move {
            print_time: 0.0,
            start_pos: [1.0, 1.0, 0.0, 0.0],
            end_pos: [4.0, 5.0, 0.0, 0.0],
            axes_r: [0.6, 0.8, 0.0, 0.0],
            move_d: 5.0,
            start_v: 5.0,
            cruise_v: 5.0,
            end_v: 5.0,
            accel: 100.0,
            accel_t: 0.0,
            cruise_t: 1.0,
            decel_t: 0.0,
        };
        let x = StepperKin::axis(0, 0.01);
        assert!((x.position_at(&mv, 0.5) - 2.5).abs() < 1e-12);
        assert!((x.position_at(&mv, 1.0) - 4.0).abs() < 1e-12);
        let y = StepperKin::axis(1, 0.01);
        assert!((y.position_at(&mv, 1.0) - 5.0).abs() < 1e-12);
    }
}
