//! Homing support: after the MCU stopped this stepper part-way through its schedule (an
//! endstop's trsync fired), the compressor takes the MCU's position as the truth.
//!
//! What the MCU did: it discarded every queued step after the stop, so its position is the
//! reported one and its queue is empty. What must follow: a `reset_step_clock` before the next
//! step (the MCU's step clock base is stale), a `set_next_step_dir`, and step generation
//! re-anchored at the stepper's new commanded position. Steps generated but never compressed
//! (never sent) are dropped; nothing already emitted is touched.

use super::StepCompressor;
use crate::stepgen::StepGen;

impl StepCompressor {
    /// Resynchronises with an MCU that stopped this stepper at `mcu_position` net steps, the
    /// stepper now being commanded at `stepper_mm` (its position in mm in the kinematics'
    /// stepper coordinates); `clock_freq` is the MCU clock rate (ticks per print second).
    pub fn resync(&mut self, mcu_position: i64, stepper_mm: f64, clock_freq: f64) {
        self.pending.clear();
        self.head = 0;
        self.flips.clear();
        self.lines.clear();
        self.next = None;
        self.started = false;
        self.last_clock = 0;
        self.dir = None;
        self.last_add = 0;
        self.last_ideal = 0.0;
        self.position_steps = mcu_position;
        self.gen = StepGen::new(self.step_dist, clock_freq, stepper_mm);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::compress::StepCmd;

    #[test]
    fn next_steps_start_with_a_reset_and_a_direction() {
        let mut c = StepCompressor::new(0.01, 1e6, 25);
        for i in 1..=100 {
            c.push_step(1000.0 * i as f64, true);
        }
        let mut out = Vec::new();
        c.finish(&mut out);
        assert_eq!(c.position_steps(), 100);
        // The MCU stopped after 37 steps; the next steps are earlier than the old schedule.
        c.resync(37, 0.37, 1e6);
        assert_eq!(c.position_steps(), 37);
        out.clear();
        c.push_step(5000.0, false);
        c.push_step(6000.0, false);
        c.finish(&mut out);
        assert!(matches!(out[0], StepCmd::ResetClock { clock } if clock < 5000));
        assert_eq!(out[1], StepCmd::SetDir { dir: false });
        assert!(matches!(out[2], StepCmd::QueueStep { count: 2, first_clock, .. } if first_clock <= 5000));
        assert_eq!(c.position_steps(), 35);
    }
}
