//! FORCE_MOVE and STEPPER_BUZZ on the pipeline: the toolhead comes to rest, the named stepper's
//! lane moves on its own (see [`crate::force_move`]) while the toolhead dwells for the move's
//! duration, and its steps are released at once (a console command on an idle printer must
//! not wait for a next move).

use super::{LaneEvent, Pipeline};
use crate::force_move::{forced_move, BUZZ_CYCLES, BUZZ_DISTANCE, BUZZ_DWELLS, BUZZ_VELOCITY};
use crate::machine::{PlanError, PlanErrorKind};
use crate::stepgen::StepCmd;

fn bad(msg: String) -> PlanError {
    PlanError {
        line: 0,
        kind: PlanErrorKind::BadParameter(msg),
    }
}

impl Pipeline {
    /// The index of the stepper named `name` (as printer.cfg names it: `stepper_x`,
    /// `extruder`, an `[extruder_stepper NAME]`'s NAME).
    pub fn stepper_index(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }

    /// FORCE_MOVE STEPPER=`stepper` DISTANCE= VELOCITY= [ACCEL=]: the stepper alone moves
    /// `distance` mm; its step commands are appended to `out` with everything final before.
    pub fn force_move(
        &mut self,
        stepper: &str,
        distance: f64,
        velocity: f64,
        accel: f64,
        out: &mut Vec<(usize, StepCmd)>,
    ) -> Result<(), PlanError> {
        let lane = self
            .stepper_index(stepper)
            .ok_or_else(|| bad(format!("Unknown stepper {stepper}")))?;
        if !(velocity.is_finite() && velocity > 0.0) {
            return Err(bad(format!("VELOCITY={velocity} must be above 0")));
        }
        if !(accel.is_finite() && accel >= 0.0) {
            return Err(bad(format!("ACCEL={accel} must have minimum of 0")));
        }
        if !distance.is_finite() || distance.abs() > 1e4 {
            return Err(bad(format!("DISTANCE={distance} is not a plausible distance")));
        }
        // Steps of the moves before (and pressure advance's or shaping's tail) come first.
        self.th.flush();
        let tail = self.settle + self.max_err_ticks as f64 / self.clock_freq;
        self.th.dwell(tail).map_err(|e| bad(e.to_string()))?;
        let t0 = self.th.print_time();
        let duration = forced_move(t0, 0.0, distance, velocity, accel).duration();
        self.th.dwell(duration).map_err(|e| bad(e.to_string()))?;
        self.th.take_moves(&mut self.moves);
        let at = self.dispatched + self.moves.len() as u64;
        self.pa_pending
            .push_back((at, LaneEvent::ForceMove(lane, t0, distance, velocity, accel)));
        self.dispatch(true, true, 0);
        self.collect(true, out);
        self.release(u64::MAX, out);
        self.planned_until = self.planned_until.max(t0 + duration);
        Ok(())
    }

    /// STEPPER_BUZZ STEPPER=`stepper`: ten cycles of 1 mm forward and back (Klipper's).
    pub fn stepper_buzz(&mut self, stepper: &str, out: &mut Vec<(usize, StepCmd)>) -> Result<(), PlanError> {
        for _ in 0..BUZZ_CYCLES {
            self.force_move(stepper, BUZZ_DISTANCE, BUZZ_VELOCITY, 0.0, out)?;
            self.th.dwell(BUZZ_DWELLS.0).map_err(|e| bad(e.to_string()))?;
            self.force_move(stepper, -BUZZ_DISTANCE, BUZZ_VELOCITY, 0.0, out)?;
            self.th.dwell(BUZZ_DWELLS.1).map_err(|e| bad(e.to_string()))?;
        }
        Ok(())
    }
}
