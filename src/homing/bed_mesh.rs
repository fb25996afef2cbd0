//! `[bed_mesh]`'s G-code commands on a live print: `BED_MESH_CALIBRATE` (probes the grid with
//! the probe, builds the mesh and applies it), `BED_MESH_OUTPUT`, `BED_MESH_CLEAR` and
//! `BED_MESH_PROFILE LOAD|SAVE|REMOVE` (profiles kept for the session and written by
//! SAVE_CONFIG as `[bed_mesh NAME]`).
//!
//! Calibration, as Klipper's probe-points helper does it: Z to `horizontal_move_z` (the probe's
//! `lift_speed`), then for each point (serpentine rows, see [`planner::bed_mesh::points`]) the
//! nozzle to the point minus the probe's X/Y offsets at `speed`, one PROBE there (the probe's
//! samples and tolerance), back up to `horizontal_move_z`. The bed height at a point is the
//! trigger's Z minus the probe's `z_offset` (0 where the nozzle touches at Z = 0), shifted so
//! `zero_reference_position`'s height is 0 when that is set. The mesh's X, Y are the probe's:
//! the bed under the probe there. The default profile is not loaded at start (as current
//! Klipper): `BED_MESH_PROFILE LOAD=default` does it.
//!
//! Each probe's stop latency (the pass's executed/cancelled step bounds around the trigger)
//! is summarised in one line against the 25 ms multi-MCU budget.

use std::sync::{Arc, Mutex};

use planner::bed_mesh::points::ProbeGrid;
use planner::bed_mesh::split::{AppliedMesh, ApplySettings};
use planner::bed_mesh::{Algorithm, MeshParams, ZMesh};
use sysconfig::autosave::Changes;
use sysconfig::printer::{BedMeshSection, MeshShape, BED_MESH_ALGORITHMS};

use super::probe::{bad, lift, param, run_probe, ProbeParams};
use super::{plain_move, HomingCtx, HomingError, LevelingError, ParamProblem};

/// The G-code commands this module runs.
pub const COMMANDS: [&str; 4] = [
    "BED_MESH_CALIBRATE",
    "BED_MESH_OUTPUT",
    "BED_MESH_CLEAR",
    "BED_MESH_PROFILE",
];

/// The multi-MCU stop budget the latency summary is held against (µs).
const BUDGET_US: f64 = 25_000.0;

/// One saved mesh.
#[derive(Debug, Clone, PartialEq)]
pub struct Profile {
    pub name: String,
    pub mesh: ZMesh,
}

/// The session's meshes: profiles, the one in use, and what SAVE_CONFIG must write.
#[derive(Debug, Default)]
pub struct MeshState {
    pub profiles: Vec<Profile>,
    /// The mesh applied to moves and its profile name.
    pub active: Option<Profile>,
    /// Profile changes for SAVE_CONFIG.
    pub pending: Changes,
}

/// `[bed_mesh]` as the running printer holds it.
#[derive(Debug, Clone)]
pub struct BedMeshOut {
    pub cfg: BedMeshSection,
    pub state: Arc<Mutex<MeshState>>,
}

impl BedMeshOut {
    /// The section with its saved profiles loaded (a profile the config holds was checked when
    /// it was read).
    pub fn new(cfg: BedMeshSection) -> BedMeshOut {
        let profiles = cfg
            .profiles
            .iter()
            .filter_map(|p| {
                let mesh = ZMesh::new(p.params.clone(), p.points.clone()).ok()?;
                Some(Profile {
                    name: p.name.clone(),
                    mesh,
                })
            })
            .collect();
        BedMeshOut {
            cfg,
            state: Arc::new(Mutex::new(MeshState {
                profiles,
                ..MeshState::default()
            })),
        }
    }

    /// The fade and split settings.
    pub fn settings(&self) -> ApplySettings {
        let c = &self.cfg;
        ApplySettings {
            fade_start: c.fade_start,
            fade_end: c.fade_end,
            fade_target: c.fade_target,
            split_delta_z: c.split_delta_z,
            move_check_distance: c.move_check_distance,
        }
    }

    /// Klipper's `bed_mesh` status object now.
    pub fn status(&self) -> crate::events::BedMeshStatus {
        let Ok(s) = self.state.lock() else {
            return crate::events::BedMeshStatus::default();
        };
        let profiles = s.profiles.iter().map(|p| p.name.clone()).collect();
        match &s.active {
            None => crate::events::BedMeshStatus {
                profiles,
                ..Default::default()
            },
            Some(p) => crate::events::BedMeshStatus {
                profile_name: p.name.clone(),
                mesh_min: p.mesh.params().min,
                mesh_max: p.mesh.params().max,
                probed_matrix: p.mesh.probed().to_vec(),
                mesh_matrix: p.mesh.mesh_rows(),
                profiles,
            },
        }
    }

    /// The pending profile changes, taken (SAVE_CONFIG writes them).
    pub fn take_pending(&self) -> Changes {
        self.state
            .lock()
            .map(|mut s| std::mem::take(&mut s.pending))
            .unwrap_or_default()
    }
}

fn num(raw: &str, key: &str, v: &str) -> Result<f64, HomingError> {
    v.trim()
        .parse::<f64>()
        .ok()
        .filter(|x| x.is_finite())
        .ok_or_else(|| {
            let (value, key) = (v.to_string(), key.to_string());
            bad(raw, ParamProblem::Unparsable { value, key })
        })
}

fn pair(raw: &str, key: &str, v: &str) -> Result<[f64; 2], HomingError> {
    match v.split(',').collect::<Vec<_>>().as_slice() {
        [x, y] => Ok([num(raw, key, x)?, num(raw, key, y)?]),
        _ => {
            let (key, value) = (key.to_string(), v.to_string());
            Err(bad(raw, ParamProblem::NotPair { key, value }))
        }
    }
}

/// What one BED_MESH_CALIBRATE probes and how it interpolates.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrateParams {
    pub profile: String,
    pub horizontal_move_z: f64,
    pub grid: ProbeGrid,
    pub pps: [usize; 2],
    pub algorithm: Algorithm,
    pub tension: f64,
}

impl CalibrateParams {
    /// The config's settings overridden by the command's `PROFILE`, `HORIZONTAL_MOVE_Z`,
    /// `MESH_MIN`, `MESH_MAX`, `PROBE_COUNT`, `MESH_RADIUS`, `MESH_ORIGIN`,
    /// `ROUND_PROBE_COUNT`, `ALGORITHM`; `METHOD=manual` and `ADAPTIVE=1` are refused.
    pub fn parse(cfg: &BedMeshSection, raw: &str) -> Result<CalibrateParams, HomingError> {
        if param(raw, "METHOD").is_some_and(|m| !m.eq_ignore_ascii_case("automatic")) {
            return Err(bad(raw, ParamProblem::OnlyAutomatic));
        }
        if param(raw, "ADAPTIVE").is_some_and(|a| a.trim() != "0") {
            return Err(bad(raw, ParamProblem::Adaptive));
        }
        let grid = match &cfg.shape {
            MeshShape::Rectangular { min, max, count } => {
                let min = param(raw, "MESH_MIN").map_or(Ok(*min), |v| pair(raw, "MESH_MIN", &v))?;
                let max = param(raw, "MESH_MAX").map_or(Ok(*max), |v| pair(raw, "MESH_MAX", &v))?;
                let count = match param(raw, "PROBE_COUNT") {
                    None => *count,
                    Some(v) => {
                        let p = pair(raw, "PROBE_COUNT", &v)
                            .or_else(|_| num(raw, "PROBE_COUNT", &v).map(|n| [n, n]))?;
                        if p.iter().any(|&n| !(3.0..=99.0).contains(&n) || n.fract() != 0.0) {
                            return Err(bad(raw, ParamProblem::ProbeCount));
                        }
                        [p[0] as usize, p[1] as usize]
                    }
                };
                if max[0] <= min[0] || max[1] <= min[1] {
                    return Err(bad(raw, ParamProblem::MeshMaxBelowMin));
                }
                ProbeGrid {
                    min,
                    max,
                    count,
                    round: None,
                }
            }
            MeshShape::Round {
                origin,
                radius,
                count,
            } => {
                let origin =
                    param(raw, "MESH_ORIGIN").map_or(Ok(*origin), |v| pair(raw, "MESH_ORIGIN", &v))?;
                let radius =
                    param(raw, "MESH_RADIUS").map_or(Ok(*radius), |v| num(raw, "MESH_RADIUS", &v))?;
                let count = match param(raw, "ROUND_PROBE_COUNT") {
                    None => *count,
                    Some(v) => {
                        let n = num(raw, "ROUND_PROBE_COUNT", &v)?;
                        if !(3.0..=99.0).contains(&n) || n.fract() != 0.0 || n % 2.0 != 1.0 {
                            return Err(bad(raw, ParamProblem::RoundProbeCount));
                        }
                        n as usize
                    }
                };
                if radius <= 0.0 {
                    let key = "MESH_RADIUS".to_string();
                    return Err(bad(raw, ParamProblem::NotAbove { key, min: 0.0 }));
                }
                ProbeGrid::round(origin, radius, count)
            }
        };
        let algorithm = match param(raw, "ALGORITHM") {
            None => cfg.algorithm,
            Some(v) => BED_MESH_ALGORITHMS
                .iter()
                .find(|(n, _)| n.eq_ignore_ascii_case(&v))
                .map(|&(_, a)| a)
                .ok_or_else(|| bad(raw, ParamProblem::Algorithm { value: v.clone() }))?,
        };
        Ok(CalibrateParams {
            profile: param(raw, "PROFILE").unwrap_or_else(|| "default".to_string()),
            horizontal_move_z: param(raw, "HORIZONTAL_MOVE_Z")
                .map_or(Ok(cfg.horizontal_move_z), |v| num(raw, "HORIZONTAL_MOVE_Z", &v))?,
            grid,
            pps: cfg.pps,
            algorithm,
            tension: cfg.bicubic_tension,
        })
    }

    /// The mesh parameters of the probed grid.
    pub fn mesh_params(&self) -> MeshParams {
        MeshParams {
            min: self.grid.min,
            max: self.grid.max,
            count: self.grid.count,
            pps: self.pps,
            algorithm: self.algorithm,
            tension: self.tension,
        }
    }
}

/// Runs bed mesh command `name` written as `raw`; its output lines go to `out`.
pub fn run(ctx: &mut HomingCtx<'_>, name: &str, raw: &str, out: &mut Vec<String>) -> Result<(), HomingError> {
    let Some(bm) = ctx.machine.bed_mesh.clone() else {
        return Err(HomingError::NoSection {
            name: name.to_string(),
            section: "bed_mesh",
        });
    };
    match name {
        "BED_MESH_CALIBRATE" => calibrate(ctx, &bm, raw, out),
        "BED_MESH_CLEAR" => {
            set_active(ctx, &bm, None);
            Ok(())
        }
        "BED_MESH_OUTPUT" => {
            let state = bm.state.lock().map_err(|_| LevelingError::MeshStateLost)?;
            match &state.active {
                None => out.push("Bed has not been probed".to_string()),
                Some(p) => out.extend(output_lines(&p.mesh, bm.cfg.horizontal_move_z, ctx.machine)),
            }
            Ok(())
        }
        _ => profile_command(ctx, &bm, raw, out),
    }
}

/// Applies `profile`'s mesh to the moves (`None`: no mesh).
fn set_active(ctx: &mut HomingCtx<'_>, bm: &BedMeshOut, profile: Option<Profile>) {
    let applied = profile
        .as_ref()
        .map(|p| AppliedMesh::new(p.mesh.clone(), bm.settings()));
    ctx.pipeline.set_bed_mesh(applied);
    if let Ok(mut s) = bm.state.lock() {
        s.active = profile;
    }
}

/// Keeps `mesh` as profile `name` for the session and for SAVE_CONFIG.
fn save_profile(state: &mut MeshState, name: &str, mesh: &ZMesh) {
    state.profiles.retain(|p| p.name != name);
    state.profiles.push(Profile {
        name: name.to_string(),
        mesh: mesh.clone(),
    });
    let section = format!("bed_mesh {name}");
    for (k, v) in sysconfig::printer::bed_mesh_profile_options(mesh.params(), mesh.probed()) {
        state.pending.set(&section, &k, v);
    }
}

/// `BED_MESH_PROFILE LOAD=|SAVE=|REMOVE=`.
fn profile_command(
    ctx: &mut HomingCtx<'_>,
    bm: &BedMeshOut,
    raw: &str,
    out: &mut Vec<String>,
) -> Result<(), HomingError> {
    let lost = |_| LevelingError::MeshStateLost;
    if let Some(name) = param(raw, "LOAD") {
        let found = bm
            .state
            .lock()
            .map_err(lost)?
            .profiles
            .iter()
            .find(|p| p.name == name)
            .cloned();
        let p = found.ok_or(LevelingError::UnknownProfile { name })?;
        set_active(ctx, bm, Some(p));
        return Ok(());
    }
    if let Some(name) = param(raw, "SAVE") {
        let mut s = bm.state.lock().map_err(lost)?;
        let Some(active) = s.active.clone() else {
            return Err(LevelingError::NotProbed.into());
        };
        save_profile(&mut s, &name, &active.mesh);
        s.active = Some(Profile {
            name: name.to_string(),
            mesh: active.mesh,
        });
        out.extend(saved_message(&name));
        return Ok(());
    }
    if let Some(name) = param(raw, "REMOVE") {
        let mut s = bm.state.lock().map_err(lost)?;
        if !s.profiles.iter().any(|p| p.name == name) {
            return Err(LevelingError::UnknownProfile { name }.into());
        }
        s.profiles.retain(|p| p.name != name);
        s.pending.remove_section(&format!("bed_mesh {name}"));
        out.push(format!("Profile [{name}] removed from storage for this session."));
        out.push(
            "The SAVE_CONFIG command will update the printer configuration and restart the printer"
                .to_string(),
        );
        return Ok(());
    }
    Err(bad(raw, ParamProblem::ProfileAction))
}

/// Klipper's answer to a profile saved for the session (its two lines).
fn saved_message(name: &str) -> [String; 2] {
    [
        format!("Bed Mesh state has been saved to profile [{name}] for the current session."),
        "The SAVE_CONFIG command will update the printer config file and restart the printer.".to_string(),
    ]
}

/// BED_MESH_CALIBRATE.
fn calibrate(
    ctx: &mut HomingCtx<'_>,
    bm: &BedMeshOut,
    raw: &str,
    out: &mut Vec<String>,
) -> Result<(), HomingError> {
    let Some(probe) = ctx.machine.probe.clone() else {
        return Err(LevelingError::NeedsProbe {
            name: "BED_MESH_CALIBRATE".to_string(),
        }
        .into());
    };
    let cp = CalibrateParams::parse(&bm.cfg, raw)?;
    let pp = ProbeParams::parse(&probe.cfg, raw, probe.cfg.samples)?;
    if !ctx.pipeline.gcode_state().homed().iter().all(|&h| h) {
        return Err(LevelingError::NotHomed.into());
    }
    set_active(ctx, bm, None);
    let points = cp.grid.points();
    let offsets = [probe.cfg.x_offset, probe.cfg.y_offset];
    let first_pass = ctx.probe_passes.len();
    let heights = super::bltouch::session(ctx, |ctx| {
        lift(ctx, cp.horizontal_move_z, probe.cfg.lift_speed)?;
        let mut heights = Vec::with_capacity(points.len());
        for p in &points {
            let mut pos = ctx.pipeline.position();
            pos[0] = p.xy[0] - offsets[0];
            pos[1] = p.xy[1] - offsets[1];
            pos[2] = cp.horizontal_move_z;
            plain_move(ctx, pos, bm.cfg.speed)?;
            let z = run_probe(ctx, &probe, &pp, out)?;
            heights.push(z - probe.cfg.z_offset);
            lift(ctx, cp.horizontal_move_z, probe.cfg.lift_speed)?;
        }
        Ok(heights)
    })?;
    let mut matrix = cp.grid.matrix(&heights).ok_or(LevelingError::EmptyRow)?;
    let mut mesh = ZMesh::new(cp.mesh_params(), matrix.clone()).map_err(LevelingError::from)?;
    if let Some([x, y]) = bm.cfg.zero_reference_position {
        let z0 = mesh.calc_z(x, y);
        matrix.iter_mut().flatten().for_each(|v| *v -= z0);
        mesh = ZMesh::new(cp.mesh_params(), matrix).map_err(LevelingError::from)?;
    }
    out.push(latency_line(
        "bed_mesh",
        &ctx.probe_passes[first_pass.min(ctx.probe_passes.len())..],
    ));
    out.push("Mesh Bed Leveling Complete".to_string());
    {
        let mut s = bm.state.lock().map_err(|_| LevelingError::MeshStateLost)?;
        save_profile(&mut s, &cp.profile, &mesh);
    }
    out.extend(saved_message(&cp.profile));
    set_active(
        ctx,
        bm,
        Some(Profile {
            name: cp.profile,
            mesh,
        }),
    );
    Ok(())
}

/// `WHO: N probe passes, stop at most A..B us after trigger (budget 25000 us)`: the largest
/// lower and upper bounds of the passes' stop latency.
pub(crate) fn latency_line(who: &str, passes: &[super::PassReport]) -> String {
    if passes.is_empty() {
        return format!("{who}: no probe passes");
    }
    let lo = passes
        .iter()
        .map(|p| p.last_step_after_s)
        .fold(f64::NEG_INFINITY, f64::max);
    let hi = passes
        .iter()
        .map(|p| p.next_step_after_s)
        .fold(f64::NEG_INFINITY, f64::max);
    format!(
        "{who}: {} probe passes, stop at most {:.0}..{:.0} us after trigger (budget {BUDGET_US:.0} us)",
        passes.len(),
        lo * 1e6,
        hi * 1e6
    )
}

/// BED_MESH_OUTPUT's report.
fn output_lines(mesh: &ZMesh, search_height: f64, machine: &crate::hardware::Machine) -> Vec<String> {
    let p = mesh.params();
    let (min, max) = mesh.range();
    let (xo, yo) = machine
        .probe
        .as_ref()
        .map_or((0.0, 0.0), |p| (p.cfg.x_offset, p.cfg.y_offset));
    let mut lines = vec![
        format!("Mesh X,Y: {},{}", p.count[0], p.count[1]),
        format!("Search Height: {search_height}"),
        format!("Mesh Offsets: X={xo:.4}, Y={yo:.4}"),
        format!("Mesh Average: {:.2}", mesh.average()),
        format!("Mesh Range: min={min:.4} max={max:.4}"),
        format!("Interpolation Algorithm: {}", p.effective_algorithm().name()),
        "Measured points:".to_string(),
    ];
    for row in mesh.probed().iter().rev() {
        lines.push(format!(
            "  {}",
            row.iter()
                .map(|v| format!("{v:.6}"))
                .collect::<Vec<_>>()
                .join(" ")
        ));
    }
    lines
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg(shape: MeshShape) -> BedMeshSection {
        BedMeshSection {
            shape,
            speed: 50.0,
            horizontal_move_z: 5.0,
            pps: [2, 2],
            algorithm: Algorithm::Lagrange,
            bicubic_tension: 0.2,
            fade_start: 1.0,
            fade_end: 0.0,
            fade_target: None,
            split_delta_z: 0.025,
            move_check_distance: 5.0,
            zero_reference_position: None,
            profiles: Vec::new(),
        }
    }

    fn rect() -> BedMeshSection {
        cfg(MeshShape::Rectangular {
            min: [10.0, 10.0],
            max: [190.0, 190.0],
            count: [3, 3],
        })
    }

    #[test]
    fn calibrate_parameters_override_the_config() {
        let p = CalibrateParams::parse(&rect(), "BED_MESH_CALIBRATE").unwrap();
        assert_eq!(
            (p.profile.as_str(), p.horizontal_move_z, p.grid.count),
            ("default", 5.0, [3, 3])
        );
        let p = CalibrateParams::parse(
            &rect(),
            "BED_MESH_CALIBRATE PROFILE=pla MESH_MIN=20,30 MESH_MAX=100,110 PROBE_COUNT=5,4 ALGORITHM=bicubic horizontal_move_z=2",
        )
        .unwrap();
        assert_eq!(
            (p.grid.min, p.grid.max, p.grid.count),
            ([20.0, 30.0], [100.0, 110.0], [5, 4])
        );
        assert_eq!(
            (p.profile.as_str(), p.algorithm, p.horizontal_move_z),
            ("pla", Algorithm::Bicubic, 2.0)
        );
        let p = CalibrateParams::parse(&rect(), "BED_MESH_CALIBRATE PROBE_COUNT=4").unwrap();
        assert_eq!(p.grid.count, [4, 4]);
        let round = cfg(MeshShape::Round {
            origin: [0.0, 0.0],
            radius: 50.0,
            count: 5,
        });
        let p =
            CalibrateParams::parse(&round, "BED_MESH_CALIBRATE MESH_RADIUS=40 ROUND_PROBE_COUNT=7").unwrap();
        assert_eq!((p.grid.min, p.grid.count), ([-40.0, -40.0], [7, 7]));
        assert!(p.grid.round.is_some());
    }

    #[test]
    fn bad_calibrate_parameters_are_named() {
        let e = |raw: &str| CalibrateParams::parse(&rect(), raw).unwrap_err().to_string();
        assert_eq!(
            e("BED_MESH_CALIBRATE METHOD=manual"),
            "Error on 'BED_MESH_CALIBRATE METHOD=manual': only METHOD=automatic (the probe) is supported"
        );
        assert!(e("BED_MESH_CALIBRATE ADAPTIVE=1").contains("ADAPTIVE meshes are not supported"));
        assert!(e("BED_MESH_CALIBRATE PROBE_COUNT=2").contains("PROBE_COUNT must be"));
        assert!(e("BED_MESH_CALIBRATE MESH_MIN=1").contains("MESH_MIN must be 'X,Y'"));
        assert!(e("BED_MESH_CALIBRATE MESH_MIN=200,0").contains("MESH_MAX must be above MESH_MIN"));
        assert!(e("BED_MESH_CALIBRATE ALGORITHM=x").contains("ALGORITHM must be"));
        let round = cfg(MeshShape::Round {
            origin: [0.0, 0.0],
            radius: 50.0,
            count: 5,
        });
        assert!(
            CalibrateParams::parse(&round, "BED_MESH_CALIBRATE ROUND_PROBE_COUNT=4")
                .unwrap_err()
                .to_string()
                .contains("must be odd")
        );
    }

    #[test]
    fn profiles_are_kept_for_save_config() {
        let params = MeshParams {
            min: [0.0, 0.0],
            max: [10.0, 10.0],
            count: [3, 3],
            pps: [2, 2],
            algorithm: Algorithm::Lagrange,
            tension: 0.2,
        };
        let mesh = ZMesh::new(params, vec![vec![0.0, 0.1, 0.2]; 3]).unwrap();
        let mut s = MeshState::default();
        save_profile(&mut s, "default", &mesh);
        save_profile(&mut s, "default", &mesh);
        assert_eq!(s.profiles.len(), 1);
        let items = s.pending.items();
        assert_eq!(items.len(), 1);
        assert_eq!(items[0].0, "bed_mesh default");
    }

    #[test]
    fn latency_summary() {
        assert_eq!(latency_line("bed_mesh", &[]), "bed_mesh: no probe passes");
    }
}
