//! Where `BED_MESH_CALIBRATE` probes and how the results become the probed matrix.
//!
//! Rectangular bed: `count` = (x, y) points evenly spaced from `min` to `max`, probed row by
//! row from `min`'s Y, the rows in alternating X direction (left to right, then right to left)
//! to keep travel short. Round bed: a square grid of `count` × `count` points (odd) over the
//! circle of `radius` around `origin`, keeping only the points inside it (within a 1 µm
//! tolerance); the matrix's missing corners take the nearest probed value of their row (the
//! mesh stays rectangular, as Klipper's round meshes are).

/// A grid of probe points.
#[derive(Debug, Clone, PartialEq)]
pub struct ProbeGrid {
    pub min: [f64; 2],
    pub max: [f64; 2],
    pub count: [usize; 2],
    /// Round bed: (origin, radius); only points inside the circle are probed.
    pub round: Option<([f64; 2], f64)>,
}

/// One point to probe: its grid position and X, Y.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbePoint {
    pub col: usize,
    pub row: usize,
    pub xy: [f64; 2],
}

impl ProbeGrid {
    /// A round bed's grid: `count` (odd, ≥ 3) points per axis across the circle.
    pub fn round(origin: [f64; 2], radius: f64, count: usize) -> ProbeGrid {
        ProbeGrid {
            min: [origin[0] - radius, origin[1] - radius],
            max: [origin[0] + radius, origin[1] + radius],
            count: [count, count],
            round: Some((origin, radius)),
        }
    }

    /// The X, Y of grid point (`col`, `row`).
    pub fn xy(&self, col: usize, row: usize) -> [f64; 2] {
        let at = |i: usize, k: usize| {
            let n = self.count[i].max(2) - 1;
            self.min[i] + (self.max[i] - self.min[i]) * k as f64 / n as f64
        };
        [at(0, col), at(1, row)]
    }

    /// The points to probe, in probing order.
    pub fn points(&self) -> Vec<ProbePoint> {
        let mut out = Vec::new();
        for row in 0..self.count[1] {
            let cols: Vec<usize> = if row % 2 == 0 {
                (0..self.count[0]).collect()
            } else {
                (0..self.count[0]).rev().collect()
            };
            for col in cols {
                let xy = self.xy(col, row);
                let inside = self.round.is_none_or(|(o, r)| {
                    ((xy[0] - o[0]).powi(2) + (xy[1] - o[1]).powi(2)).sqrt() <= r + 1e-6
                });
                if inside {
                    out.push(ProbePoint { col, row, xy });
                }
            }
        }
        out
    }

    /// The probed matrix (`[row][col]`) from the measured heights of [`Self::points`] in the
    /// same order; `None` if their number differs or a row has no point.
    pub fn matrix(&self, heights: &[f64]) -> Option<Vec<Vec<f64>>> {
        let points = self.points();
        if points.len() != heights.len() {
            return None;
        }
        let mut m: Vec<Vec<Option<f64>>> = vec![vec![None; self.count[0]]; self.count[1]];
        for (p, &z) in points.iter().zip(heights) {
            m[p.row][p.col] = Some(z);
        }
        m.into_iter()
            .map(|row| {
                let first = row.iter().position(Option::is_some)?;
                let last = row.iter().rposition(Option::is_some)?;
                Some(
                    row.iter()
                        .enumerate()
                        .map(|(c, v)| match v {
                            Some(v) => *v,
                            None if c < first => row[first].unwrap_or(0.0),
                            None => row[last].unwrap_or(0.0),
                        })
                        .collect(),
                )
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rectangular_points_snake_along_the_rows() {
        let g = ProbeGrid {
            min: [10.0, 20.0],
            max: [30.0, 40.0],
            count: [3, 2],
            round: None,
        };
        let xy: Vec<[f64; 2]> = g.points().iter().map(|p| p.xy).collect();
        assert_eq!(
            xy,
            [
                [10.0, 20.0],
                [20.0, 20.0],
                [30.0, 20.0],
                [30.0, 40.0],
                [20.0, 40.0],
                [10.0, 40.0]
            ]
        );
        let m = g.matrix(&[1.0, 2.0, 3.0, 6.0, 5.0, 4.0]).unwrap();
        assert_eq!(m, vec![vec![1.0, 2.0, 3.0], vec![4.0, 5.0, 6.0]]);
        assert_eq!(g.matrix(&[1.0]), None);
    }

    #[test]
    fn round_beds_skip_the_corners_and_pad_the_rows() {
        let g = ProbeGrid::round([0.0, 0.0], 10.0, 3);
        let pts = g.points();
        // The 4 corners are outside the circle.
        assert_eq!(pts.len(), 5);
        assert!(pts.iter().all(|p| p.xy[0].hypot(p.xy[1]) <= 10.0 + 1e-6));
        let heights: Vec<f64> = (0..5).map(f64::from).collect();
        let m = g.matrix(&heights).unwrap();
        // Row 0: only the centre column (0); row 1 (reversed): 3 points 1, 2, 3 from the right.
        assert_eq!(m, vec![vec![0.0; 3], vec![3.0, 2.0, 1.0], vec![4.0; 3]]);
    }
}
