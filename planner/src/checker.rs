//! Step command checker: replays `queue_step` / `set_next_step_dir` / `reset_step_clock` like the
//! MCU does (notes/contract.md "Step semantics") and proves, step by step, that every real step
//! lies in [ideal − max_error, ideal], never before the previous step, in the ideal step's
//! direction, and that the commands contain exactly the generated steps.
//!
//! [`Checker`] is incremental (feed ideal steps and commands as they are produced, memory stays
//! bounded by the steps in flight); [`check`] is the one-shot form.

use std::collections::VecDeque;

use crate::compress::MAX_INTERVAL;
pub use crate::stepgen::{IdealStep, StepCmd};

/// What a successful check saw.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct CheckStats {
    pub steps: u64,
    pub queue_steps: u64,
    pub resets: u64,
    pub dir_changes: u64,
    /// Net signed steps (the MCU's `stepper_get_position`).
    pub position: i64,
    /// Largest (ideal − real) seen, in ticks.
    pub max_early_ticks: f64,
}

/// The first violation found.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CheckError {
    #[error("command {cmd}: queue_step before any reset_step_clock")]
    NoClock { cmd: u64 },
    #[error("command {cmd}: queue_step before any set_next_step_dir")]
    NoDir { cmd: u64 },
    #[error("command {cmd}: queue_step with count 0")]
    ZeroCount { cmd: u64 },
    #[error("command {cmd}: reset_step_clock to {clock} is before the previous step at {prev}")]
    ResetBackwards { cmd: u64, clock: u64, prev: u64 },
    #[error("command {cmd}: interval {interval} outside 0..={max}")]
    BadInterval { cmd: u64, interval: i64, max: u64 },
    #[error("command {cmd}: first/last clock fields {fields:?} but the replay gives {replay:?}")]
    ClockFields {
        cmd: u64,
        fields: (u64, u64),
        replay: (u64, u64),
    },
    #[error("step {step}: at clock {clock}, before the previous step at {prev}")]
    OutOfOrder { step: u64, clock: u64, prev: u64 },
    #[error("step {step}: more steps commanded than generated")]
    ExtraStep { step: u64 },
    #[error("step {step}: direction {dir} but the ideal step's is {ideal}")]
    WrongDir { step: u64, dir: bool, ideal: bool },
    #[error("step {step}: at clock {clock}, {early:.1} ticks before its ideal time {ideal:.1} (max {max})")]
    TooEarly {
        step: u64,
        clock: u64,
        ideal: f64,
        early: f64,
        max: u32,
    },
    #[error("step {step}: at clock {clock}, after its ideal time {ideal:.1}")]
    TooLate { step: u64, clock: u64, ideal: f64 },
    #[error("{missing} generated steps were never commanded")]
    MissingSteps { missing: usize },
}

/// Incremental replay of one stepper's commands against its ideal steps.
#[derive(Debug)]
pub struct Checker {
    max_err: u32,
    ideal: VecDeque<IdealStep>,
    last_clock: Option<u64>,
    dir: Option<bool>,
    prev_step: u64,
    cmd: u64,
    stats: CheckStats,
    /// Compare each `queue_step`'s `first_clock`/`last_clock` with the replay.
    clock_fields: bool,
    /// Ticks a step may lie outside [ideal − max_error, ideal] (0, or ½ for the wire).
    tick_slack: f64,
}

impl Checker {
    pub fn new(max_error_ticks: u32) -> Checker {
        Checker {
            max_err: max_error_ticks,
            ideal: VecDeque::new(),
            last_clock: None,
            dir: None,
            prev_step: 0,
            cmd: 0,
            stats: CheckStats::default(),
            clock_fields: true,
            tick_slack: 0.0,
        }
    }

    /// A checker for commands decoded from the wire, which carries no first and last clock:
    /// those fields of `queue_step` are not compared (everything else is). A step on the wire
    /// is a whole tick: within half a tick of [ideal − max_error, ideal] counts as inside, as
    /// Klipper's host rounds each step time to the nearest tick (its stream's first step of
    /// examples/square.gcode lies 0.5 tick after the ideal time).
    pub fn for_wire(max_error_ticks: u32) -> Checker {
        Checker {
            clock_fields: false,
            tick_slack: 0.5,
            ..Checker::new(max_error_ticks)
        }
    }

    /// The clock of the next ideal step not commanded yet.
    pub fn next_ideal_clock(&self) -> Option<f64> {
        self.ideal.front().map(|s| s.clock)
    }

    /// Adds generated steps (in order) that later commands must contain.
    pub fn push_ideal(&mut self, steps: impl IntoIterator<Item = IdealStep>) {
        self.ideal.extend(steps);
    }

    /// Replays one command.
    pub fn check_cmd(&mut self, c: &StepCmd) -> Result<(), CheckError> {
        let cmd = self.cmd;
        self.cmd += 1;
        match *c {
            StepCmd::SetDir { dir } => {
                if self.dir.is_some_and(|d| d != dir) {
                    self.stats.dir_changes += 1;
                }
                self.dir = Some(dir);
            }
            StepCmd::ResetClock { clock } => {
                if self.stats.steps > 0 && clock < self.prev_step {
                    return Err(CheckError::ResetBackwards {
                        cmd,
                        clock,
                        prev: self.prev_step,
                    });
                }
                self.last_clock = Some(clock);
                self.stats.resets += 1;
            }
            StepCmd::QueueStep {
                interval,
                count,
                add,
                first_clock,
                last_clock,
            } => {
                let Some(mut clock) = self.last_clock else {
                    return Err(CheckError::NoClock { cmd });
                };
                let Some(dir) = self.dir else {
                    return Err(CheckError::NoDir { cmd });
                };
                if count == 0 {
                    return Err(CheckError::ZeroCount { cmd });
                }
                let mut iv = interval as i64;
                let mut first = None;
                for _ in 0..count {
                    if iv < 0 || iv as u64 > MAX_INTERVAL {
                        return Err(CheckError::BadInterval {
                            cmd,
                            interval: iv,
                            max: MAX_INTERVAL,
                        });
                    }
                    clock = clock.checked_add(iv as u64).ok_or(CheckError::BadInterval {
                        cmd,
                        interval: iv,
                        max: MAX_INTERVAL,
                    })?;
                    first.get_or_insert(clock);
                    self.step(clock, dir)?;
                    iv += add as i64;
                }
                let replay = (first.unwrap_or(clock), clock);
                if self.clock_fields && (first_clock, last_clock) != replay {
                    return Err(CheckError::ClockFields {
                        cmd,
                        fields: (first_clock, last_clock),
                        replay,
                    });
                }
                self.last_clock = Some(clock);
                self.stats.queue_steps += 1;
            }
        }
        Ok(())
    }

    fn step(&mut self, clock: u64, dir: bool) -> Result<(), CheckError> {
        let step = self.stats.steps;
        let Some(ideal) = self.ideal.pop_front() else {
            return Err(CheckError::ExtraStep { step });
        };
        if step > 0 && clock < self.prev_step {
            return Err(CheckError::OutOfOrder {
                step,
                clock,
                prev: self.prev_step,
            });
        }
        if dir != ideal.dir {
            return Err(CheckError::WrongDir {
                step,
                dir,
                ideal: ideal.dir,
            });
        }
        let c = clock as f64;
        if c > ideal.clock + self.tick_slack {
            return Err(CheckError::TooLate {
                step,
                clock,
                ideal: ideal.clock,
            });
        }
        let early = ideal.clock - c;
        if c < ideal.clock - self.max_err as f64 - self.tick_slack {
            return Err(CheckError::TooEarly {
                step,
                clock,
                ideal: ideal.clock,
                early,
                max: self.max_err,
            });
        }
        self.stats.max_early_ticks = self.stats.max_early_ticks.max(early);
        self.stats.steps += 1;
        self.stats.position += if dir { 1 } else { -1 };
        self.prev_step = clock;
        Ok(())
    }

    /// Ideal steps not commanded yet.
    pub fn outstanding(&self) -> usize {
        self.ideal.len()
    }

    /// Statistics so far, failing if generated steps were never commanded.
    pub fn finish(&self) -> Result<CheckStats, CheckError> {
        if !self.ideal.is_empty() {
            return Err(CheckError::MissingSteps {
                missing: self.ideal.len(),
            });
        }
        Ok(self.stats)
    }
}

/// Checks one stepper's full command list against its full list of ideal steps.
pub fn check(cmds: &[StepCmd], ideal: &[IdealStep], max_error_ticks: u32) -> Result<CheckStats, CheckError> {
    let mut c = Checker::new(max_error_ticks);
    c.push_ideal(ideal.iter().copied());
    for cmd in cmds {
        c.check_cmd(cmd)?;
    }
    c.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ideal(clocks: &[f64]) -> Vec<IdealStep> {
        clocks
            .iter()
            .map(|&clock| IdealStep { clock, dir: true })
            .collect()
    }

    #[test]
    fn accepts_an_exact_replay() {
        let cmds = [
            StepCmd::ResetClock { clock: 1000 },
            StepCmd::SetDir { dir: true },
            StepCmd::QueueStep {
                interval: 100,
                count: 3,
                add: 10,
                first_clock: 1100,
                last_clock: 1330,
            },
        ];
        let stats = check(&cmds, &ideal(&[1100.5, 1210.0, 1335.0]), 10).unwrap();
        assert_eq!(stats.steps, 3);
        assert_eq!(stats.position, 3);
        assert_eq!(stats.max_early_ticks, 5.0);
    }

    #[test]
    fn rejects_violations() {
        let q = |interval, count, add, first_clock, last_clock| StepCmd::QueueStep {
            interval,
            count,
            add,
            first_clock,
            last_clock,
        };
        let r = StepCmd::ResetClock { clock: 0 };
        let d = StepCmd::SetDir { dir: true };
        let one = ideal(&[100.0]);
        assert!(matches!(
            check(&[d, q(100, 1, 0, 100, 100)], &one, 5),
            Err(CheckError::NoClock { .. })
        ));
        assert!(matches!(
            check(&[r, q(100, 1, 0, 100, 100)], &one, 5),
            Err(CheckError::NoDir { .. })
        ));
        assert!(matches!(
            check(&[r, d, q(100, 0, 0, 100, 100)], &one, 5),
            Err(CheckError::ZeroCount { .. })
        ));
        assert!(matches!(
            check(&[r, d, q(101, 1, 0, 101, 101)], &one, 5),
            Err(CheckError::TooLate { .. })
        ));
        assert!(matches!(
            check(&[r, d, q(94, 1, 0, 94, 94)], &one, 5),
            Err(CheckError::TooEarly { .. })
        ));
        assert!(check(&[r, d, q(95, 1, 0, 95, 95)], &one, 5).is_ok());
        assert!(matches!(
            check(&[r, d, q(100, 1, 0, 99, 100)], &one, 5),
            Err(CheckError::ClockFields { .. })
        ));
        // From the wire: no clock fields to compare, the steps still checked.
        let mut w = Checker::for_wire(5);
        w.push_ideal(one.iter().copied());
        assert_eq!(w.next_ideal_clock(), Some(100.0));
        for c in [r, d, q(100, 1, 0, 0, 0)] {
            w.check_cmd(&c).unwrap();
        }
        assert_eq!(w.finish().map(|s| s.steps), Ok(1));
        let mut w = Checker::for_wire(5);
        w.push_ideal(one.iter().copied());
        w.check_cmd(&r).unwrap();
        w.check_cmd(&d).unwrap();
        assert!(matches!(
            w.check_cmd(&q(94, 1, 0, 0, 0)),
            Err(CheckError::TooEarly { .. })
        ));
        // On the wire a step time is the nearest tick (Klipper rounds): half a tick of slack.
        let mut w = Checker::for_wire(5);
        w.push_ideal(ideal(&[99.5, 110.4, 120.0]).iter().copied());
        for c in [r, d, q(100, 1, 0, 0, 0), q(10, 1, 0, 0, 0)] {
            w.check_cmd(&c).unwrap();
        }
        assert!(matches!(
            w.check_cmd(&q(11, 1, 0, 0, 0)),
            Err(CheckError::TooLate { .. })
        ));
        assert!(
            matches!(
                check(&[r, d, q(100, 1, 0, 100, 100)], &ideal(&[99.5]), 5),
                Err(CheckError::TooLate { .. })
            ),
            "Cadence's own commands stay within the exact bound"
        );
        assert!(matches!(
            check(&[r, d, q(100, 2, 0, 100, 200)], &one, 5),
            Err(CheckError::ExtraStep { .. })
        ));
        assert!(matches!(
            check(&[r, d], &one, 5),
            Err(CheckError::MissingSteps { missing: 1 })
        ));
        let down = StepCmd::SetDir { dir: false };
        assert!(matches!(
            check(&[r, down, q(100, 1, 0, 100, 100)], &one, 5),
            Err(CheckError::WrongDir { .. })
        ));
        let two = ideal(&[100.0, 100.0]);
        assert!(matches!(
            check(&[r, d, q(100, 2, -150, 100, 50)], &two, 100),
            Err(CheckError::BadInterval { .. })
        ));
        let late = [r, d, q(100, 1, 0, 100, 100), StepCmd::ResetClock { clock: 50 }];
        assert!(matches!(
            check(&late, &one, 5),
            Err(CheckError::ResetBackwards { .. })
        ));
    }
}
