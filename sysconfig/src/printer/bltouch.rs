//! `[bltouch]`: a BLTouch probe, Klipper's options, names and defaults.
//!
//! The section replaces `[probe]`: its `sensor_pin` is the probe's input (and
//! `probe:z_virtual_endstop`), and it takes every `[probe]` option but `pin`. The
//! `control_pin` carries the servo pulses that deploy and stow the pin (a soft-PWM output with
//! a 20 ms cycle on its MCU).

use super::error::ConfigError;
use super::pins::{PinKind, PinRef, PinRegistry, Share};
use super::probe::{read_probe_options, ProbeSection};
use super::reader::{Bounds, SectionReader};

/// `set_output_mode`: the sensor output a BLTouch V3 is asked for at start.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OutputMode {
    /// 5 V output.
    FiveVolt,
    /// Open drain.
    OpenDrain,
}

impl OutputMode {
    /// Klipper's option value (and `BLTOUCH_STORE MODE=`).
    pub fn name(self) -> &'static str {
        match self {
            OutputMode::FiveVolt => "5V",
            OutputMode::OpenDrain => "OD",
        }
    }
}

/// The choices of `set_output_mode`.
pub const OUTPUT_MODES: [(&str, OutputMode); 2] =
    [("5V", OutputMode::FiveVolt), ("OD", OutputMode::OpenDrain)];

/// `[bltouch]`'s own options.
#[derive(Debug, Clone, PartialEq)]
pub struct BlTouchSection {
    /// The servo signal output.
    pub control_pin: PinRef,
    /// Time the pin takes to move up or down (s), > 0; default 0.680.
    pub pin_move_time: f64,
    /// Stow between the samples of one measurement; default true.
    pub stow_on_each_sample: bool,
    /// Probe in touch switch mode; default false.
    pub probe_with_touch_mode: bool,
    /// The sensor reads "not triggered" once the pin is up (checked after every stow);
    /// default true.
    pub pin_up_reports_not_triggered: bool,
    /// The sensor reads "triggered" after pin_up + touch_mode (the self-test); default true.
    pub pin_up_touch_mode_reports_triggered: bool,
    /// Output mode requested at start; default none.
    pub set_output_mode: Option<OutputMode>,
}

/// Reads `[bltouch]`: the probe it is (its `sensor_pin` as the probe's pin) and its own options.
pub(crate) fn read_bltouch(
    s: &SectionReader<'_>,
    pins: &mut PinRegistry,
) -> Result<(ProbeSection, BlTouchSection), ConfigError> {
    let sensor_pin = s.pin("sensor_pin", PinKind::Input, pins, Share::Exclusive)?;
    let control_pin = s.pin("control_pin", PinKind::Output, pins, Share::Exclusive)?;
    let probe = read_probe_options(s, sensor_pin)?;
    let pin_move_time = s.float_or("pin_move_time", 0.680, Bounds::ANY.above(0.0))?;
    let flag = |option: &str, default: bool| s.opt_bool(option).map(|v| v.unwrap_or(default));
    let bltouch = BlTouchSection {
        control_pin,
        pin_move_time,
        stow_on_each_sample: flag("stow_on_each_sample", true)?,
        probe_with_touch_mode: flag("probe_with_touch_mode", false)?,
        pin_up_reports_not_triggered: flag("pin_up_reports_not_triggered", true)?,
        pin_up_touch_mode_reports_triggered: flag("pin_up_touch_mode_reports_triggered", true)?,
        set_output_mode: match s.value("set_output_mode") {
            Some(_) => Some(s.choice("set_output_mode", &OUTPUT_MODES, None)?),
            None => None,
        },
    };
    Ok((probe, bltouch))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::printer::test_support::read_section;

    /// Reads `[bltouch]` followed by `body` (from line 2).
    fn bltouch(body: &str) -> Result<(ProbeSection, BlTouchSection), String> {
        read_section("bltouch", body, read_bltouch)
    }

    #[test]
    fn defaults_follow_klipper() {
        let (p, b) =
            bltouch("sensor_pin: ^PA4\ncontrol_pin: PA5\nz_offset: 2.1\n").unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            (p.pin.pin.as_str(), p.pin.pullup, p.z_offset, p.speed),
            ("PA4", true, 2.1, 5.0)
        );
        assert_eq!(b.control_pin.pin, "PA5");
        assert_eq!(b.pin_move_time, 0.680);
        assert!(b.stow_on_each_sample && !b.probe_with_touch_mode);
        assert!(b.pin_up_reports_not_triggered && b.pin_up_touch_mode_reports_triggered);
        assert_eq!(b.set_output_mode, None);
    }

    #[test]
    fn options_are_read_and_checked() {
        let (p, b) = bltouch(
            "sensor_pin: ^PA4\ncontrol_pin: PA5\nz_offset: 1\nsamples: 3\npin_move_time: 0.4\n\
             stow_on_each_sample: False\nprobe_with_touch_mode: true\npin_up_reports_not_triggered: 0\n\
             pin_up_touch_mode_reports_triggered: False\nset_output_mode: OD\n",
        )
        .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(p.samples, 3);
        assert_eq!(b.pin_move_time, 0.4);
        assert!(!b.stow_on_each_sample && b.probe_with_touch_mode);
        assert!(!b.pin_up_reports_not_triggered && !b.pin_up_touch_mode_reports_triggered);
        assert_eq!(b.set_output_mode, Some(OutputMode::OpenDrain));
        let err = |body: &str| bltouch(body).err().unwrap_or_default();
        assert!(err("sensor_pin: PA4\nz_offset: 1\n").contains("control_pin"));
        assert!(err("control_pin: PA5\nz_offset: 1\n").contains("sensor_pin"));
        assert!(err("sensor_pin: PA4\ncontrol_pin: PA5\n").contains("z_offset"));
        assert!(
            err("sensor_pin: PA4\ncontrol_pin: PA5\nz_offset: 1\nset_output_mode: 12V\n")
                .contains("set_output_mode")
        );
        assert!(
            err("sensor_pin: PA4\ncontrol_pin: PA5\nz_offset: 1\npin_move_time: 0\n")
                .contains("pin_move_time")
        );
        assert!(err("sensor_pin: PA4\ncontrol_pin: ^PA5\nz_offset: 1\n").contains("control_pin"));
        assert!(err("sensor_pin: PA4\ncontrol_pin: PA5\nz_offset: 1\npin: PA6\n").contains("'pin'"));
    }
}
