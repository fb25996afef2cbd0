//! What a print's G-code asked of the heaters (M104/M109/M140/M190), the part fan (M106/M107),
//! the display (M117), position and temperature queries (M114, M105) and motors off (M84/M18).
//! Recorded while planning, with no I/O and no allocation on the planner thread, and reported
//! with the print's summary (the heaters themselves are driven by `crate::heaters::runtime`;
//! without a heater loop, e.g. in batch mode, a real board's first heat command is warned about
//! once).

use planner::gcode::CommandText;
use planner::machine::{Applied, HeaterId};

/// How many of the latest M117 messages and M114 reports the summary shows.
const KEEP: usize = 4;

/// The latest `KEEP` texts of one kind, with their G-code line, and how many there were.
#[derive(Debug, Default)]
struct Latest {
    ring: [Option<(usize, CommandText)>; KEEP],
    count: u64,
}

impl Latest {
    fn push(&mut self, line: usize, text: CommandText) {
        self.ring[(self.count % KEEP as u64) as usize] = Some((line, text));
        self.count += 1;
    }

    /// Oldest first.
    fn iter(&self) -> impl Iterator<Item = &(usize, CommandText)> {
        let start = (self.count % KEEP as u64) as usize;
        (0..KEEP).filter_map(move |k| self.ring[(start + k) % KEEP].as_ref())
    }
}

/// One heater's commands.
#[derive(Debug, Default, Clone, Copy)]
struct HeaterLog {
    target: f64,
    commands: u64,
    waits: u64,
}

/// See the module doc.
#[derive(Debug, Default)]
pub(crate) struct Accessories {
    /// Extruder, bed.
    heaters: [HeaterLog; 2],
    fan_speed: Option<f64>,
    fan_changes: u64,
    messages: Latest,
    reports: Latest,
    motors_off: u64,
    /// A real board prints: heater commands that ask for heat are warned about (once).
    real_board: bool,
    warned: bool,
}

impl Accessories {
    /// `real_board`: some MCU of the print is a real board (not the simulator).
    pub fn new(real_board: bool) -> Accessories {
        Accessories {
            real_board,
            ..Accessories::default()
        }
    }

    /// Records what `applied` (from G-code line `line`) asked; returns the one-time warning
    /// for heat asked of a real board.
    pub fn record(&mut self, line: usize, applied: &Applied) -> Option<String> {
        match applied {
            Applied::Heater { heater, target, wait } => {
                let h = &mut self.heaters[usize::from(*heater == HeaterId::Bed)];
                h.target = *target;
                h.commands += 1;
                h.waits += u64::from(*wait);
                if self.real_board && *target > 0.0 && !self.warned {
                    self.warned = true;
                    return Some(format!(
                        "line {line}: Cadence does not drive heaters yet: the {} is not heated to {target} °C \
                         and the print does not wait for it (reported once)",
                        heater_name(*heater)
                    ));
                }
            }
            Applied::Fan { speed } => {
                if self.fan_speed != Some(*speed) {
                    self.fan_changes += 1;
                }
                self.fan_speed = Some(*speed);
            }
            Applied::Message(text) => self.messages.push(line, text.clone()),
            Applied::Report(text) => self.reports.push(line, text.clone()),
            Applied::MotorsOff => self.motors_off += 1,
            Applied::Done
            | Applied::Unsupported(_)
            | Applied::PressureAdvance { .. }
            | Applied::Extruder { .. } => {}
        }
        None
    }

    /// The summary's lines (none when the G-code asked nothing of these).
    pub fn lines(&self) -> Vec<String> {
        let mut out = Vec::new();
        let used: Vec<String> = [HeaterId::Extruder(0), HeaterId::Bed]
            .into_iter()
            .zip(self.heaters)
            .filter(|(_, h)| h.commands > 0)
            .map(|(id, h)| {
                format!(
                    "{} last target {} °C ({} commands, {} waits)",
                    heater_name(id),
                    h.target,
                    h.commands,
                    h.waits
                )
            })
            .collect();
        if !used.is_empty() {
            let how = if self.real_board {
                "not driven by Cadence"
            } else {
                "G-code"
            };
            out.push(format!("heaters ({how}): {}", used.join(", ")));
        }
        if let Some(speed) = self.fan_speed {
            out.push(format!(
                "part fan (G-code): {} changes, last {:.0} %",
                self.fan_changes,
                speed * 100.0
            ));
        }
        for (kind, latest) in [("M117", &self.messages), ("M114", &self.reports)] {
            let earlier = latest.count.saturating_sub(KEEP as u64);
            if earlier > 0 {
                out.push(format!("{kind}: {earlier} earlier, then:"));
            }
            for (line, text) in latest.iter() {
                out.push(format!("{kind} (line {line}): {}", text.as_str()));
            }
        }
        if self.motors_off > 0 {
            out.push(format!(
                "M84/M18: {} times (axes unhomed, stepper drivers turned off)",
                self.motors_off
            ));
        }
        out
    }
}

fn heater_name(id: HeaterId) -> &'static str {
    id.name()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_and_reports() {
        let mut a = Accessories::new(false);
        let heat = |target, wait| Applied::Heater {
            heater: HeaterId::Extruder(0),
            target,
            wait,
        };
        assert_eq!(a.record(1, &heat(215.0, false)), None);
        a.record(2, &heat(215.0, true));
        a.record(3, &Applied::Fan { speed: 1.0 });
        a.record(4, &Applied::Fan { speed: 1.0 });
        a.record(5, &Applied::Fan { speed: 0.5 });
        for k in 0..6 {
            a.record(10 + k, &Applied::Message(CommandText::new(&format!("Layer {k}"))));
        }
        a.record(
            20,
            &Applied::Report(CommandText::new("X:1.000 Y:2.000 Z:3.000 E:0.000")),
        );
        let lines = a.lines();
        assert_eq!(
            lines[0],
            "heaters (G-code): extruder last target 215 °C (2 commands, 1 waits)"
        );
        assert_eq!(lines[1], "part fan (G-code): 2 changes, last 50 %");
        assert_eq!(lines[2], "M117: 2 earlier, then:");
        assert_eq!(lines[3], "M117 (line 12): Layer 2");
        assert_eq!(lines[6], "M117 (line 15): Layer 5");
        assert_eq!(lines[7], "M114 (line 20): X:1.000 Y:2.000 Z:3.000 E:0.000");
        assert_eq!(lines.len(), 8);
        assert!(Accessories::new(true).lines().is_empty());
    }

    #[test]
    fn a_real_board_warns_once_about_heat() {
        let mut a = Accessories::new(true);
        let bed = |target| Applied::Heater {
            heater: HeaterId::Bed,
            target,
            wait: true,
        };
        assert_eq!(a.record(1, &bed(0.0)), None);
        let w = a.record(2, &bed(60.0)).expect("warned");
        assert!(
            w.contains("line 2") && w.contains("heater_bed") && w.contains("60"),
            "{w}"
        );
        assert_eq!(a.record(3, &bed(60.0)), None);
        assert!(a.lines()[0].starts_with("heaters (not driven by Cadence): heater_bed last target 60 °C"));
    }
}
