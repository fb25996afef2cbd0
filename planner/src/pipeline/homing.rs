//! Homing support for the host's homing sequence (docs/protocol.md "Homing").
//!
//! A homing move is an ordinary final move whose steps are all generated and released at once
//! ([`Pipeline::home_move`] then [`Pipeline::generate`] with the toolhead at rest). The MCU
//! stops the axis steppers part-way through when the endstop's trsync fires; then
//! [`Pipeline::resync_after_stop`] makes the planner agree with what really happened:
//! - the toolhead's next move starts at a print time the caller picks (≥ now + lead), not at the
//!   end of the move that was cut short, from the position the caller computed;
//! - each stopped stepper's net step count becomes the MCU's reported position, its next step
//!   is preceded by `reset_step_clock` and `set_next_step_dir`, and its step generation is
//!   re-anchored at the new commanded position (steps never compressed are dropped; nothing
//!   already emitted is taken back);
//! - the compression horizon and `planned_until` go back to that print time, so the global
//!   clock order of released commands still holds.
//!
//! With input shaping the homing move is shaped too (as on Klipper); after a stop every shaped
//! generator starts afresh at the next move, which starts the shaper's span after the given
//! print time so that its shaped steps do not come before it. Only the inline backend without
//! pressure advance supports this (worker lanes and the pressure-advance generator keep time
//! state this module cannot rewind):
//! [`Pipeline::supports_homing`].

use super::{Backend, Pipeline};
use crate::gcode::{Command, GcodeLine};
use crate::machine::{PlanError, PlanErrorKind};
use crate::toolhead::Move;

fn config_error(msg: &str) -> PlanError {
    PlanError {
        line: 0,
        kind: PlanErrorKind::Config(msg.to_string()),
    }
}

impl Pipeline {
    /// True when [`Self::resync_after_stop`] can work (inline lanes, no pressure advance).
    pub fn supports_homing(&self) -> bool {
        match &self.backend {
            Backend::Inline(lanes, _) => lanes.iter().all(|l| l.pa.is_none()),
            Backend::Threads(..) => false,
        }
    }

    /// Print time at which the next move would start.
    pub fn toolhead_print_time(&self) -> f64 {
        self.th.print_time()
    }

    /// Makes the next move start no earlier than `print_time` (the toolhead must not schedule
    /// moves in the past after waiting). Flushes the lookahead.
    pub fn raise_print_time(&mut self, print_time: f64) -> Result<(), PlanError> {
        self.th.flush();
        let wait = print_time - self.th.print_time();
        if wait > 0.0 {
            self.th.dwell(wait).map_err(|e| PlanError {
                line: 0,
                kind: PlanErrorKind::Move(e),
            })?;
        }
        Ok(())
    }

    /// The acceleration limit of the moves planned from now on (mm/s²).
    pub fn max_accel(&self) -> f64 {
        self.th.config().max_accel
    }

    /// Sets the acceleration limit of the moves planned from now on, as `M204 S` does.
    pub fn set_max_accel(&mut self, accel: f64) -> Result<(), PlanError> {
        self.th
            .set_limits(None, Some(accel), None, None)
            .map_err(|e| config_error(&e.to_string()))
    }

    /// Redefines the toolhead position (X, Y, Z, E) without moving, as G-code sees it too
    /// (G92 offsets are kept). Flushes the lookahead.
    pub fn set_toolhead_position(&mut self, pos: [f64; 4]) {
        self.th.set_position(pos);
        self.sync_gcode_position();
    }

    /// Applies `mesh` to the G-code moves from now on (`None`: none): `BED_MESH_PROFILE LOAD`,
    /// `BED_MESH_CLEAR`, the end of `BED_MESH_CALIBRATE`.
    pub fn set_bed_mesh(&mut self, mesh: Option<crate::bed_mesh::split::AppliedMesh>) {
        self.state.set_bed_mesh(mesh, &self.th);
    }

    /// The G-code state's last position follows the toolhead: `G28` naming no axis at the
    /// state level (the parser never produces it) redefines nothing and re-reads the position.
    fn sync_gcode_position(&mut self) {
        let line = GcodeLine {
            line_no: 0,
            cmd: Command::Home {
                x: false,
                y: false,
                z: false,
            },
        };
        // Cannot fail: no motion, no parameter.
        let _ = self.state.apply(&line, &mut self.th);
    }

    /// Queues a straight move to `target` at `speed` mm/s that comes to rest at its end, and
    /// makes it final: the next [`Self::generate`] releases all its steps. Returns the move
    /// (`None` for a zero-length move). The caller sets the start time first
    /// ([`Self::raise_print_time`]).
    pub fn home_move(&mut self, target: [f64; 4], speed: f64) -> Result<Option<Move>, PlanError> {
        self.th.flush();
        let before = self.th.moves_total();
        self.th.move_to(target, speed).map_err(|e| PlanError {
            line: 0,
            kind: PlanErrorKind::Move(e),
        })?;
        self.th.flush();
        let start = self.moves.len();
        self.th.take_moves(&mut self.moves);
        self.sync_gcode_position();
        if self.th.moves_total() == before {
            return Ok(None);
        }
        Ok(self.moves[start..].last().copied())
    }

    /// Keeps the steppers of lanes `idx` still through the following moves (Z motors left out
    /// of one Z_TILT_ADJUST correction): each follows the extruder axis instead, which the
    /// caller's Z moves leave alone, from its step position now. [`Self::thaw_lanes`] gives
    /// the kinematics back; the caller then resyncs every lane whose stepper moved apart from
    /// the toolhead ([`Self::resync_after_stop`]). Needs the inline lanes, at rest.
    pub fn freeze_lanes(&mut self, idx: &[usize]) -> Result<(), PlanError> {
        if !self.supports_homing() {
            return Err(config_error("moving single steppers needs the inline planner"));
        }
        self.th.flush();
        let e = self.th.position()[3];
        if let Backend::Inline(lanes, _) = &mut self.backend {
            for &i in idx {
                let (Some(lane), Some(view)) = (lanes.get_mut(i), self.views.get(i)) else {
                    return Err(config_error("freeze: unknown stepper index"));
                };
                let kin = crate::kinematics::StepperKin::axis(3, lane.kin.step_dist);
                self.frozen.push((i, std::mem::replace(&mut lane.kin, kin)));
                lane.comp.resync(view.position, e, lane.clock.freq);
            }
        }
        Ok(())
    }

    /// Gives the lanes [`Self::freeze_lanes`] kept still their kinematics back.
    pub fn thaw_lanes(&mut self) {
        if let Backend::Inline(lanes, _) = &mut self.backend {
            for (i, kin) in self.frozen.drain(..) {
                if let Some(lane) = lanes.get_mut(i) {
                    lane.kin = kin;
                }
            }
        }
    }

    /// Net steps emitted so far by stepper `idx`.
    pub fn stepper_position(&self, idx: usize) -> Option<i64> {
        self.views.get(idx).map(|v| v.position)
    }

    /// After the MCUs stopped some steppers part-way through the last move: the next move
    /// starts at `print_time` from toolhead position `pos`; `stopped` lists (stepper index,
    /// the MCU's net step position) of every stepper the MCUs stopped. Call after the move's
    /// commands were all released by [`Self::generate`].
    pub fn resync_after_stop(
        &mut self,
        print_time: f64,
        pos: [f64; 4],
        stopped: &[(usize, i64)],
    ) -> Result<(), PlanError> {
        if !self.supports_homing() {
            return Err(config_error(
                "homing needs the inline planner without pressure advance",
            ));
        }
        if !(print_time.is_finite() && print_time >= 0.0) || pos.iter().any(|v| !v.is_finite()) {
            return Err(config_error("homing: non-finite resync time or position"));
        }
        // Shaped steps start `settle` before a motion (0 without shaping).
        self.th.reset_after_stop(print_time + self.settle, pos);
        self.sync_gcode_position();
        if let Backend::Inline(lanes, _) = &mut self.backend {
            for lane in lanes.iter_mut() {
                if let Some(g) = &mut lane.shaped {
                    g.restart();
                }
            }
            for &(idx, steps) in stopped {
                let (Some(lane), Some(view)) = (lanes.get_mut(idx), self.views.get_mut(idx)) else {
                    return Err(config_error("homing: unknown stepper index"));
                };
                let mm = lane.kin.position(&pos);
                // The stepper keeps counting at its own clock's rate.
                lane.comp.resync(steps, mm, lane.clock.freq);
                view.position = steps;
            }
        }
        let horizon = (print_time * self.clock_freq).max(0.0) as u64;
        self.upto = self.upto.min(horizon);
        self.planned_until = print_time;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use crate::pipeline::{Pipeline, PipelineConfig, StepperSpec};
    use crate::stepgen::StepCmd;
    use crate::toolhead::ToolheadConfig;

    fn pipeline() -> Pipeline {
        pipeline_with(crate::pipeline::PipelineOptions::default())
    }

    fn pipeline_with(opts: crate::pipeline::PipelineOptions) -> Pipeline {
        let cfg = PipelineConfig {
            toolhead: ToolheadConfig {
                max_velocity: 300.0,
                max_accel: 3000.0,
                minimum_cruise_ratio: 0.5,
                square_corner_velocity: 5.0,
                max_z_velocity: 15.0,
                max_z_accel: 100.0,
                max_extrude_only_velocity: 50.0,
                max_extrude_only_accel: 1000.0,
                max_extrude_only_distance: 50.0,
                axis_limits: [(0.0, 200.0); 3],
            },
            steppers: (0..3)
                .map(|axis| StepperSpec {
                    name: format!("stepper_{axis}"),
                    axis,
                    step_dist: 0.0125,
                    extruder: None,
                })
                .collect(),
            clock_freq: 1e6,
            max_error_s: 25e-6,
            home_position: [0.0; 3],
        };
        Pipeline::with_options(cfg, 1.0, opts).unwrap()
    }

    fn net_steps(cmds: &[(usize, StepCmd)], idx: usize) -> i64 {
        let mut dir = true;
        let mut n = 0;
        for &(i, c) in cmds {
            if i != idx {
                continue;
            }
            match c {
                StepCmd::SetDir { dir: d } => dir = d,
                StepCmd::QueueStep { count, .. } => n += if dir { count as i64 } else { -(count as i64) },
                StepCmd::ResetClock { .. } => {}
            }
        }
        n
    }

    #[test]
    fn homing_move_stop_and_resync() {
        let mut p = pipeline();
        assert!(p.supports_homing());
        p.set_toolhead_position([300.0, 10.0, 10.0, 0.0]);
        p.raise_print_time(2.0).unwrap();
        let mv = p.home_move([0.0, 10.0, 10.0, 0.0], 10.0).unwrap().unwrap();
        assert_eq!(mv.print_time, 2.0);
        assert!(mv.end_time() > 31.0);
        let mut out = Vec::new();
        p.generate(&mut out);
        assert_eq!(net_steps(&out, 0), -24000);
        // The MCU stopped X after 800 steps (10 mm) at print time ~3 s; resync at 3.5 s.
        p.resync_after_stop(3.5, [0.05, 10.0, 10.0, 0.0], &[(0, -800)])
            .unwrap();
        assert_eq!(p.stepper_positions()[0], -800);
        assert_eq!(p.position()[0], 0.05);
        assert_eq!(p.toolhead_print_time(), 3.5);
        assert_eq!(p.planned_until(), 3.5);
        // Retract 5 mm: starts with a reset at ≥ 3.5 s, 400 steps up.
        out.clear();
        p.home_move([5.05, 10.0, 10.0, 0.0], 10.0).unwrap().unwrap();
        p.generate(&mut out);
        let x: Vec<_> = out.iter().filter(|(i, _)| *i == 0).map(|&(_, c)| c).collect();
        assert!(matches!(x[0], StepCmd::ResetClock { clock } if (3_500_000..3_600_000).contains(&clock)));
        assert_eq!(x[1], StepCmd::SetDir { dir: true });
        assert_eq!(net_steps(&out, 0), 400);
        assert_eq!(p.stepper_positions()[0], -400);
        assert_eq!(p.gcode_state().gcode_position()[0], 5.05);
        // Every released command is in clock order.
        let mut last = 0;
        for &(_, c) in &out {
            if let StepCmd::QueueStep { first_clock, .. } = c {
                assert!(first_clock >= last);
                last = first_clock;
            }
        }
    }

    #[test]
    fn shaped_homing_move_stop_and_resync() {
        use crate::shaper::{AxisShaper, InputShaper};
        let shaper = InputShaper {
            x: AxisShaper {
                freq: 50.0,
                ..AxisShaper::default()
            },
            y: AxisShaper {
                freq: 40.0,
                ..AxisShaper::default()
            },
        };
        let mut p = pipeline_with(crate::pipeline::PipelineOptions {
            input_shaper: Some(shaper),
            ..Default::default()
        });
        assert!(p.supports_homing());
        p.set_toolhead_position([300.0, 10.0, 10.0, 0.0]);
        p.raise_print_time(2.0).unwrap();
        p.home_move([0.0, 10.0, 10.0, 0.0], 10.0).unwrap().unwrap();
        let mut out = Vec::new();
        p.generate(&mut out);
        assert_eq!(net_steps(&out, 0), -24000);
        p.resync_after_stop(3.5, [0.05, 10.0, 10.0, 0.0], &[(0, -800)])
            .unwrap();
        assert_eq!(p.stepper_positions()[0], -800);
        let lead = shaper.span();
        assert!((p.toolhead_print_time() - (3.5 + lead)).abs() < 1e-12);
        // Retract 5 mm, then move Y: every shaped step after 3.5 s, counts exact.
        out.clear();
        p.home_move([5.05, 10.0, 10.0, 0.0], 10.0).unwrap().unwrap();
        p.home_move([5.05, 20.0, 10.0, 0.0], 10.0).unwrap().unwrap();
        p.generate(&mut out);
        let x: Vec<_> = out.iter().filter(|(i, _)| *i == 0).map(|&(_, c)| c).collect();
        assert!(matches!(x[0], StepCmd::ResetClock { clock } if (3_500_000..3_600_000).contains(&clock)));
        assert_eq!(net_steps(&out, 0), 400);
        assert_eq!(net_steps(&out, 1), 800);
        assert_eq!(p.stepper_positions()[..2], [-400, 800]);
        let mut last = 3_500_000;
        for &(_, c) in &out {
            if let StepCmd::QueueStep { first_clock, .. } = c {
                assert!(first_clock >= last);
                last = first_clock;
            }
        }
    }
}
