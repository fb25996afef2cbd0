//! `[screws_tilt_adjust]` and `[bed_screws]`: the bed's levelling screws (Klipper's options).
//!
//! Both: `screw1`, `screw2`… (`X, Y`, nozzle positions; at least 3, up to the first missing
//! index), `screwN_name` (default `screw at X,Y` with three decimals, as Klipper names them), `horizontal_move_z` (default 5), `speed` (> 0,
//! default 50). `[screws_tilt_adjust]`: `screw_thread` (`CW-M3` default, `CCW-M3`, `CW-M4`,
//! `CCW-M4`, `CW-M5`, `CCW-M5`, `CW-M6`, `CCW-M6`, `CW-M8`, `CCW-M8`). `[bed_screws]`:
//! `screwN_fine_adjust` (`X, Y`), `probe_height` (default 0), `probe_speed` (> 0, default 5).

use planner::gcode::bed_screws::{BedScrewsConfig, ScrewSpot};

use super::bed_mesh::pair as xy;
use super::error::ConfigError;
use super::reader::{Bounds, SectionReader};

/// A screw thread: its pitch (mm per turn) and whether turning clockwise lowers the bed there.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScrewThread {
    pub pitch: f64,
    pub clockwise: bool,
}

/// The choices of `screw_thread`.
pub const SCREW_THREADS: [(&str, ScrewThread); 10] = [
    (
        "CW-M3",
        ScrewThread {
            pitch: 0.5,
            clockwise: true,
        },
    ),
    (
        "CCW-M3",
        ScrewThread {
            pitch: 0.5,
            clockwise: false,
        },
    ),
    (
        "CW-M4",
        ScrewThread {
            pitch: 0.7,
            clockwise: true,
        },
    ),
    (
        "CCW-M4",
        ScrewThread {
            pitch: 0.7,
            clockwise: false,
        },
    ),
    (
        "CW-M5",
        ScrewThread {
            pitch: 0.8,
            clockwise: true,
        },
    ),
    (
        "CCW-M5",
        ScrewThread {
            pitch: 0.8,
            clockwise: false,
        },
    ),
    (
        "CW-M6",
        ScrewThread {
            pitch: 1.0,
            clockwise: true,
        },
    ),
    (
        "CCW-M6",
        ScrewThread {
            pitch: 1.0,
            clockwise: false,
        },
    ),
    (
        "CW-M8",
        ScrewThread {
            pitch: 1.25,
            clockwise: true,
        },
    ),
    (
        "CCW-M8",
        ScrewThread {
            pitch: 1.25,
            clockwise: false,
        },
    ),
];

/// One screw.
#[derive(Debug, Clone, PartialEq)]
pub struct Screw {
    pub name: String,
    pub xy: [f64; 2],
    /// `[bed_screws]` `screwN_fine_adjust`.
    pub fine_adjust: Option<[f64; 2]>,
}

/// `[screws_tilt_adjust]` or `[bed_screws]`.
#[derive(Debug, Clone, PartialEq)]
pub struct ScrewsSection {
    pub screws: Vec<Screw>,
    pub horizontal_move_z: f64,
    pub speed: f64,
    /// `[screws_tilt_adjust]` only.
    pub thread: ScrewThread,
    /// `[bed_screws]` only.
    pub probe_height: f64,
    pub probe_speed: f64,
}

/// Reads either section (`tilt`: `[screws_tilt_adjust]`).
pub(crate) fn read_screws(s: &SectionReader<'_>, tilt: bool) -> Result<ScrewsSection, ConfigError> {
    let mut screws = Vec::new();
    for n in 1.. {
        let Some(at) = xy(s, &format!("screw{n}"))? else {
            break;
        };
        let name = match s.value(&format!("screw{n}_name")) {
            Some(v) => v.text.clone(),
            None => format!("screw at {:.3},{:.3}", at[0], at[1]),
        };
        let fine_adjust = match tilt {
            true => None,
            false => xy(s, &format!("screw{n}_fine_adjust"))?,
        };
        screws.push(Screw {
            name,
            xy: at,
            fine_adjust,
        });
    }
    if screws.len() < 3 {
        return Err(ConfigError::BadSection {
            at: s.at().clone(),
            section: s.name().to_string(),
            reason: format!(
                "needs at least 3 screws (screw1, screw2, screw3), got {}",
                screws.len()
            ),
        });
    }
    let default_thread = SCREW_THREADS[0].1;
    Ok(ScrewsSection {
        screws,
        horizontal_move_z: s.float_or("horizontal_move_z", 5.0, Bounds::ANY)?,
        speed: s.float_or("speed", 50.0, Bounds::ANY.above(0.0))?,
        thread: match tilt {
            true => s.choice("screw_thread", &SCREW_THREADS, Some(default_thread))?,
            false => default_thread,
        },
        probe_height: match tilt {
            true => 0.0,
            false => s.float_or("probe_height", 0.0, Bounds::ANY)?,
        },
        probe_speed: match tilt {
            true => 5.0,
            false => s.float_or("probe_speed", 5.0, Bounds::ANY.above(0.0))?,
        },
    })
}

/// The `BED_SCREWS_ADJUST` tool's settings of a `[bed_screws]` section.
pub fn bed_screws_tool(section: &ScrewsSection) -> BedScrewsConfig {
    let spot = |xy: [f64; 2], name: &str| ScrewSpot {
        xy,
        name: name.to_string(),
    };
    BedScrewsConfig {
        screws: section.screws.iter().map(|s| spot(s.xy, &s.name)).collect(),
        fine: section
            .screws
            .iter()
            .filter_map(|s| Some(spot(s.fine_adjust?, &s.name)))
            .collect(),
        speed: section.speed,
        probe_speed: section.probe_speed,
        horizontal_move_z: section.horizontal_move_z,
        probe_height: section.probe_height,
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use crate::printer::parse_str;

    use crate::printer::bed_mesh::tests::BASE;

    fn parse(body: &str) -> Result<crate::printer::PrinterConfig, String> {
        parse_str(&format!("{BASE}{body}"), Path::new("printer.cfg")).map_err(|e| e.to_string())
    }

    #[test]
    fn both_sections_read_their_screws() {
        let c = parse(
            "[screws_tilt_adjust]\nscrew1: 10, 10\nscrew1_name: front left\nscrew2: 190, 10\nscrew3: 100, 190\nscrew_thread: CCW-M4\n\
             [bed_screws]\nscrew1: 10, 10\nscrew1_fine_adjust: 0, 0\nscrew2: 190, 10\nscrew3: 100, 190\nprobe_speed: 3\n",
        )
        .unwrap();
        let t = c.screws_tilt_adjust.unwrap();
        assert_eq!(
            (t.screws[0].name.as_str(), t.screws[1].name.as_str()),
            ("front left", "screw at 190.000,10.000")
        );
        assert_eq!((t.thread.pitch, t.thread.clockwise), (0.7, false));
        let b = c.bed_screws.unwrap();
        assert_eq!((b.screws[0].fine_adjust, b.probe_speed), (Some([0.0, 0.0]), 3.0));
        let tool = c.host.host.bed_screws.unwrap();
        assert_eq!((tool.screws.len(), tool.fine.len()), (3, 1));
        assert_eq!(
            (tool.fine[0].xy, tool.fine[0].name.as_str()),
            ([0.0, 0.0], "screw at 10.000,10.000")
        );
        assert_eq!(
            (tool.horizontal_move_z, tool.probe_speed, tool.speed),
            (5.0, 3.0, 50.0)
        );
    }

    #[test]
    fn errors() {
        let e = parse("[screws_tilt_adjust]\nscrew1: 10, 10\nscrew2: 190, 10\n").unwrap_err();
        assert!(e.contains("needs at least 3 screws"), "{e}");
        let e = parse("[screws_tilt_adjust]\nscrew1: 10\nscrew2: 190, 10\nscrew3: 1, 1\n").unwrap_err();
        assert!(
            e.contains("[screws_tilt_adjust] screw1: must be two numbers 'X, Y', got '10'"),
            "{e}"
        );
        let e =
            parse("[screws_tilt_adjust]\nscrew1: 1, 1\nscrew2: 190, 10\nscrew3: 1, 1\nscrew_thread: M3\n")
                .unwrap_err();
        assert!(e.contains("expected one of CW-M3"), "{e}");
    }
}
