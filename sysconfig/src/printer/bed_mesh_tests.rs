//! Tests of `[bed_mesh]` and its profiles.

use std::path::Path;

use planner::bed_mesh::Algorithm;
use proptest::prelude::*;

use super::MeshShape;
use crate::printer::{parse_str, PrinterConfig};

/// A cartesian printer whose Z homes on a `[probe]` on the main MCU (other sections' tests
/// append theirs).
pub(crate) const BASE: &str = "[mcu]\nserial: /dev/ttyACM0\n\
    [printer]\nkinematics: cartesian\nmax_velocity: 300\nmax_accel: 3000\n\
    [stepper_x]\nstep_pin: PA0\ndir_pin: PA1\nmicrosteps: 16\nrotation_distance: 40\nposition_max: 200\nendstop_pin: PA3\nposition_endstop: 0\n\
    [stepper_y]\nstep_pin: PB0\ndir_pin: PB1\nmicrosteps: 16\nrotation_distance: 40\nposition_max: 200\nendstop_pin: PB3\nposition_endstop: 0\n\
    [stepper_z]\nstep_pin: PC0\ndir_pin: PC1\nmicrosteps: 16\nrotation_distance: 8\nposition_max: 200\nendstop_pin: probe:z_virtual_endstop\n\
    [probe]\npin: ^PA4\nz_offset: 1.5\n";

fn parse(text: &str) -> Result<PrinterConfig, String> {
    parse_str(text, Path::new("printer.cfg")).map_err(|e| e.to_string())
}

fn mesh(body: &str) -> Result<super::BedMeshSection, String> {
    parse(&format!("{BASE}[bed_mesh]\n{body}")).map(|c| c.bed_mesh.unwrap_or_else(|| panic!("no mesh")))
}

#[test]
fn rectangular_defaults_and_options() {
    let m = mesh("mesh_min: 10, 10\nmesh_max: 190, 180\n").unwrap();
    assert_eq!(
        m.shape,
        MeshShape::Rectangular {
            min: [10.0, 10.0],
            max: [190.0, 180.0],
            count: [3, 3]
        }
    );
    assert_eq!((m.speed, m.horizontal_move_z, m.pps), (50.0, 5.0, [2, 2]));
    assert_eq!((m.algorithm, m.bicubic_tension), (Algorithm::Lagrange, 0.2));
    assert_eq!((m.fade_start, m.fade_end, m.fade_target), (1.0, 0.0, None));
    assert_eq!((m.split_delta_z, m.move_check_distance), (0.025, 5.0));
    let m = mesh(
        "mesh_min: 10, 10\nmesh_max: 190, 180\nprobe_count: 7, 5\nalgorithm: bicubic\nbicubic_tension: 0.3\n\
         mesh_pps: 3, 1\nfade_start: 1\nfade_end: 10\nfade_target: 0\nsplit_delta_z: 0.01\nmove_check_distance: 3\n\
         speed: 100\nhorizontal_move_z: 3\nzero_reference_position: 100, 100\n",
    )
    .unwrap();
    assert!(matches!(m.shape, MeshShape::Rectangular { count: [7, 5], .. }));
    assert_eq!(
        (m.algorithm, m.pps, m.fade_end, m.fade_target),
        (Algorithm::Bicubic, [3, 1], 10.0, Some(0.0))
    );
    assert_eq!(m.zero_reference_position, Some([100.0, 100.0]));
}

#[test]
fn round_beds() {
    let m = mesh("mesh_radius: 75\nmesh_origin: 0, 5\nround_probe_count: 7\nalgorithm: bicubic\n").unwrap();
    assert_eq!(
        m.shape,
        MeshShape::Round {
            origin: [0.0, 5.0],
            radius: 75.0,
            count: 7
        }
    );
}

#[test]
fn bad_options_are_named() {
    let cases = [
        ("mesh_min: 10, 10\n", "printer.cfg:33: Option 'mesh_max' in section 'bed_mesh' must be specified"),
        ("mesh_min: 10\nmesh_max: 20, 20\n", "printer.cfg:34: [bed_mesh] mesh_min: must be two numbers 'X, Y', got '10'"),
        ("mesh_min: 10, 10\nmesh_max: 5, 20\n", "printer.cfg:35: [bed_mesh] mesh_max: must be above mesh_min on both axes: mesh_min 10, 10, mesh_max 5, 20"),
        ("mesh_min: 0, 0\nmesh_max: 9, 9\nprobe_count: 2\n", "printer.cfg:36: [bed_mesh] probe_count: must have minimum of 3, got 2"),
        ("mesh_min: 0, 0\nmesh_max: 9, 9\nprobe_count: 7, 3\n", "printer.cfg:21: [bed_mesh] needs no: unused"),
        ("mesh_radius: 50\nround_probe_count: 4\n", "printer.cfg:35: [bed_mesh] round_probe_count: must be odd, got 4"),
        ("mesh_min: 0, 0\nmesh_max: 9, 9\nfade_end: 0.5\n", "printer.cfg:36: [bed_mesh] fade_end: must be above fade_start (1), got 0.5"),
        ("mesh_min: 0, 0\nmesh_max: 9, 9\nalgorithm: spline\n", "printer.cfg:36: [bed_mesh] algorithm: expected one of lagrange, bicubic, got 'spline'"),
        ("mesh_min: 0, 0\nmesh_max: 9, 9\nfaulty_region_1_min: 1, 1\n", "printer.cfg:36: [bed_mesh] faulty_region_1_min: faulty regions are not supported by Cadence yet"),
        ("mesh_min: 0, 0\nmesh_max: 9, 9\nmove_check_distance: 1\n", "printer.cfg:36: [bed_mesh] move_check_distance: must have minimum of 3, got 1"),
    ];
    for (body, want) in cases {
        let got = mesh(body).map(|_| ()).unwrap_err();
        if want.ends_with("needs no: unused") {
            assert!(got.contains("probe_count of at most 6"), "{got}");
        } else {
            assert_eq!(got, want, "{body}");
        }
    }
    let no_probe = BASE
        .replace("[probe]\npin: ^PA4\nz_offset: 1.5\n", "")
        .replace("probe:z_virtual_endstop", "PC3\nposition_endstop: 0");
    let e = parse(&format!("{no_probe}[bed_mesh]\nmesh_min: 0, 0\nmesh_max: 9, 9\n"))
        .map(|_| ())
        .unwrap_err();
    assert!(e.contains("[bed_mesh]") && e.contains("needs a probe"), "{e}");
}

#[test]
fn bicubic_with_few_points_warns_and_uses_lagrange() {
    let c = parse(&format!(
        "{BASE}[bed_mesh]\nmesh_min: 0, 0\nmesh_max: 9, 9\nalgorithm: bicubic\n"
    ))
    .unwrap();
    assert_eq!(c.bed_mesh.map(|m| m.algorithm), Some(Algorithm::Lagrange));
    assert!(
        c.warnings
            .iter()
            .any(|w| w.contains("bicubic interpolation needs")),
        "{:?}",
        c.warnings
    );
}

#[test]
fn saved_profiles_are_read_back() {
    let params = planner::bed_mesh::MeshParams {
        min: [10.0, 20.0],
        max: [100.0, 110.0],
        count: [3, 2],
        pps: [2, 0],
        algorithm: Algorithm::Lagrange,
        tension: 0.2,
    };
    let points = vec![vec![0.1, -0.05, 0.0125], vec![0.0, 0.2, -0.3]];
    let opts = super::profile_options(&params, &points);
    let mut changes = crate::autosave::Changes::default();
    for (k, v) in &opts {
        changes.set("bed_mesh default", k, v);
    }
    let text = format!("{BASE}[bed_mesh]\nmesh_min: 0, 0\nmesh_max: 9, 9\n");
    let saved = crate::autosave::render(&text, Path::new("printer.cfg"), &changes, &mut |_| {
        Ok(String::new())
    })
    .unwrap()
    .unwrap();
    assert!(
        saved.contains(
            "#*# [bed_mesh default]\n#*# version = 1\n#*# points =\n#*# \t0.100000, -0.050000, 0.012500\n"
        ),
        "{saved}"
    );
    let c = parse(&saved).unwrap();
    let p = &c.bed_mesh.unwrap().profiles[0];
    assert_eq!(
        (p.name.as_str(), &p.params, &p.points),
        ("default", &params, &points)
    );
    let bad = saved.replace("#*# x_count = 3", "#*# x_count = 4");
    assert!(parse(&bad)
        .unwrap_err()
        .contains("probed matrix is 2x3, expected 2x4"));
}

proptest! {
    /// Any text in `[bed_mesh]` options is an error or a mesh, never a panic.
    #[test]
    fn options_never_panic(a in "[-0-9., a-z]{0,12}", b in "[-0-9., ]{0,12}") {
        let _ = mesh(&format!("mesh_min: {a}\nmesh_max: {b}\nprobe_count: {a}\nmesh_pps: {b}\n"));
        let _ = mesh(&format!("mesh_radius: {b}\nmesh_origin: {a}\nround_probe_count: {b}\n"));
    }
}
