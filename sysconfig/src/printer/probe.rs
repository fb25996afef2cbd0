//! `[probe]`: a Z probe (an endstop-like input pin, possibly on another MCU) with Klipper's
//! options, names, defaults and bounds.
//!
//! The probe's pin also provides the virtual endstop `probe:z_virtual_endstop`: with it as
//! `[stepper_z] endstop_pin`, Z homes on the probe and the endstop position is the probe's
//! `z_offset` (`position_endstop` is then not an option of `[stepper_z]`).
//!
//! A probe measurement with `samples` > 1 retracts `sample_retract_dist` at `lift_speed` between
//! samples; when the spread (max − min) of the samples exceeds `samples_tolerance`, the samples
//! are taken again up to `samples_tolerance_retries` times; the result is the `median` or the
//! `average` (default) of the samples.

use super::error::ConfigError;
use super::pins::{PinKind, PinRef, PinRegistry, Share};
use super::reader::{Bounds, SectionReader};
use planner::gcode::macros::MacroDef;

/// The pseudo-MCU name of the probe's virtual endstop (`probe:z_virtual_endstop`).
pub const PROBE_PIN_MCU: &str = "probe";
/// The one pin the probe's pseudo-MCU has.
pub const Z_VIRTUAL_ENDSTOP: &str = "z_virtual_endstop";

/// How the samples of one probe measurement combine.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SamplesResult {
    /// The middle sample (the mean of the two middle ones for an even count).
    Median,
    /// The mean.
    Average,
}

impl SamplesResult {
    /// Klipper's option value.
    pub fn name(self) -> &'static str {
        match self {
            SamplesResult::Median => "median",
            SamplesResult::Average => "average",
        }
    }
}

/// The choices of `samples_result`.
pub const SAMPLES_RESULTS: [(&str, SamplesResult); 2] = [
    ("median", SamplesResult::Median),
    ("average", SamplesResult::Average),
];

/// `[probe]`.
#[derive(Debug, Clone, PartialEq)]
pub struct ProbeSection {
    /// The probe's input pin (`^`/`~`, `!` and `mcu_name:` allowed).
    pub pin: PinRef,
    /// Probe position relative to the nozzle (mm); default 0.
    pub x_offset: f64,
    pub y_offset: f64,
    /// Nozzle height when the probe triggers (mm); required.
    pub z_offset: f64,
    /// Probing speed (mm/s), > 0; default 5.
    pub speed: f64,
    /// Speed of the retract between samples (mm/s), > 0; default `speed`.
    pub lift_speed: f64,
    /// Samples per measurement, ≥ 1; default 1.
    pub samples: u32,
    /// Retract between samples (mm), > 0; default 2.
    pub sample_retract_dist: f64,
    /// Default average.
    pub samples_result: SamplesResult,
    /// Largest allowed spread of the samples (mm), ≥ 0; default 0.100.
    pub samples_tolerance: f64,
    /// Re-measurements when the spread is too large, ≥ 0; default 0.
    pub samples_tolerance_retries: u32,
    /// Z the probing move heads for; `None`: `[stepper_z] position_min`.
    pub z_position: Option<f64>,
    /// `activate_gcode`: run before each probing session (a G28 on the probe, PROBE,
    /// a levelling command), as a macro named [`PROBE_ACTIVATE_MACRO`]; `[probe]` only.
    pub activate_gcode: Option<MacroDef>,
    /// `deactivate_gcode`: run after each probing session, as a macro named
    /// [`PROBE_DEACTIVATE_MACRO`]; `[probe]` only.
    pub deactivate_gcode: Option<MacroDef>,
}

/// The macro name of `[probe] activate_gcode` (lower case: no G-code line can call it).
pub const PROBE_ACTIVATE_MACRO: &str = "probe_activate_gcode";
/// The macro name of `[probe] deactivate_gcode`.
pub const PROBE_DEACTIVATE_MACRO: &str = "probe_deactivate_gcode";

/// Option `option` of section `s`, when written and not blank, as a macro named `name`.
fn script(s: &SectionReader<'_>, option: &str, name: &str) -> Option<MacroDef> {
    let v = s.value(option)?;
    (!v.text.trim().is_empty()).then(|| MacroDef {
        name: name.to_string(),
        gcode: v.text.clone(),
        description: None,
        rename_existing: None,
        variables: Vec::new(),
        at: s.at().to_string(),
    })
}

pub(crate) fn read_probe(s: &SectionReader<'_>, pins: &mut PinRegistry) -> Result<ProbeSection, ConfigError> {
    let pin = s.pin("pin", PinKind::Input, pins, Share::Exclusive)?;
    Ok(ProbeSection {
        activate_gcode: script(s, "activate_gcode", PROBE_ACTIVATE_MACRO),
        deactivate_gcode: script(s, "deactivate_gcode", PROBE_DEACTIVATE_MACRO),
        ..read_probe_options(s, pin)?
    })
}

/// The options every probe section shares (`[probe]`, `[bltouch]`…), around its input `pin`.
pub(crate) fn read_probe_options(s: &SectionReader<'_>, pin: PinRef) -> Result<ProbeSection, ConfigError> {
    let x_offset = s.float_or("x_offset", 0.0, Bounds::ANY)?;
    let y_offset = s.float_or("y_offset", 0.0, Bounds::ANY)?;
    let z_offset = s.float("z_offset", Bounds::ANY)?;
    let speed = s.float_or("speed", 5.0, Bounds::ANY.above(0.0))?;
    let lift_speed = s.float_or("lift_speed", speed, Bounds::ANY.above(0.0))?;
    let samples = s.int("samples", Some(1u32), 1..=i64::from(u32::MAX))?;
    let sample_retract_dist = s.float_or("sample_retract_dist", 2.0, Bounds::ANY.above(0.0))?;
    let samples_result = s.choice("samples_result", &SAMPLES_RESULTS, Some(SamplesResult::Average))?;
    let samples_tolerance = s.float_or("samples_tolerance", 0.100, Bounds::ANY.min(0.0))?;
    let samples_tolerance_retries =
        s.int("samples_tolerance_retries", Some(0u32), 0..=i64::from(u32::MAX))?;
    let z_position = s.opt_float("z_position", Bounds::ANY)?;
    Ok(ProbeSection {
        pin,
        x_offset,
        y_offset,
        z_offset,
        speed,
        lift_speed,
        samples,
        sample_retract_dist,
        samples_result,
        samples_tolerance,
        samples_tolerance_retries,
        z_position,
        activate_gcode: None,
        deactivate_gcode: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::printer::test_support::{read_never_panics, read_section};
    use proptest::prelude::*;

    /// Reads `[probe]` followed by `body` (from line 2).
    fn probe(body: &str) -> Result<ProbeSection, String> {
        read_section("probe", body, read_probe)
    }

    #[test]
    fn defaults_follow_klipper() {
        let p = probe("pin: ^!probe_mcu:PA4\nz_offset: 1.5\n").unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            (p.pin.mcu.as_str(), p.pin.pin.as_str(), p.pin.pullup, p.pin.invert),
            ("probe_mcu", "PA4", true, true)
        );
        assert_eq!((p.x_offset, p.y_offset, p.z_offset), (0.0, 0.0, 1.5));
        assert_eq!((p.speed, p.lift_speed, p.samples), (5.0, 5.0, 1));
        assert_eq!(
            (p.sample_retract_dist, p.samples_result, p.samples_tolerance),
            (2.0, SamplesResult::Average, 0.1)
        );
        assert_eq!((p.samples_tolerance_retries, p.z_position), (0, None));
    }

    #[test]
    fn every_option_is_read() {
        let p = probe(
            "pin: PA4\nx_offset: -20\ny_offset: 5.5\nz_offset: 0.8\nspeed: 3\nlift_speed: 10\nsamples: 3\n\
             sample_retract_dist: 1.5\nsamples_result: median\nsamples_tolerance: 0.01\n\
             samples_tolerance_retries: 2\nz_position: -1\n",
        )
        .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((p.x_offset, p.y_offset, p.z_offset), (-20.0, 5.5, 0.8));
        assert_eq!((p.speed, p.lift_speed, p.samples), (3.0, 10.0, 3));
        assert_eq!(
            (p.sample_retract_dist, p.samples_result, p.samples_tolerance),
            (1.5, SamplesResult::Median, 0.01)
        );
        assert_eq!((p.samples_tolerance_retries, p.z_position), (2, Some(-1.0)));
        assert_eq!(
            probe("pin: PA4\nz_offset: 1\nspeed: 8\n").map(|p| p.lift_speed),
            Ok(8.0)
        );
    }

    #[test]
    fn activate_and_deactivate_scripts_are_macros() {
        let p = probe(
            "pin: PA4\nz_offset: 1\nactivate_gcode:\n  probe_reset\n  G4 P10\ndeactivate_gcode: M117 up\n",
        )
        .unwrap_or_else(|e| panic!("{e}"));
        let a = p.activate_gcode.unwrap_or_else(|| panic!("no activate_gcode"));
        assert_eq!(
            (a.name.as_str(), a.gcode.trim()),
            (PROBE_ACTIVATE_MACRO, "probe_reset\nG4 P10")
        );
        let d = p
            .deactivate_gcode
            .unwrap_or_else(|| panic!("no deactivate_gcode"));
        assert_eq!(
            (d.name.as_str(), d.gcode.as_str()),
            (PROBE_DEACTIVATE_MACRO, "M117 up")
        );
        // Blank, as Klipper's default: no script.
        let p = probe("pin: PA4\nz_offset: 1\nactivate_gcode:\n").unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(p.activate_gcode, None);
    }

    #[test]
    fn errors_name_file_line_section_and_option() {
        let cases = [
            ("z_offset: 1\n", "printer.cfg:1: Option 'pin' in section 'probe' must be specified"),
            ("pin: PA4\n", "printer.cfg:1: Option 'z_offset' in section 'probe' must be specified"),
            ("pin: PA4\nz_offset: x\n", "printer.cfg:3: [probe] z_offset: expected a number, got 'x'"),
            ("pin: PA4\nz_offset: 1\nspeed: 0\n", "printer.cfg:4: [probe] speed: must be above 0, got 0"),
            (
                "pin: PA4\nz_offset: 1\nlift_speed: -1\n",
                "printer.cfg:4: [probe] lift_speed: must be above 0, got -1",
            ),
            ("pin: PA4\nz_offset: 1\nsamples: 0\n", "printer.cfg:4: [probe] samples: must have minimum of 1, got 0"),
            (
                "pin: PA4\nz_offset: 1\nsamples: 2.5\n",
                "printer.cfg:4: [probe] samples: expected an integer, got '2.5'",
            ),
            (
                "pin: PA4\nz_offset: 1\nsample_retract_dist: 0\n",
                "printer.cfg:4: [probe] sample_retract_dist: must be above 0, got 0",
            ),
            (
                "pin: PA4\nz_offset: 1\nsamples_result: mean\n",
                "printer.cfg:4: [probe] samples_result: expected one of median, average, got 'mean'",
            ),
            (
                "pin: PA4\nz_offset: 1\nsamples_tolerance: -0.1\n",
                "printer.cfg:4: [probe] samples_tolerance: must have minimum of 0, got -0.1",
            ),
            (
                "pin: PA4\nz_offset: 1\nsamples_tolerance_retries: -1\n",
                "printer.cfg:4: [probe] samples_tolerance_retries: must have minimum of 0, got -1",
            ),
            (
                "pin: nope:PA4\nz_offset: 1\n",
                "printer.cfg:2: [probe] pin: pin 'nope:PA4' refers to mcu 'nope', but there is no [mcu nope] \
                 section",
            ),
            (
                "pin: !^PA4\nz_offset: 1\n",
                "printer.cfg:2: [probe] pin: invalid pin '!^PA4': '^' or '~' must come before '!'",
            ),
            (
                "pin: probe:z_virtual_endstop\nz_offset: 1\n",
                "printer.cfg:2: [probe] pin: pin 'probe:z_virtual_endstop' is the probe's own virtual endstop \
                 (only for [stepper_z] endstop_pin)",
            ),
            ("pin: PA4\nz_offset: 1\nfoo: 2\n", "printer.cfg:4: Option 'foo' is not valid in section 'probe'"),
        ];
        for (body, want) in cases {
            assert_eq!(probe(body).map(|_| ()), Err(want.to_string()), "{body}");
        }
    }

    proptest! {
        #[test]
        fn never_panics(
            speed in "[-0-9.a-z]{0,6}",
            samples in "[-0-9.a-z]{0,4}",
            result in "[a-z]{0,8}",
        ) {
            let options = [("speed", &*speed), ("samples", &*samples), ("samples_result", &*result)];
            read_never_panics("probe", "pin: PA4\nz_offset: 1\n", &options, read_probe);
        }
    }
}
