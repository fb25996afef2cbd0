//! Z_TILT_ADJUST's and QUAD_GANTRY_LEVEL's maths: the plane (or, for four corners, the
//! bilinear surface) through probed heights and each Z motor's correction.
//!
//! The probed heights `z_j` at points `p_j` are fitted by least squares with
//! `z = a + b·x + c·y` (when the points all lie on one line, with `z = a + s·t` along it, the
//! slope across it taken as 0). Where the fit is higher the nozzle met the bed later, so the
//! gantry is low there: motor `i` at `P_i` moves by `fit(P_i) − mean_i fit(P_i)`, which makes
//! the gantry parallel to the bed and keeps its mean height.

/// Corrections (mm, + is up) of the motors at `motors` from the probed `(point, z)` pairs;
/// `None` with fewer than 2 points or all at one place.
pub fn motor_adjustments(probed: &[([f64; 2], f64)], motors: &[[f64; 2]]) -> Option<Vec<f64>> {
    let fit = fit_plane(probed)?;
    let at: Vec<f64> = motors.iter().map(|m| fit(m[0], m[1])).collect();
    let mean = at.iter().sum::<f64>() / at.len().max(1) as f64;
    Some(at.iter().map(|v| v - mean).collect())
}

/// The least-squares plane (or line) through the points, as a function of (x, y).
pub fn fit_plane(probed: &[([f64; 2], f64)]) -> Option<impl Fn(f64, f64) -> f64> {
    let n = probed.len() as f64;
    if probed.len() < 2 {
        return None;
    }
    let mx = probed.iter().map(|(p, _)| p[0]).sum::<f64>() / n;
    let my = probed.iter().map(|(p, _)| p[1]).sum::<f64>() / n;
    let mz = probed.iter().map(|(_, z)| z).sum::<f64>() / n;
    let (mut sxx, mut sxy, mut syy, mut sxz, mut syz) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for (p, z) in probed {
        let (dx, dy, dz) = (p[0] - mx, p[1] - my, z - mz);
        sxx += dx * dx;
        sxy += dx * dy;
        syy += dy * dy;
        sxz += dx * dz;
        syz += dy * dz;
    }
    let det = sxx * syy - sxy * sxy;
    let scale = (sxx + syy).max(f64::MIN_POSITIVE);
    let (b, c) = if det.abs() > 1e-9 * scale * scale {
        ((sxz * syy - syz * sxy) / det, (syz * sxx - sxz * sxy) / det)
    } else if scale > 1e-12 {
        // Collinear: the covariance has rank 1, its larger row points along the line.
        let (ux, uy) = if sxx >= syy { (sxx, sxy) } else { (sxy, syy) };
        let norm = ux.hypot(uy);
        if norm <= 0.0 {
            return None;
        }
        let (ux, uy) = (ux / norm, uy / norm);
        let stt = probed
            .iter()
            .map(|(p, _)| ((p[0] - mx) * ux + (p[1] - my) * uy).powi(2))
            .sum::<f64>();
        let stz = probed
            .iter()
            .map(|(p, z)| ((p[0] - mx) * ux + (p[1] - my) * uy) * (z - mz))
            .sum::<f64>();
        let s = stz / stt;
        (s * ux, s * uy)
    } else {
        return None;
    };
    Some(move |x: f64, y: f64| mz + b * (x - mx) + c * (y - my))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tilted_plane_is_levelled() {
        let plane = |x: f64, y: f64| 1.0 + 0.002 * x - 0.001 * y;
        let pts: Vec<([f64; 2], f64)> = [[30.0, 20.0], [170.0, 20.0], [100.0, 180.0]]
            .iter()
            .map(|&p| (p, plane(p[0], p[1])))
            .collect();
        let motors = [[-50.0, 18.0], [100.0, 250.0], [250.0, 18.0]];
        let adj = motor_adjustments(&pts, &motors).unwrap();
        let at: Vec<f64> = motors.iter().map(|m| plane(m[0], m[1])).collect();
        let mean = at.iter().sum::<f64>() / 3.0;
        for (a, v) in adj.iter().zip(&at) {
            assert!((a - (v - mean)).abs() < 1e-9);
        }
    }

    #[test]
    fn collinear_points_fit_a_line() {
        // Two motors along X, points along X only.
        let pts = vec![([20.0, 100.0], 0.1), ([180.0, 100.0], 0.5)];
        let adj = motor_adjustments(&pts, &[[0.0, 100.0], [200.0, 100.0]]).unwrap();
        assert!(
            (adj[0] + 0.25).abs() < 1e-9 && (adj[1] - 0.25).abs() < 1e-9,
            "{adj:?}"
        );
        assert!(motor_adjustments(&pts[..1], &[[0.0, 0.0]]).is_none());
        assert!(motor_adjustments(&[([1.0, 1.0], 0.0), ([1.0, 1.0], 1.0)], &[[0.0, 0.0]]).is_none());
    }

    proptest::proptest! {
        /// For heights on any plane the corrections are that plane at the motors minus their
        /// mean (they sum to 0), and never NaN.
        #[test]
        fn plane_heights_give_exact_corrections(
            a in -1.0f64..1.0, b in -0.01f64..0.01, c in -0.01f64..0.01,
            pts in proptest::collection::vec((0.0f64..200.0, 0.0f64..200.0), 3..8),
        ) {
            let plane = |x: f64, y: f64| a + b * x + c * y;
            let probed: Vec<([f64; 2], f64)> = pts.iter().map(|&(x, y)| ([x, y], plane(x, y))).collect();
            let motors = [[0.0, 0.0], [200.0, 0.0], [100.0, 200.0]];
            if let Some(adj) = motor_adjustments(&probed, &motors) {
                proptest::prop_assert!(adj.iter().all(|v| v.is_finite()));
                proptest::prop_assert!(adj.iter().sum::<f64>().abs() < 1e-6);
            }
        }
    }
}

/// QUAD_GANTRY_LEVEL's corrections: the bilinear surface `a + b·x + c·y + d·x·y` through the
/// four probed points (a gantry hung from four corners bends that way), at each motor, minus
/// their mean; `None` when the points do not pin the surface down.
pub fn quad_adjustments(probed: &[([f64; 2], f64)], motors: &[[f64; 2]]) -> Option<Vec<f64>> {
    let [p0, p1, p2, p3] = probed else {
        return None;
    };
    let rows: Vec<[f64; 5]> = [p0, p1, p2, p3]
        .iter()
        .map(|(p, z)| [1.0, p[0], p[1], p[0] * p[1], *z])
        .collect();
    let k = solve4(rows)?;
    let at: Vec<f64> = motors
        .iter()
        .map(|m| k[0] + k[1] * m[0] + k[2] * m[1] + k[3] * m[0] * m[1])
        .collect();
    let mean = at.iter().sum::<f64>() / at.len().max(1) as f64;
    Some(at.iter().map(|v| v - mean).collect())
}

/// Solves 4 linear equations (augmented rows) by Gaussian elimination with partial pivoting.
fn solve4(mut m: Vec<[f64; 5]>) -> Option<[f64; 4]> {
    let scale = m
        .iter()
        .flat_map(|r| r[..4].iter())
        .fold(0.0f64, |a, v| a.max(v.abs()));
    for col in 0..4 {
        let pivot = (col..4).max_by(|&a, &b| m[a][col].abs().total_cmp(&m[b][col].abs()))?;
        if m[pivot][col].abs() <= 1e-12 * scale.max(1.0) {
            return None;
        }
        m.swap(col, pivot);
        let pivot_row = m[col];
        for (r, row) in m.iter_mut().enumerate() {
            if r != col {
                let f = row[col] / pivot_row[col];
                for (v, p) in row.iter_mut().zip(pivot_row).skip(col) {
                    *v -= f * p;
                }
            }
        }
    }
    Some([
        m[0][4] / m[0][0],
        m[1][4] / m[1][1],
        m[2][4] / m[2][2],
        m[3][4] / m[3][3],
    ])
}

#[cfg(test)]
mod quad_tests {
    use super::*;

    #[test]
    fn a_bent_gantry_is_levelled_at_its_corners() {
        let g = |x: f64, y: f64| 0.3 + 0.002 * x - 0.001 * y + 1e-5 * x * y;
        let probed: Vec<([f64; 2], f64)> = [[20.0, 20.0], [20.0, 180.0], [180.0, 180.0], [180.0, 20.0]]
            .iter()
            .map(|&p| (p, g(p[0], p[1])))
            .collect();
        let corners = [[0.0, 0.0], [0.0, 200.0], [200.0, 200.0], [200.0, 0.0]];
        let adj = quad_adjustments(&probed, &corners).unwrap();
        let at: Vec<f64> = corners.iter().map(|c| g(c[0], c[1])).collect();
        let mean = at.iter().sum::<f64>() / 4.0;
        for (a, v) in adj.iter().zip(&at) {
            assert!((a - (v - mean)).abs() < 1e-9, "{adj:?}");
        }
        let line: Vec<([f64; 2], f64)> = (0..4).map(|i| ([i as f64, 0.0], 0.0)).collect();
        assert!(quad_adjustments(&line, &corners).is_none(), "collinear points");
        assert!(quad_adjustments(&probed[..3], &corners).is_none());
    }
}
