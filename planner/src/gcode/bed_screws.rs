//! `[bed_screws]`'s interactive tool, as Klipper runs it: `BED_SCREWS_ADJUST` takes the nozzle
//! to each bed screw in turn (up to `horizontal_move_z`, over, down to `probe_height`), and the
//! user answers each with `ACCEPT` (the screw needed no turn), `ADJUSTED` (it was turned
//! noticeably) or `ABORT`. The tool counts the screws accepted in a row, going round the screws
//! as often as needed (an `ADJUSTED` starts the count again): once every screw is accepted in a
//! row, it goes through the `screwN_fine_adjust` points the same way, if there are any, then up
//! to `horizontal_move_z`, and is done. `ACCEPT`, `ADJUSTED` and `ABORT` are commands only while
//! the tool runs (else unknown, as in Klipper). One difference: Klipper counts the fine stage
//! against the number of screws, so a config where only some screws have a fine-adjust point
//! never finishes; here it counts against the fine points (the same when every screw has one).
//!
//! This module is the state machine alone: each command gives the moves to make (toolhead
//! coordinates, an axis left `None` keeps its place) and the message for the user; the G-code
//! feed makes the moves. A move that fails ends the tool ([`BedScrewsTool::abort`]).

/// The tool's commands.
pub const COMMANDS: [&str; 4] = ["BED_SCREWS_ADJUST", "ACCEPT", "ADJUSTED", "ABORT"];

/// One place the nozzle goes to: a screw, or its fine-adjust point.
#[derive(Debug, Clone, PartialEq)]
pub struct ScrewSpot {
    pub xy: [f64; 2],
    pub name: String,
}

/// What `[bed_screws]` configures.
#[derive(Debug, Clone, PartialEq)]
pub struct BedScrewsConfig {
    /// `screwN` (at least three).
    pub screws: Vec<ScrewSpot>,
    /// `screwN_fine_adjust` of the screws that have one, named as their screw.
    pub fine: Vec<ScrewSpot>,
    /// `speed` (mm/s), moves over the bed.
    pub speed: f64,
    /// `probe_speed` (mm/s), moves up and down.
    pub probe_speed: f64,
    pub horizontal_move_z: f64,
    pub probe_height: f64,
}

/// A toolhead move: X, Y, Z (`None`: where it is) at `speed` mm/s.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ToolMove {
    pub xyz: [Option<f64>; 3],
    pub speed: f64,
}

/// What one command does: moves, then a message for the user.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ToolStep {
    pub moves: Vec<ToolMove>,
    pub message: Option<String>,
}

/// The stage the tool is in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// The screws themselves.
    Adjust,
    /// Their fine-adjust points.
    Fine,
}

impl Stage {
    /// The name Klipper's status gives it.
    pub fn name(self) -> &'static str {
        match self {
            Stage::Adjust => "adjust",
            Stage::Fine => "fine",
        }
    }
}

/// Why a command of the tool was refused (Klipper's wording).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BedScrewsError {
    #[error("Already in bed_screws helper; use ABORT to exit")]
    AlreadyActive,
    /// `ACCEPT`/`ADJUSTED`/`ABORT` while the tool is not running (the feed does not route
    /// them here then: a bug if seen).
    #[error("{0}: the bed screws tool is not running (start it with BED_SCREWS_ADJUST)")]
    NotActive(String),
    #[error("{0}: not a command of the bed screws tool")]
    Unknown(String),
}

/// The tool and where it stands.
#[derive(Debug, Clone, PartialEq)]
pub struct BedScrewsTool {
    cfg: BedScrewsConfig,
    stage: Option<Stage>,
    current: usize,
    /// Spots accepted in a row (an `ADJUSTED` counts as none).
    accepted: usize,
}

impl BedScrewsTool {
    pub fn new(cfg: BedScrewsConfig) -> BedScrewsTool {
        BedScrewsTool {
            cfg,
            stage: None,
            current: 0,
            accepted: 0,
        }
    }

    /// True while the nozzle is at a screw waiting for an answer.
    pub fn is_active(&self) -> bool {
        self.stage.is_some()
    }

    /// Whether `name` is one of the tool's commands now: `BED_SCREWS_ADJUST` always, the
    /// answers while the tool runs.
    pub fn handles(&self, name: &str) -> bool {
        match name {
            "BED_SCREWS_ADJUST" => true,
            "ACCEPT" | "ADJUSTED" | "ABORT" => self.is_active(),
            _ => false,
        }
    }

    /// Runs command `name`.
    pub fn run(&mut self, name: &str) -> Result<ToolStep, BedScrewsError> {
        match name {
            "BED_SCREWS_ADJUST" => {
                if self.is_active() {
                    return Err(BedScrewsError::AlreadyActive);
                }
                self.accepted = 0;
                let mut step = ToolStep {
                    moves: vec![self.lift(self.cfg.speed)],
                    message: None,
                };
                self.go_to(Stage::Adjust, 0, &mut step);
                Ok(step)
            }
            "ACCEPT" | "ADJUSTED" => {
                let Some(stage) = self.stage else {
                    return Err(BedScrewsError::NotActive(name.to_string()));
                };
                self.accepted = match name {
                    "ADJUSTED" => 0,
                    _ => self.accepted + 1,
                };
                Ok(self.next(stage))
            }
            "ABORT" => {
                if !self.is_active() {
                    return Err(BedScrewsError::NotActive(name.to_string()));
                }
                self.abort();
                Ok(ToolStep::default())
            }
            other => Err(BedScrewsError::Unknown(other.to_string())),
        }
    }

    /// Ends the tool where it stands (`ABORT`, or a move that failed).
    pub fn abort(&mut self) {
        self.stage = None;
        self.current = 0;
        self.accepted = 0;
    }

    /// After an answer in `stage`: the next spot, round again from the first screw, the fine
    /// stage, or done.
    fn next(&mut self, stage: Stage) -> ToolStep {
        let mut step = ToolStep::default();
        let spots = self.spots(stage).len();
        let needed = match stage {
            Stage::Adjust => self.cfg.screws.len(),
            Stage::Fine => spots,
        };
        if self.accepted < needed && self.current + 1 < spots {
            self.go_to(stage, self.current + 1, &mut step);
        } else if self.accepted < needed {
            self.go_to(Stage::Adjust, 0, &mut step);
        } else if stage == Stage::Adjust && !self.cfg.fine.is_empty() {
            self.accepted = 0;
            self.go_to(Stage::Fine, 0, &mut step);
        } else {
            self.abort();
            step.moves.push(self.lift(self.cfg.probe_speed));
            step.message = Some("Bed screws tool completed successfully".to_string());
        }
        step
    }

    /// Up to `horizontal_move_z` where the nozzle is.
    fn lift(&self, speed: f64) -> ToolMove {
        ToolMove {
            xyz: [None, None, Some(self.cfg.horizontal_move_z)],
            speed,
        }
    }

    fn spots(&self, stage: Stage) -> &[ScrewSpot] {
        match stage {
            Stage::Adjust => &self.cfg.screws,
            Stage::Fine => &self.cfg.fine,
        }
    }

    /// Up, over to spot `i` of `stage`, down to `probe_height`, and the prompt.
    fn go_to(&mut self, stage: Stage, i: usize, step: &mut ToolStep) {
        let Some(spot) = self.spots(stage).get(i).cloned() else {
            self.abort();
            return;
        };
        let [x, y] = spot.xy;
        let (z_up, z_down) = (self.cfg.horizontal_move_z, self.cfg.probe_height);
        step.moves.push(self.lift(self.cfg.probe_speed));
        step.moves.push(ToolMove {
            xyz: [Some(x), Some(y), Some(z_up)],
            speed: self.cfg.speed,
        });
        step.moves.push(ToolMove {
            xyz: [Some(x), Some(y), Some(z_down)],
            speed: self.cfg.probe_speed,
        });
        self.stage = Some(stage);
        self.current = i;
        step.message = Some(format!(
            "Adjust {}. Then run ACCEPT, ADJUSTED, or ABORT\nUse ADJUSTED if a significant screw adjustment is made",
            spot.name
        ));
    }

    /// Klipper's `bed_screws` status: active, stage (`adjust`/`fine`), the spot's index and
    /// the spots accepted in a row.
    pub fn status(&self) -> (bool, Option<&'static str>, usize, usize) {
        (
            self.is_active(),
            self.stage.map(Stage::name),
            self.current,
            self.accepted,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg(fine: bool) -> BedScrewsConfig {
        let spot = |x: f64, y: f64, name: &str| ScrewSpot {
            xy: [x, y],
            name: name.to_string(),
        };
        BedScrewsConfig {
            screws: vec![
                spot(30.0, 30.0, "front left"),
                spot(170.0, 30.0, "front right"),
                spot(100.0, 170.0, "back"),
            ],
            fine: match fine {
                true => vec![
                    spot(40.0, 40.0, "front left"),
                    spot(160.0, 40.0, "front right"),
                    spot(100.0, 160.0, "back"),
                ],
                false => Vec::new(),
            },
            speed: 50.0,
            probe_speed: 5.0,
            horizontal_move_z: 5.0,
            probe_height: 0.1,
        }
    }

    /// The spot a step ends over and the screw it prompts for.
    fn at(step: &ToolStep) -> ([f64; 2], String) {
        let last = step.moves.last().unwrap();
        let xy = [last.xyz[0].unwrap(), last.xyz[1].unwrap()];
        let name = step
            .message
            .as_deref()
            .unwrap()
            .trim_start_matches("Adjust ")
            .split('.')
            .next()
            .unwrap();
        (xy, name.to_string())
    }

    #[test]
    fn each_screw_in_turn_then_done_when_all_are_accepted() {
        let mut t = BedScrewsTool::new(cfg(false));
        assert!(!t.handles("ACCEPT") && t.handles("BED_SCREWS_ADJUST"));
        let s = t.run("BED_SCREWS_ADJUST").unwrap();
        // Up at `speed`, then up, over and down to the first screw.
        assert_eq!(s.moves.len(), 4);
        assert_eq!(
            s.moves[0],
            ToolMove {
                xyz: [None, None, Some(5.0)],
                speed: 50.0
            }
        );
        assert_eq!(
            s.moves[3],
            ToolMove {
                xyz: [Some(30.0), Some(30.0), Some(0.1)],
                speed: 5.0
            }
        );
        assert!(s
            .message
            .as_deref()
            .unwrap()
            .starts_with("Adjust front left. Then run ACCEPT, ADJUSTED, or ABORT\n"));
        assert!(t.handles("ACCEPT") && t.is_active());
        assert_eq!(at(&t.run("ACCEPT").unwrap()).1, "front right");
        assert_eq!(t.status(), (true, Some("adjust"), 1, 1));
        assert_eq!(at(&t.run("ACCEPT").unwrap()).1, "back");
        let done = t.run("ACCEPT").unwrap();
        assert_eq!(
            done.message.as_deref(),
            Some("Bed screws tool completed successfully")
        );
        assert_eq!(
            done.moves,
            vec![ToolMove {
                xyz: [None, None, Some(5.0)],
                speed: 5.0
            }]
        );
        assert!(!t.is_active() && !t.handles("ACCEPT"));
    }

    #[test]
    fn screws_go_round_until_all_are_accepted_in_a_row_then_the_fine_points() {
        let mut t = BedScrewsTool::new(cfg(true));
        t.run("BED_SCREWS_ADJUST").unwrap();
        t.run("ACCEPT").unwrap();
        // Front right turned: the count starts again, and goes round to the front left.
        assert_eq!(at(&t.run("ADJUSTED").unwrap()).1, "back");
        assert_eq!(t.status(), (true, Some("adjust"), 2, 0));
        let round = t.run("ACCEPT").unwrap();
        assert_eq!(at(&round), ([30.0, 30.0], "front left".to_string()));
        assert_eq!(at(&t.run("ACCEPT").unwrap()).1, "front right");
        // Back, front left, front right accepted in a row: the fine points.
        let fine = t.run("ACCEPT").unwrap();
        assert_eq!(at(&fine), ([40.0, 40.0], "front left".to_string()));
        assert_eq!(t.status(), (true, Some("fine"), 0, 0));
        t.run("ACCEPT").unwrap();
        t.run("ACCEPT").unwrap();
        assert!(t
            .run("ACCEPT")
            .unwrap()
            .message
            .unwrap()
            .contains("completed successfully"));
        assert!(!t.is_active());
    }

    #[test]
    fn fewer_fine_points_than_screws_still_finish() {
        let mut c = cfg(true);
        c.fine.truncate(1);
        let mut t = BedScrewsTool::new(c);
        t.run("BED_SCREWS_ADJUST").unwrap();
        for _ in 0..3 {
            t.run("ACCEPT").unwrap();
        }
        assert_eq!(t.status(), (true, Some("fine"), 0, 0));
        assert!(t
            .run("ACCEPT")
            .unwrap()
            .message
            .unwrap()
            .contains("completed successfully"));
    }

    #[test]
    fn abort_and_refusals() {
        let mut t = BedScrewsTool::new(cfg(false));
        assert_eq!(t.run("ACCEPT"), Err(BedScrewsError::NotActive("ACCEPT".into())));
        t.run("BED_SCREWS_ADJUST").unwrap();
        assert_eq!(t.run("BED_SCREWS_ADJUST"), Err(BedScrewsError::AlreadyActive));
        assert_eq!(
            t.run("BED_SCREWS_ADJUST").unwrap_err().to_string(),
            "Already in bed_screws helper; use ABORT to exit"
        );
        assert_eq!(t.run("ABORT").unwrap(), ToolStep::default());
        assert!(!t.is_active() && !t.handles("ABORT"));
        assert!(t.run("BED_SCREWS_ADJUST").is_ok());
    }
}
