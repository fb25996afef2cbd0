//! `[input_shaper]` (Klipper's, optional): the shapers the toolhead's X and Y motion is
//! convolved with before kinematics. `shaper_type` (default mzv) names the type of both axes,
//! `shaper_type_x` / `shaper_type_y` override it; `shaper_freq_x` / `shaper_freq_y` (Hz, default
//! 0 = that axis unshaped); `damping_ratio_x` / `damping_ratio_y` (default 0.1, at most the
//! type's limit: 0.99, or 0.4 / 0.3 / 0.2 for ei / 2hump_ei / 3hump_ei). Cadence shapes X and Y
//! only: a `shaper_freq_z` above 0 is refused, and so is shaping on delta kinematics.

use planner::shaper::{AxisShaper, InputShaper, ShaperType, DEFAULT_DAMPING_RATIO};

use super::error::{ConfigError, ValueProblem};
use super::reader::{Bounds, SectionReader};

/// `[input_shaper]`: the planner's settings.
pub type InputShaperSection = InputShaper;

/// One axis's options (`axis` = x, y or z).
fn read_axis(s: &SectionReader<'_>, common: ShaperType, axis: char) -> Result<AxisShaper, ConfigError> {
    let shaper_type = s.choice(&format!("shaper_type_{axis}"), &ShaperType::ALL, Some(common))?;
    let damping_ratio = s.float_or(
        &format!("damping_ratio_{axis}"),
        DEFAULT_DAMPING_RATIO,
        Bounds::ANY.min(0.0).max(shaper_type.max_damping_ratio()),
    )?;
    let freq_key = format!("shaper_freq_{axis}");
    let freq = s.float_or(&freq_key, 0.0, Bounds::ANY.min(0.0))?;
    let shaper = AxisShaper {
        shaper_type,
        freq,
        damping_ratio,
    };
    if let Err(e) = shaper.validate() {
        if let Some(v) = s.value(&freq_key) {
            return Err(s.bad(&freq_key, v, ValueProblem::Invalid(e.to_string())));
        }
    }
    Ok(shaper)
}

pub(crate) fn read_input_shaper(
    s: &SectionReader<'_>,
    is_delta: bool,
) -> Result<InputShaperSection, ConfigError> {
    let common = s.choice("shaper_type", &ShaperType::ALL, Some(ShaperType::Mzv))?;
    let x = read_axis(s, common, 'x')?;
    let y = read_axis(s, common, 'y')?;
    let z = read_axis(s, common, 'z')?;
    if z.enabled() {
        if let Some(v) = s.value("shaper_freq_z") {
            return Err(s.bad(
                "shaper_freq_z",
                v,
                ValueProblem::Invalid("Cadence shapes X and Y only (use 0 or leave it out)".into()),
            ));
        }
    }
    let shaper = InputShaper { x, y };
    if is_delta && shaper.enabled() {
        return Err(ConfigError::BadSection {
            at: s.at().clone(),
            section: s.name().to_string(),
            reason:
                "input shaping is not supported on delta kinematics by Cadence (cartesian, corexy, corexz)"
                    .into(),
        });
    }
    Ok(shaper)
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::printer::simulated_with as config;

    #[test]
    fn reads_klippers_options_and_defaults() {
        let c = config("").unwrap();
        assert_eq!(c.input_shaper, None);
        let c = config("[input_shaper]\nshaper_freq_x: 50\nshaper_freq_y: 40").unwrap();
        let s = c.input_shaper.unwrap();
        assert_eq!(s.x.shaper_type, ShaperType::Mzv);
        assert_eq!((s.x.freq, s.y.freq, s.x.damping_ratio), (50.0, 40.0, 0.1));
        assert!(
            c.warnings.iter().all(|w| !w.contains("input_shaper")),
            "{:?}",
            c.warnings
        );
        let c = config(
            "[input_shaper]\nshaper_type: ei\nshaper_type_y: 2hump_ei\nshaper_freq_x: 60.5\n\
             shaper_freq_y: 45\ndamping_ratio_x: 0.05\ndamping_ratio_y: 0.2\nshaper_freq_z: 0",
        )
        .unwrap();
        let s = c.input_shaper.unwrap();
        assert_eq!(
            (s.x.shaper_type, s.y.shaper_type),
            (ShaperType::Ei, ShaperType::TwoHumpEi)
        );
        assert_eq!((s.x.damping_ratio, s.y.damping_ratio), (0.05, 0.2));
        // An empty section is a shaper that shapes nothing (SET_INPUT_SHAPER can turn it on).
        let s = config("[input_shaper]").unwrap().input_shaper.unwrap();
        assert!(!s.enabled());
    }

    #[test]
    fn bad_values_name_file_line_section_and_option() {
        let line = crate::printer::SIMULATED_PRINTER_CFG.lines().count() + 2;
        for (text, want) in [
            (
                "shaper_type: foo",
                "shaper_type: expected one of zv, mzv, zvd, ei, 2hump_ei, 3hump_ei, got 'foo'",
            ),
            ("shaper_type_x: MZV", "shaper_type_x: expected one of"),
            (
                "shaper_freq_x: -1",
                "shaper_freq_x: must have minimum of 0, got -1",
            ),
            (
                "shaper_freq_y: fast",
                "shaper_freq_y: expected a number, got 'fast'",
            ),
            (
                "shaper_type: 3hump_ei\ndamping_ratio_x: 0.3",
                "damping_ratio_x: must have maximum of 0.2",
            ),
            ("shaper_freq_x: 2", "shaper_freq_x: shaper mzv at 2 Hz spans"),
            ("shaper_freq_z: 30", "shaper_freq_z: Cadence shapes X and Y only"),
            (
                "shaper_freq_q: 30",
                "Option 'shaper_freq_q' is not valid in section 'input_shaper'",
            ),
        ] {
            let e = config(&format!("[input_shaper]\n{text}")).unwrap_err();
            assert!(e.contains(want), "{text}: {e}");
            let at = format!("printer.cfg:{}", line + text.lines().count());
            assert!(e.starts_with(&at), "{text}: {e} (expected at {at})");
            if !want.starts_with("Option") {
                assert!(e.contains("[input_shaper]"), "{e}");
            }
        }
    }
}
