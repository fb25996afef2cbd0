//! Bed levelling maths (Klipper's `[bed_mesh]`): a probed grid of bed heights, upsampled and
//! interpolated into a Z offset at any X, Y, and moves split along it. Pure computation.
//!
//! - [`ZMesh`]: the probed matrix (`probed[row][col]`, row = Y index, col = X index, evenly
//!   spaced between `min` and `max`) upsampled by `mesh_pps` points between each pair of probed
//!   points, with Lagrange polynomials through a whole row/column ([`Algorithm::Lagrange`]) or a
//!   cardinal Hermite spline of tension `bicubic_tension` through four neighbours
//!   ([`Algorithm::Bicubic`]); [`ZMesh::calc_z`] interpolates the upsampled grid bilinearly
//!   (clamped to the mesh's rectangle outside it).
//! - [`split`]: fade (`fade_start`/`fade_end`/`fade_target`) and the move splitter
//!   (`split_delta_z`, `move_check_distance`).
//! - [`points`]: the probe points of `BED_MESH_CALIBRATE` on rectangular and round beds.
//! - [`tilt`]: `Z_TILT_ADJUST`'s plane fit and per-motor corrections.

pub mod points;
pub mod split;
pub mod tilt;

/// How the probed points are upsampled.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Algorithm {
    /// One polynomial through every point of a row (then of a column); at most 6 points.
    Lagrange,
    /// A cardinal spline through each four consecutive points; at least 4 points.
    Bicubic,
}

impl Algorithm {
    /// Klipper's option value.
    pub fn name(self) -> &'static str {
        match self {
            Algorithm::Lagrange => "lagrange",
            Algorithm::Bicubic => "bicubic",
        }
    }
}

/// Largest probe count per axis Lagrange interpolation is allowed (its polynomials oscillate
/// beyond it).
pub const LAGRANGE_MAX_COUNT: usize = 6;
/// Smallest probe count per axis of bicubic interpolation.
pub const BICUBIC_MIN_COUNT: usize = 4;

/// The mesh's geometry and interpolation settings.
#[derive(Debug, Clone, PartialEq)]
pub struct MeshParams {
    /// Lower-left probed point (X, Y).
    pub min: [f64; 2],
    /// Upper-right probed point.
    pub max: [f64; 2],
    /// Probed points per row (X) and per column (Y), each ≥ 2.
    pub count: [usize; 2],
    /// Interpolated points between two probed points, per axis.
    pub pps: [usize; 2],
    pub algorithm: Algorithm,
    /// Bicubic tension, 0..=2.
    pub tension: f64,
}

impl MeshParams {
    /// The algorithm actually used: Klipper falls back to Lagrange when bicubic lacks points,
    /// and interpolation is off without `pps`.
    pub fn effective_algorithm(&self) -> Algorithm {
        if self.count.iter().any(|&c| c < BICUBIC_MIN_COUNT) {
            Algorithm::Lagrange
        } else {
            self.algorithm
        }
    }
}

/// Why a mesh cannot be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MeshError {
    #[error("bed_mesh: probe count must be at least 2 per axis, got {0}x{1}")]
    TooFewPoints(usize, usize),
    #[error("bed_mesh: probed matrix is {rows}x{cols}, expected {want_rows}x{want_cols}")]
    Shape {
        rows: usize,
        cols: usize,
        want_rows: usize,
        want_cols: usize,
    },
    #[error("bed_mesh: mesh_max ({max_x}, {max_y}) must be above mesh_min ({min_x}, {min_y})")]
    Extent {
        min_x: f64,
        min_y: f64,
        max_x: f64,
        max_y: f64,
    },
    #[error("bed_mesh: probed value {0} is not a finite number")]
    NotFinite(f64),
    #[error(
        "bed_mesh: lagrange interpolation supports at most {LAGRANGE_MAX_COUNT} points per axis, got {0}"
    )]
    LagrangeCount(usize),
    #[error("bed_mesh: the upsampled mesh would have {0} points (at most 100000)")]
    TooLarge(usize),
}

/// Points of an upsampled mesh at most (keeps a bad profile from exhausting memory).
const MAX_MESH_POINTS: usize = 100_000;

/// A probed and upsampled bed mesh.
#[derive(Debug, Clone, PartialEq)]
pub struct ZMesh {
    params: MeshParams,
    probed: Vec<Vec<f64>>,
    /// Upsampled points per axis.
    mesh_count: [usize; 2],
    /// Upsampled heights, row-major (Y rows of X points).
    mesh: Vec<f64>,
    /// Distance between upsampled points per axis.
    step: [f64; 2],
}

impl ZMesh {
    /// Builds the mesh from `probed[row][col]` (rows along Y from `min`'s Y).
    pub fn new(params: MeshParams, probed: Vec<Vec<f64>>) -> Result<ZMesh, MeshError> {
        let [cx, cy] = params.count;
        if cx < 2 || cy < 2 {
            return Err(MeshError::TooFewPoints(cx, cy));
        }
        if probed.len() != cy || probed.iter().any(|r| r.len() != cx) {
            return Err(MeshError::Shape {
                rows: probed.len(),
                cols: probed.first().map_or(0, Vec::len),
                want_rows: cy,
                want_cols: cx,
            });
        }
        let extent_ok = (0..2)
            .all(|i| params.min[i].is_finite() && params.max[i].is_finite() && params.max[i] > params.min[i]);
        if !extent_ok {
            return Err(MeshError::Extent {
                min_x: params.min[0],
                min_y: params.min[1],
                max_x: params.max[0],
                max_y: params.max[1],
            });
        }
        if let Some(&v) = probed.iter().flatten().find(|v| !v.is_finite()) {
            return Err(MeshError::NotFinite(v));
        }
        let algorithm = params.effective_algorithm();
        if algorithm == Algorithm::Lagrange && cx.max(cy) > LAGRANGE_MAX_COUNT && params.pps != [0, 0] {
            return Err(MeshError::LagrangeCount(cx.max(cy)));
        }
        let mesh_count = [
            (cx - 1).saturating_mul(params.pps[0]).saturating_add(cx),
            (cy - 1).saturating_mul(params.pps[1]).saturating_add(cy),
        ];
        let total = mesh_count[0].saturating_mul(mesh_count[1]);
        if total > MAX_MESH_POINTS {
            return Err(MeshError::TooLarge(total));
        }
        let step = [
            (params.max[0] - params.min[0]) / (mesh_count[0] - 1) as f64,
            (params.max[1] - params.min[1]) / (mesh_count[1] - 1) as f64,
        ];
        // Upsample every probed row along X, then every column of that along Y.
        let rows: Vec<Vec<f64>> = probed
            .iter()
            .map(|r| upsample(r, params.pps[0], algorithm, params.tension))
            .collect();
        let mut mesh = vec![0.0; total];
        for col in 0..mesh_count[0] {
            let column: Vec<f64> = rows.iter().map(|r| r[col]).collect();
            let up = upsample(&column, params.pps[1], algorithm, params.tension);
            for (row, v) in up.into_iter().enumerate() {
                mesh[row * mesh_count[0] + col] = v;
            }
        }
        Ok(ZMesh {
            params,
            probed,
            mesh_count,
            mesh,
            step,
        })
    }

    pub fn params(&self) -> &MeshParams {
        &self.params
    }

    /// The probed heights, `[row][col]`.
    pub fn probed(&self) -> &[Vec<f64>] {
        &self.probed
    }

    /// Upsampled points per axis (X, Y).
    pub fn mesh_count(&self) -> [usize; 2] {
        self.mesh_count
    }

    /// The upsampled grid as rows (Y) of X points.
    pub fn mesh_rows(&self) -> Vec<Vec<f64>> {
        self.mesh
            .chunks(self.mesh_count[0].max(1))
            .map(<[f64]>::to_vec)
            .collect()
    }

    /// The X, Y of probed point (`col`, `row`).
    pub fn probed_point(&self, col: usize, row: usize) -> [f64; 2] {
        let p = &self.params;
        let at = |i: usize, k: usize| p.min[i] + (p.max[i] - p.min[i]) * k as f64 / (p.count[i] - 1) as f64;
        [at(0, col), at(1, row)]
    }

    /// Smallest and largest probed height.
    pub fn range(&self) -> (f64, f64) {
        let it = self.probed.iter().flatten().copied();
        (
            it.clone().fold(f64::INFINITY, f64::min),
            it.fold(f64::NEG_INFINITY, f64::max),
        )
    }

    /// The mean probed height.
    pub fn average(&self) -> f64 {
        let n = self.params.count[0] * self.params.count[1];
        self.probed.iter().flatten().sum::<f64>() / n as f64
    }

    /// The bed height at (`x`, `y`): bilinear between the four surrounding upsampled points,
    /// the nearest edge outside the mesh.
    pub fn calc_z(&self, x: f64, y: f64) -> f64 {
        let (tx, ix) = self.index(x, 0);
        let (ty, iy) = self.index(y, 1);
        let w = self.mesh_count[0];
        let at = |r: usize, c: usize| self.mesh.get(r * w + c).copied().unwrap_or(0.0);
        let z0 = lerp(tx, at(iy, ix), at(iy, ix + 1));
        let z1 = lerp(tx, at(iy + 1, ix), at(iy + 1, ix + 1));
        lerp(ty, z0, z1)
    }

    /// The cell (lower index, ≤ count − 2) holding coordinate `v` of axis `axis` and the
    /// fraction within it (0..=1, clamped).
    fn index(&self, v: f64, axis: usize) -> (f64, usize) {
        let n = self.mesh_count[axis];
        let pos = (v - self.params.min[axis]) / self.step[axis];
        let pos = if pos.is_finite() {
            pos.clamp(0.0, (n - 1) as f64)
        } else {
            0.0
        };
        let i = (pos.floor() as usize).min(n - 2);
        (pos - i as f64, i)
    }
}

fn lerp(t: f64, a: f64, b: f64) -> f64 {
    a + t * (b - a)
}

/// `pts` (≥ 2 evenly spaced values) with `pps` values inserted between each two, by
/// `algorithm`.
fn upsample(pts: &[f64], pps: usize, algorithm: Algorithm, tension: f64) -> Vec<f64> {
    let n = pts.len();
    let total = (n - 1) * pps + n;
    let mut out = Vec::with_capacity(total);
    for k in 0..total {
        let seg = k / (pps + 1);
        let frac = (k % (pps + 1)) as f64 / (pps + 1) as f64;
        if frac == 0.0 || seg + 1 >= n {
            out.push(pts[seg.min(n - 1)]);
            continue;
        }
        let pos = seg as f64 + frac;
        out.push(match algorithm {
            Algorithm::Lagrange => lagrange(pts, pos),
            Algorithm::Bicubic => {
                let get = |i: isize| pts[i.clamp(0, n as isize - 1) as usize];
                let s = seg as isize;
                cardinal([get(s - 1), get(s), get(s + 1), get(s + 2)], frac, tension)
            }
        });
    }
    out
}

/// The Lagrange polynomial through (i, pts[i]) evaluated at `pos`.
fn lagrange(pts: &[f64], pos: f64) -> f64 {
    let mut sum = 0.0;
    for (i, &v) in pts.iter().enumerate() {
        let mut w = 1.0;
        for j in 0..pts.len() {
            if j != i {
                w *= (pos - j as f64) / (i as f64 - j as f64);
            }
        }
        sum += w * v;
    }
    sum
}

/// The cardinal Hermite spline between p[1] and p[2] at `t` (0..1): tangents
/// `tension · (p[2] − p[0])` and `tension · (p[3] − p[1])` (tension 0.5: Catmull-Rom).
fn cardinal(p: [f64; 4], t: f64, tension: f64) -> f64 {
    let t2 = t * t;
    let t3 = t2 * t;
    let m1 = tension * (p[2] - p[0]);
    let m2 = tension * (p[3] - p[1]);
    p[1] * (2.0 * t3 - 3.0 * t2 + 1.0)
        + p[2] * (-2.0 * t3 + 3.0 * t2)
        + m1 * (t3 - 2.0 * t2 + t)
        + m2 * (t3 - t2)
}

#[cfg(test)]
mod tests;
