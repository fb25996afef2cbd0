//! `[mcu]` / `[mcu NAME]` (how to reach each microcontroller) and Cadence's own `[simulator]`
//! (settings of the simulated MCU process the host spawns for `serial: simulator`).

use super::error::ConfigError;
use super::pins::MAIN_MCU;
use super::reader::{Bounds, Reader, SectionReader};

/// The reserved `serial:` value: the host spawns its own simulated MCU instead of opening a port.
pub const SIMULATOR_SERIAL: &str = "simulator";

/// One MCU.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct McuSection {
    /// `"mcu"` for `[mcu]`, `NAME` for `[mcu NAME]`.
    pub name: String,
    /// Serial device path, or [`SIMULATOR_SERIAL`].
    pub serial: String,
    /// Default 250000, at least 2400.
    pub baud: u32,
    /// `arduino`, `cheetah`, `command` or `rpi_usb`.
    pub restart_method: Option<String>,
}

impl McuSection {
    /// True for `serial: simulator`.
    pub fn is_simulated(&self) -> bool {
        self.serial == SIMULATOR_SERIAL
    }
}

/// `[simulator]` (optional, Cadence-specific).
#[derive(Debug, Clone, PartialEq)]
pub struct SimulatorSection {
    /// The simulated MCU's CLOCK_FREQ in Hz; default 50 MHz.
    pub clock_freq: u64,
    /// Simulated seconds per real second; default 1.
    pub time_scale: f64,
    /// Where the simulated `[probe]` triggers: the simulated world's Z coordinate (mm) of the
    /// bed surface as the probe sees it; default 0. Independent of the probe's settings, so a
    /// test can check what PROBE measures.
    pub bed_surface_z: f64,
    /// The simulated bed's slope along X and Y (mm per mm; default 0): the probe triggers at
    /// `bed_surface_z + bed_tilt_x · x + bed_tilt_y · y + bed_warp · sin(2πx/P) · sin(2πy/P)` at
    /// the probe's X, Y (P = `bed_warp_period`).
    pub bed_tilt: [f64; 2],
    /// Amplitude of the simulated bed's bumps (mm; default 0).
    pub bed_warp: f64,
    /// Their wavelength (mm, > 0; default 100).
    pub bed_warp_period: f64,
    /// How far each Z motor's end of the gantry starts above the first's (mm, `[stepper_z]`
    /// first: `0, 0.4` lifts `[stepper_z1]`'s end by 0.4); default none: a level gantry.
    pub gantry_tilt: Vec<f64>,
    /// Where each Z motor's own endstop triggers above `[stepper_z] position_endstop`, on that
    /// motor's end of the gantry (mm, `[stepper_z]` first: `0, 0.2` puts `[stepper_z1]`'s
    /// switch 0.2 mm higher); default none: every switch at `position_endstop`.
    pub z_endstop_offsets: Vec<f64>,
}

impl SimulatorSection {
    /// True when the simulated bed is not flat.
    pub fn bed_is_shaped(&self) -> bool {
        self.bed_tilt != [0.0, 0.0] || self.bed_warp != 0.0
    }
}

impl Default for SimulatorSection {
    fn default() -> Self {
        SimulatorSection {
            clock_freq: 50_000_000,
            time_scale: 1.0,
            bed_surface_z: 0.0,
            bed_tilt: [0.0, 0.0],
            bed_warp: 0.0,
            bed_warp_period: 100.0,
            gantry_tilt: Vec::new(),
            z_endstop_offsets: Vec::new(),
        }
    }
}

const RESTART_METHODS: [(&str, &str); 4] = [
    ("arduino", "arduino"),
    ("cheetah", "cheetah"),
    ("command", "command"),
    ("rpi_usb", "rpi_usb"),
];

fn read_mcu(s: &SectionReader<'_>, name: &str) -> Result<McuSection, ConfigError> {
    let serial = s.string("serial")?;
    let baud = s.int("baud", Some(250_000u32), 2400..=i64::from(u32::MAX))?;
    let restart_method = match s.value("restart_method") {
        Some(_) => Some(s.choice("restart_method", &RESTART_METHODS, None)?.to_string()),
        None => None,
    };
    Ok(McuSection {
        name: name.to_string(),
        serial,
        baud,
        restart_method,
    })
}

/// `[mcu]` first (required), then every `[mcu NAME]` in file order.
pub(crate) fn read_mcus(reader: &Reader<'_>) -> Result<Vec<McuSection>, ConfigError> {
    let main = reader
        .section(MAIN_MCU)
        .ok_or_else(|| ConfigError::MissingSection {
            file: reader.main_file().to_path_buf(),
            section: MAIN_MCU.to_string(),
            needed_by: None,
        })?;
    let mut mcus = vec![read_mcu(&main, MAIN_MCU)?];
    for s in reader.sections_with_arg(MAIN_MCU) {
        let name = s.arg().unwrap_or_default();
        let reason = if name == MAIN_MCU {
            Some("an extra MCU cannot be named 'mcu'".to_string())
        } else if name.contains(|c: char| c.is_whitespace() || matches!(c, '^' | '~' | '!' | ':')) {
            Some(format!(
                "MCU name '{name}' must be one word without '^', '~', '!' or ':'"
            ))
        } else {
            None
        };
        if let Some(reason) = reason {
            return Err(ConfigError::BadSection {
                at: s.at().clone(),
                section: s.name().to_string(),
                reason,
            });
        }
        mcus.push(read_mcu(&s, name)?);
    }
    Ok(mcus)
}

pub(crate) fn read_simulator(s: &SectionReader<'_>) -> Result<SimulatorSection, ConfigError> {
    let d = SimulatorSection::default();
    Ok(SimulatorSection {
        clock_freq: s.int("clock_freq", Some(d.clock_freq), 1..=i64::MAX)?,
        time_scale: s.float_or("time_scale", d.time_scale, Bounds::ANY.above(0.0))?,
        bed_surface_z: s.float_or("bed_surface_z", d.bed_surface_z, Bounds::ANY)?,
        bed_tilt: [
            s.float_or("bed_tilt_x", 0.0, Bounds::ANY.min(-1.0).max(1.0))?,
            s.float_or("bed_tilt_y", 0.0, Bounds::ANY.min(-1.0).max(1.0))?,
        ],
        bed_warp: s.float_or("bed_warp", 0.0, Bounds::ANY.min(-10.0).max(10.0))?,
        bed_warp_period: s.float_or("bed_warp_period", d.bed_warp_period, Bounds::ANY.above(0.0))?,
        gantry_tilt: float_list(s, "gantry_tilt")?,
        z_endstop_offsets: float_list(s, "z_endstop_offsets")?,
    })
}

/// Option `name` of `s` as a comma-separated list of numbers (empty when absent).
fn float_list(s: &SectionReader<'_>, name: &str) -> Result<Vec<f64>, ConfigError> {
    match s.value(name) {
        None => Ok(Vec::new()),
        Some(v) => v
            .text
            .split(',')
            .map(|t| super::reader::parse_float(t.trim()))
            .collect::<Result<_, _>>()
            .map_err(|p| s.bad(name, v, p)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ini;
    use std::path::Path;

    fn mcus(text: &str) -> Result<Vec<McuSection>, String> {
        let file = ini::parse_str(text, Path::new("printer.cfg")).map_err(|e| e.to_string())?;
        read_mcus(&Reader::new(&file)).map_err(|e| e.to_string())
    }

    #[test]
    fn main_first_then_named_in_file_order() {
        let m = mcus("[mcu zed]\nserial: /dev/b\n[mcu]\nserial: simulator\nrestart_method: command\n[mcu ebb]\nserial: /dev/c\nbaud: 115200\n");
        let m = m.unwrap_or_else(|e| panic!("{e}"));
        let names: Vec<_> = m
            .iter()
            .map(|m| (m.name.as_str(), m.baud, m.is_simulated()))
            .collect();
        assert_eq!(
            names,
            [
                ("mcu", 250_000, true),
                ("zed", 250_000, false),
                ("ebb", 115_200, false)
            ]
        );
        assert_eq!(m[0].restart_method.as_deref(), Some("command"));
    }

    #[test]
    fn errors() {
        assert_eq!(
            mcus("[printer]\n"),
            Err("printer.cfg: Section 'mcu' must be specified".to_string())
        );
        assert_eq!(
            mcus("[mcu]\n"),
            Err("printer.cfg:1: Option 'serial' in section 'mcu' must be specified".to_string())
        );
        assert_eq!(
            mcus("[mcu]\nserial: x\n[mcu mcu]\nserial: y\n"),
            Err("printer.cfg:3: [mcu mcu] an extra MCU cannot be named 'mcu'".to_string())
        );
        assert_eq!(
            mcus("[mcu]\nserial: x\nbaud: 300\n"),
            Err("printer.cfg:3: [mcu] baud: must have minimum of 2400, got 300".to_string())
        );
        assert_eq!(
            mcus("[mcu]\nserial: x\nrestart_method: reboot\n"),
            Err("printer.cfg:3: [mcu] restart_method: expected one of arduino, cheetah, command, rpi_usb, got \
                 'reboot'"
                .to_string())
        );
    }
}
