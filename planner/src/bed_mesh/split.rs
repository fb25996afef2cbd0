//! Applying a mesh to moves: the Z offset at a point (faded out with height) and the split of a
//! move into segments along which the offset changes linearly, as Klipper's bed_mesh does.
//!
//! Fade: below `fade_start` the full mesh offset applies; between `fade_start` and `fade_end`
//! it blends linearly into `fade_target`; above `fade_end` only `fade_target` remains (with
//! `fade_end` 0 fading is off). Offset at (x, y, z) = `fade_target + factor(z) · (mesh(x, y) −
//! fade_target)`.
//!
//! Splitting: a move that changes X or Y is walked in steps of `move_check_distance` (mm of
//! XY travel); where the offset has changed by `split_delta_z` or more since the last segment's
//! end, a segment ends there (so Z follows the mesh with linear pieces); the move's own end
//! always ends the last one. A Z-only or extrude-only move is one segment.

use super::ZMesh;

/// Fade and split settings of `[bed_mesh]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ApplySettings {
    pub fade_start: f64,
    /// 0: no fade.
    pub fade_end: f64,
    /// `None`: the mesh's average height.
    pub fade_target: Option<f64>,
    /// Offset change that ends a segment (mm), > 0.
    pub split_delta_z: f64,
    /// XY distance between offset checks (mm), > 0.
    pub move_check_distance: f64,
}

impl Default for ApplySettings {
    fn default() -> Self {
        ApplySettings {
            fade_start: 1.0,
            fade_end: 0.0,
            fade_target: None,
            split_delta_z: 0.025,
            move_check_distance: 5.0,
        }
    }
}

/// A mesh in use: offsets and splits moves.
#[derive(Debug, Clone, PartialEq)]
pub struct AppliedMesh {
    pub mesh: ZMesh,
    pub settings: ApplySettings,
    /// The resolved fade target (0 without fade).
    target: f64,
}

/// Segments per move at most (a bad setting cannot make a move endless).
const MAX_SEGMENTS: usize = 100_000;

impl AppliedMesh {
    pub fn new(mesh: ZMesh, settings: ApplySettings) -> AppliedMesh {
        let target = match (settings.fade_end > 0.0, settings.fade_target) {
            (false, _) => 0.0,
            (true, Some(t)) => t,
            (true, None) => mesh.average(),
        };
        AppliedMesh {
            mesh,
            settings,
            target,
        }
    }

    /// The fade factor at height `z`: 1 below `fade_start`, 0 from `fade_end` on.
    pub fn fade_factor(&self, z: f64) -> f64 {
        let s = &self.settings;
        if s.fade_end <= 0.0 || z <= s.fade_start {
            return 1.0;
        }
        if z >= s.fade_end || s.fade_end <= s.fade_start {
            return 0.0;
        }
        (s.fade_end - z) / (s.fade_end - s.fade_start)
    }

    /// The Z offset added at (x, y) for a move at height z.
    pub fn offset(&self, x: f64, y: f64, z: f64) -> f64 {
        let f = self.fade_factor(z);
        if f == 0.0 {
            return self.target;
        }
        self.target + f * (self.mesh.calc_z(x, y) - self.target)
    }

    /// The toolhead position of G-code position `p` (X, Y, Z, E): Z plus the offset.
    pub fn transform(&self, p: [f64; 4]) -> [f64; 4] {
        [p[0], p[1], p[2] + self.offset(p[0], p[1], p[2]), p[3]]
    }

    /// The G-code position of toolhead position `p` (inverse of [`Self::transform`]): the
    /// offset is piecewise linear in Z (full, fading, faded), so each piece is solved exactly
    /// and the one whose Z lies in its own range is taken.
    pub fn untransform(&self, p: [f64; 4]) -> [f64; 4] {
        let s = &self.settings;
        let m = self.mesh.calc_z(p[0], p[1]);
        let full = p[2] - m;
        let z = if s.fade_end <= 0.0 || full <= s.fade_start {
            full
        } else if p[2] - self.target >= s.fade_end {
            p[2] - self.target
        } else {
            // z + target + (fade_end − z) / span · d = p, with d = mesh − target.
            let span = s.fade_end - s.fade_start;
            let d = m - self.target;
            let k = 1.0 - d / span;
            if k.abs() > 1e-12 {
                (p[2] - self.target - s.fade_end * d / span) / k
            } else {
                full
            }
        };
        [p[0], p[1], z, p[3]]
    }

    /// The toolhead positions of the segments of the move from G-code position `from` to `to`
    /// (each transformed; the last one is `to`'s), appended to `out`.
    pub fn split(&self, from: [f64; 4], to: [f64; 4], out: &mut Vec<[f64; 4]>) {
        let dxy = ((to[0] - from[0]).powi(2) + (to[1] - from[1]).powi(2)).sqrt();
        let check = self.settings.move_check_distance;
        let usable = dxy.is_finite() && dxy > 0.0 && check > 0.0;
        if !usable {
            out.push(self.transform(to));
            return;
        }
        let at = |t: f64| -> [f64; 4] {
            let mut p = [0.0; 4];
            for i in 0..4 {
                p[i] = from[i] + t * (to[i] - from[i]);
            }
            p
        };
        let n = ((dxy / check).ceil() as usize).clamp(1, MAX_SEGMENTS);
        let mut last = self.offset(from[0], from[1], from[2]);
        for k in 1..n {
            let p = at(k as f64 / n as f64);
            let off = self.offset(p[0], p[1], p[2]);
            if (off - last).abs() >= self.settings.split_delta_z {
                out.push([p[0], p[1], p[2] + off, p[3]]);
                last = off;
            }
        }
        out.push(self.transform(to));
    }
}

#[cfg(test)]
mod tests {
    use super::super::{Algorithm, MeshParams};
    use super::*;

    fn tilted() -> AppliedMesh {
        // z = 0.01 x: linear, so every interpolation is exact.
        let params = MeshParams {
            min: [0.0, 0.0],
            max: [100.0, 100.0],
            count: [3, 3],
            pps: [2, 2],
            algorithm: Algorithm::Lagrange,
            tension: 0.2,
        };
        let probed = vec![vec![0.0, 0.5, 1.0]; 3];
        let mesh = ZMesh::new(params, probed).unwrap();
        AppliedMesh::new(mesh, ApplySettings::default())
    }

    #[test]
    fn a_long_move_is_split_where_the_offset_changes() {
        let m = tilted();
        let mut out = Vec::new();
        m.split([0.0, 50.0, 0.2, 0.0], [100.0, 50.0, 0.2, 5.0], &mut out);
        // Checks every 5 mm, the offset changes 0.05 per check: a segment at each.
        assert_eq!(out.len(), 20);
        for p in &out {
            assert!((p[2] - (0.2 + 0.01 * p[0])).abs() < 1e-9, "{p:?}");
            assert!((p[3] - p[0] / 20.0).abs() < 1e-9);
        }
        assert_eq!(out.last().copied(), Some([100.0, 50.0, 1.2, 5.0]));
        out.clear();
        m.split([0.0, 50.0, 0.2, 0.0], [0.0, 50.0, 3.0, 0.0], &mut out);
        assert_eq!(out, vec![[0.0, 50.0, 3.0, 0.0]], "a Z move is one segment");
    }

    #[test]
    fn fade_blends_into_the_target() {
        let mut m = tilted();
        m = AppliedMesh::new(
            m.mesh,
            ApplySettings {
                fade_start: 1.0,
                fade_end: 3.0,
                fade_target: Some(0.0),
                ..ApplySettings::default()
            },
        );
        assert_eq!(m.fade_factor(0.5), 1.0);
        assert_eq!(m.fade_factor(2.0), 0.5);
        assert_eq!(m.fade_factor(5.0), 0.0);
        assert!((m.offset(100.0, 0.0, 2.0) - 0.5).abs() < 1e-12);
        assert_eq!(m.offset(100.0, 0.0, 4.0), 0.0);
        let p = m.transform([80.0, 10.0, 1.5, 0.0]);
        let back = m.untransform(p);
        assert!((back[2] - 1.5).abs() < 1e-9, "{back:?}");
        // Without an explicit target it is the mesh's average.
        let avg = AppliedMesh::new(
            m.mesh.clone(),
            ApplySettings {
                fade_end: 3.0,
                ..ApplySettings::default()
            },
        );
        assert!((avg.offset(0.0, 0.0, 10.0) - 0.5).abs() < 1e-12);
    }

    proptest::proptest! {
        /// Every segment end lies on the straight move with Z plus the offset there, the last
        /// one is the move's end, and between two checks the offset changed by less than
        /// split_delta_z since the last segment's end.
        #[test]
        fn segments_follow_the_mesh(
            x0 in -10.0f64..110.0, y0 in -10.0f64..110.0,
            x1 in -10.0f64..110.0, y1 in -10.0f64..110.0,
            z in 0.0f64..1.0,
        ) {
            let m = tilted();
            let mut out = Vec::new();
            let from = [x0, y0, z, 0.0];
            let to = [x1, y1, z, 1.0];
            m.split(from, to, &mut out);
            proptest::prop_assert!(!out.is_empty());
            let last = out[out.len() - 1];
            proptest::prop_assert_eq!(last, m.transform(to));
            for p in &out {
                let t = p[3];
                proptest::prop_assert!((p[0] - (x0 + t * (x1 - x0))).abs() < 1e-6);
                proptest::prop_assert!((p[1] - (y0 + t * (y1 - y0))).abs() < 1e-6);
                proptest::prop_assert!((p[2] - z - m.offset(p[0], p[1], z)).abs() < 1e-9);
            }
        }
    }
}
