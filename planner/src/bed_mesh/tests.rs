//! Tests of the mesh interpolation.

use super::*;
use proptest::prelude::*;

fn params(count: [usize; 2], pps: [usize; 2], algorithm: Algorithm) -> MeshParams {
    MeshParams {
        min: [10.0, 20.0],
        max: [110.0, 70.0],
        count,
        pps,
        algorithm,
        tension: 0.2,
    }
}

fn grid(count: [usize; 2], f: impl Fn(usize, usize) -> f64) -> Vec<Vec<f64>> {
    (0..count[1])
        .map(|r| (0..count[0]).map(|c| f(c, r)).collect())
        .collect()
}

#[test]
fn the_upsampled_mesh_has_pps_points_between_probed_ones() {
    let m = ZMesh::new(
        params([3, 4], [2, 3], Algorithm::Lagrange),
        grid([3, 4], |_, _| 0.0),
    )
    .unwrap();
    assert_eq!(m.mesh_count(), [7, 13]);
    assert_eq!(m.mesh_rows().len(), 13);
}

#[test]
fn a_plane_is_reproduced_everywhere() {
    let plane = |x: f64, y: f64| 0.3 + 0.004 * x - 0.002 * y;
    for algorithm in [Algorithm::Lagrange, Algorithm::Bicubic] {
        let count = [5, 4];
        let p = params(count, [2, 2], algorithm);
        let probe = ZMesh::new(p.clone(), grid(count, |_, _| 0.0)).unwrap();
        let probed = grid(count, |c, r| {
            let [x, y] = probe.probed_point(c, r);
            plane(x, y)
        });
        let m = ZMesh::new(p, probed).unwrap();
        for (x, y) in [(10.0, 20.0), (33.3, 41.7), (60.0, 45.0), (110.0, 70.0)] {
            let z = m.calc_z(x, y);
            // Lagrange is exact; the bicubic spline's clamped ends bend a plane slightly.
            let tol = if algorithm == Algorithm::Lagrange {
                1e-9
            } else {
                0.05
            };
            assert!((z - plane(x, y)).abs() < tol, "{algorithm:?} at {x},{y}: {z}");
        }
    }
}

#[test]
fn outside_the_mesh_the_nearest_edge_counts() {
    let count = [3, 3];
    let m = ZMesh::new(
        params(count, [0, 0], Algorithm::Lagrange),
        grid(count, |c, r| (c + 10 * r) as f64),
    )
    .unwrap();
    assert_eq!(m.calc_z(-100.0, -100.0), 0.0);
    assert_eq!(m.calc_z(1000.0, 1000.0), 22.0);
    assert_eq!(m.calc_z(60.0, -5.0), 1.0);
    assert_eq!(m.calc_z(f64::NAN, 45.0), 10.0);
}

#[test]
fn bad_meshes_are_refused() {
    let e = |p: MeshParams, g: Vec<Vec<f64>>| ZMesh::new(p, g).unwrap_err().to_string();
    assert_eq!(
        e(
            params([1, 3], [0, 0], Algorithm::Lagrange),
            grid([1, 3], |_, _| 0.0)
        ),
        "bed_mesh: probe count must be at least 2 per axis, got 1x3"
    );
    assert_eq!(
        e(
            params([3, 3], [0, 0], Algorithm::Lagrange),
            grid([3, 2], |_, _| 0.0)
        ),
        "bed_mesh: probed matrix is 2x3, expected 3x3"
    );
    assert_eq!(
        e(
            params([7, 7], [2, 2], Algorithm::Lagrange),
            grid([7, 7], |_, _| 0.0)
        ),
        "bed_mesh: lagrange interpolation supports at most 6 points per axis, got 7"
    );
    let mut p = params([3, 3], [0, 0], Algorithm::Lagrange);
    p.max = [0.0, 70.0];
    assert!(e(p, grid([3, 3], |_, _| 0.0)).contains("must be above mesh_min"));
    assert!(e(
        params([3, 3], [0, 0], Algorithm::Lagrange),
        grid([3, 3], |_, _| f64::NAN)
    )
    .contains("not a finite"));
    // Bicubic with too few points falls back to lagrange, as Klipper does.
    assert_eq!(
        params([3, 5], [2, 2], Algorithm::Bicubic).effective_algorithm(),
        Algorithm::Lagrange
    );
}

fn arb_mesh() -> impl Strategy<Value = (MeshParams, Vec<Vec<f64>>)> {
    (
        2usize..=6,
        2usize..=6,
        0usize..=4,
        0usize..=4,
        prop_oneof![Just(Algorithm::Lagrange), Just(Algorithm::Bicubic)],
        0.0f64..=2.0,
    )
        .prop_flat_map(|(cx, cy, px, py, algorithm, tension)| {
            let p = MeshParams {
                tension,
                ..params([cx, cy], [px, py], algorithm)
            };
            (
                Just(p),
                proptest::collection::vec(proptest::collection::vec(-1.0f64..1.0, cx), cy),
            )
        })
}

proptest! {
    /// At every probed point the mesh is the probed height (both algorithms, any pps).
    #[test]
    fn probed_points_are_kept((p, probed) in arb_mesh()) {
        let m = ZMesh::new(p.clone(), probed.clone()).map_err(|e| TestCaseError::fail(e.to_string()))?;
        for (r, row) in probed.iter().enumerate() {
            for (c, &z) in row.iter().enumerate() {
                let [x, y] = m.probed_point(c, r);
                prop_assert!((m.calc_z(x, y) - z).abs() < 1e-9, "({c},{r}): {} vs {z}", m.calc_z(x, y));
            }
        }
    }

    /// Any X, Y (also far outside, or not finite) gives a finite height; inside one upsampled
    /// cell the height lies between that cell's corner values.
    #[test]
    fn heights_are_finite_and_bilinear_within_cells(
        (p, probed) in arb_mesh(),
        x in -1e6f64..1e6, y in -1e6f64..1e6,
        fx in 0.0f64..1.0, fy in 0.0f64..1.0,
    ) {
        let m = ZMesh::new(p.clone(), probed).map_err(|e| TestCaseError::fail(e.to_string()))?;
        prop_assert!(m.calc_z(x, y).is_finite());
        prop_assert!(m.calc_z(f64::INFINITY, f64::NEG_INFINITY).is_finite());
        let rows = m.mesh_rows();
        let [nx, ny] = m.mesh_count();
        let (cx, cy) = (((nx - 1) as f64 * fx) as usize, ((ny - 1) as f64 * fy) as usize);
        let (cx, cy) = (cx.min(nx - 2), cy.min(ny - 2));
        let step = [(p.max[0] - p.min[0]) / (nx - 1) as f64, (p.max[1] - p.min[1]) / (ny - 1) as f64];
        let (qx, qy) = (p.min[0] + (cx as f64 + 0.5) * step[0], p.min[1] + (cy as f64 + 0.5) * step[1]);
        let corners = [rows[cy][cx], rows[cy][cx + 1], rows[cy + 1][cx], rows[cy + 1][cx + 1]];
        let z = m.calc_z(qx, qy);
        let lo = corners.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = corners.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        prop_assert!(z >= lo - 1e-9 && z <= hi + 1e-9);
        prop_assert!((z - corners.iter().sum::<f64>() / 4.0).abs() < 1e-9, "cell centre is the corners' mean");
    }
}
