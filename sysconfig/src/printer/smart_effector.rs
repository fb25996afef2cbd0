//! `[smart_effector]`: Duet3D's Smart Effector, a force-sensing Z probe, with Klipper's options,
//! names and defaults.
//!
//! The section replaces `[probe]` and takes every `[probe]` option (read by the same code,
//! `pin` and the activate/deactivate scripts included), plus its own: `probe_accel` (the
//! probing moves' acceleration limit, 0 = none), `recovery_time` (a dwell before each probing
//! move, 0 = none) and `control_pin` (the effector's programming input, a digital output;
//! without it the sensitivity cannot be programmed).

use super::error::ConfigError;
use super::pins::{PinKind, PinRef, PinRegistry, Share};
use super::probe::{read_probe, ProbeSection};
use super::reader::{Bounds, SectionReader};

/// `recovery_time`'s default (s).
pub const DEFAULT_RECOVERY_TIME: f64 = 0.4;

/// `[smart_effector]`'s own options.
#[derive(Debug, Clone, PartialEq)]
pub struct SmartEffectorSection {
    /// Acceleration of the probing moves (mm/s²), ≥ 0; 0 (the default): the toolhead's.
    pub probe_accel: f64,
    /// Dwell before each probing move (s), ≥ 0; default 0.4.
    pub recovery_time: f64,
    /// The effector's control input (`!` allowed); `None`: no sensitivity programming.
    pub control_pin: Option<PinRef>,
}

/// Reads `[smart_effector]`: the probe it is (every `[probe]` option) and its own options.
pub(crate) fn read_smart_effector(
    s: &SectionReader<'_>,
    pins: &mut PinRegistry,
) -> Result<(ProbeSection, SmartEffectorSection), ConfigError> {
    let probe = read_probe(s, pins)?;
    let effector = SmartEffectorSection {
        probe_accel: s.float_or("probe_accel", 0.0, Bounds::ANY.min(0.0))?,
        recovery_time: s.float_or("recovery_time", DEFAULT_RECOVERY_TIME, Bounds::ANY.min(0.0))?,
        control_pin: s.opt_pin("control_pin", PinKind::Output, pins, Share::Exclusive)?,
    };
    Ok((probe, effector))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::printer::test_support::{read_never_panics, read_section};
    use proptest::prelude::*;

    /// Reads `[smart_effector]` followed by `body` (from line 2).
    fn effector(body: &str) -> Result<(ProbeSection, SmartEffectorSection), String> {
        read_section("smart_effector", body, read_smart_effector)
    }

    #[test]
    fn defaults_follow_klipper() {
        let (p, e) = effector("pin: probe_mcu:PA4\nz_offset: -0.1\n").unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((p.pin.mcu.as_str(), p.pin.pin.as_str()), ("probe_mcu", "PA4"));
        assert_eq!((p.z_offset, p.speed, p.samples), (-0.1, 5.0, 1));
        assert_eq!(
            e,
            SmartEffectorSection {
                probe_accel: 0.0,
                recovery_time: 0.4,
                control_pin: None,
            }
        );
    }

    #[test]
    fn every_option_is_read() {
        let (p, e) = effector(
            "pin: ^PA4\ncontrol_pin: !PA5\nprobe_accel: 500\nrecovery_time: 0\nz_offset: 0.2\n\
             speed: 2\nsamples: 3\nsamples_result: median\nactivate_gcode: M117 on\n",
        )
        .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((p.speed, p.samples, p.samples_result.name()), (2.0, 3, "median"));
        assert!(p.activate_gcode.is_some() && p.pin.pullup);
        assert_eq!((e.probe_accel, e.recovery_time), (500.0, 0.0));
        let c = e.control_pin.unwrap_or_else(|| panic!("no control_pin"));
        assert_eq!((c.pin.as_str(), c.invert), ("PA5", true));
    }

    #[test]
    fn errors_name_file_line_section_and_option() {
        let cases = [
            (
                "z_offset: 1\n",
                "printer.cfg:1: Option 'pin' in section 'smart_effector' must be specified",
            ),
            (
                "pin: PA4\n",
                "printer.cfg:1: Option 'z_offset' in section 'smart_effector' must be specified",
            ),
            (
                "pin: PA4\nz_offset: 1\nprobe_accel: -5\n",
                "printer.cfg:4: [smart_effector] probe_accel: must have minimum of 0, got -5",
            ),
            (
                "pin: PA4\nz_offset: 1\nrecovery_time: soon\n",
                "printer.cfg:4: [smart_effector] recovery_time: expected a number, got 'soon'",
            ),
            (
                "pin: PA4\nz_offset: 1\nrecovery_time: -0.1\n",
                "printer.cfg:4: [smart_effector] recovery_time: must have minimum of 0, got -0.1",
            ),
            (
                "pin: PA4\nz_offset: 1\ncontrol_pin: PA4\n",
                "printer.cfg:4: [smart_effector] control_pin: pin 'PA4' is also used by [smart_effector] pin",
            ),
            (
                "pin: PA4\nz_offset: 1\ncontrol_pin: ^PA5\n",
                "printer.cfg:4: [smart_effector] control_pin: invalid pin '^PA5': pull-up '^' / pull-down '~' \
                 is not allowed on this pin",
            ),
            (
                "pin: PA4\nz_offset: 1\ncontrol_pin: other:PA5\n",
                "printer.cfg:4: [smart_effector] control_pin: pin 'other:PA5' refers to mcu 'other', but \
                 there is no [mcu other] section",
            ),
            (
                "pin: PA4\nz_offset: 1\nsensitivity: 40\n",
                "printer.cfg:4: Option 'sensitivity' is not valid in section 'smart_effector'",
            ),
        ];
        for (body, want) in cases {
            assert_eq!(effector(body).map(|_| ()), Err(want.to_string()), "{body}");
        }
    }

    proptest! {
        #[test]
        fn never_panics(
            accel in "[-0-9.a-z]{0,6}",
            recovery in "[-0-9.e]{0,6}",
            pin in "[!^~A-Za-z0-9:_]{0,8}",
        ) {
            let options = [("probe_accel", &*accel), ("recovery_time", &*recovery), ("control_pin", &*pin)];
            read_never_panics("smart_effector", "pin: PA4\nz_offset: 1\n", &options, read_smart_effector);
        }
    }
}
