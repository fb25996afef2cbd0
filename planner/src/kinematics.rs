//! Kinematics: where each stepper is (in mm of its own travel) for a toolhead position, and back.
//!
//! Every kinematics supported so far is *linear*: a stepper's position is a fixed linear
//! combination of X, Y, Z, E (cartesian `x`, corexy `a = x + y`, `b = x − y`, the extruder
//! `e`). Along a straight move the stepper then moves at a constant share of the move's speed,
//! so its step times have closed forms ([`crate::stepgen`]). A non-linear kinematics (delta)
//! would add a [`StepperMap`] variant and use step generation's iterative fallback.

use crate::toolhead::Move;

/// How a stepper's position follows the toolhead.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum StepperMap {
    /// stepper = Σ coeffs\[i\] · pos\[i\] over X, Y, Z, E.
    Linear([f64; 4]),
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
        }
    }

    /// The coefficients when the map is linear (enables closed-form step times).
    #[inline]
    pub fn linear_coeffs(&self) -> Option<&[f64; 4]> {
        match &self.map {
            StepperMap::Linear(c) => Some(c),
        }
    }
}

/// The printer's kinematics.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kinematics {
    Cartesian,
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
        match (self, axis) {
            (Kinematics::Cartesian, 0..=3) => Ok(StepperKin::axis(axis, step_dist)),
            _ => Err(KinError { kin: *self, axis }),
        }
    }

    /// Forward kinematics: toolhead X, Y, Z from the three rail positions (mm).
    pub fn forward(&self, rails: [f64; 3]) -> [f64; 3] {
        match self {
            Kinematics::Cartesian => rails,
        }
    }

    /// Inverse kinematics: rail positions (mm) for toolhead X, Y, Z.
    pub fn inverse(&self, pos: [f64; 3]) -> [f64; 3] {
        match self {
            Kinematics::Cartesian => pos,
        }
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
