//! A simulated BLTouch: a servo-controlled probe pin and its sensor output.
//!
//! The control pin carries servo pulses (one every 20 ms while a command is sent); the width
//! of each pulse is the command, as in the BLTouch's datasheet: 650 µs pin down, 1165 µs touch
//! switch mode, 1475 µs pin up, 1780 µs self test, 2190 µs alarm release (reset), 1988 / 2091 /
//! 1884 µs the V3 output-mode commands (accepted, no effect here). A pulse is measured from the
//! control pin's rising to its falling edge (the clocks of the soft-PWM edges the firmware
//! core reports through `set_pin`) and matched to the nearest command within
//! [`WIDTH_TOLERANCE_US`]; the command takes effect at the falling edge.
//!
//! The pin needs [`MOVE_TIME_S`] to deploy or stow. The sensor output, read at a sample's
//! clock with the toolhead's Z coordinate then:
//! - pin down and deployed, Z at or below the surface: a [`PULSE_S`] pulse, after which the
//!   pin stows itself (a genuine BLTouch retracts on contact); in touch switch mode the output
//!   instead follows the contact for as long as it lasts and the pin stays down;
//! - pin hitting the surface while it deploys: alarm (the output reads triggered until `reset`);
//! - pin up in touch switch mode: triggered (`pin_up_touch_mode_reports_triggered`);
//! - otherwise (pin up, moving, or deployed in the air): not triggered.
//!
//! Faults for tests of the host's checks: `stuck` (once deployed the pin never gets up again:
//! every later `pin_up` ends in alarm, so "BLTouch failed to raise probe"), `mute` (the sensor never reports: the
//! self-test fails with "BLTouch failed to verify sensor state", and the probe never triggers).

use super::world::Coord;

/// Time the pin takes to move up or down (s).
pub const MOVE_TIME_S: f64 = 0.3;
/// Length of the output pulse on contact in pin-down mode (s).
pub const PULSE_S: f64 = 0.010;
/// Largest difference between a measured pulse and a command's width (µs).
pub const WIDTH_TOLERANCE_US: f64 = 40.0;

/// A command of the control signal.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Command {
    PinDown,
    TouchMode,
    PinUp,
    SelfTest,
    Reset,
    /// The V3 output-mode commands (5V, OD, store).
    OutputMode,
}

/// Pulse widths (µs) of the commands.
pub const WIDTHS_US: [(f64, Command); 8] = [
    (650.0, Command::PinDown),
    (1165.0, Command::TouchMode),
    (1475.0, Command::PinUp),
    (1780.0, Command::SelfTest),
    (2190.0, Command::Reset),
    (1988.0, Command::OutputMode),
    (2091.0, Command::OutputMode),
    (1884.0, Command::OutputMode),
];

/// The command of a pulse `width_us` long, if one is near enough.
pub fn decode(width_us: f64) -> Option<Command> {
    WIDTHS_US
        .iter()
        .map(|&(w, c)| ((w - width_us).abs(), c))
        .filter(|&(d, _)| d <= WIDTH_TOLERANCE_US)
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, c)| c)
}

/// An injected defect.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fault {
    /// Once deployed, the pin never gets up again: every later `pin_up` ends in alarm.
    Stuck,
    /// The sensor output never goes high.
    Mute,
}

/// `--bltouch`: where the probe is wired and what it touches.
#[derive(Debug, Clone, PartialEq)]
pub struct BlTouchSpec {
    /// Sensor output (an input pin of this MCU).
    pub sensor_pin: u8,
    /// Control (servo) input (an output pin of this MCU).
    pub control_pin: u8,
    /// The coordinate the pin's tip follows (the toolhead's Z).
    pub coord: Coord,
    /// The coordinate at which the deployed pin touches the bed.
    pub surface_mm: f64,
    /// The input reads 0 when triggered (a `!` sensor pin).
    pub active_low: bool,
    pub fault: Option<Fault>,
}

/// The probe's state.
#[derive(Debug, Clone)]
pub struct BlTouch {
    pub spec: BlTouchSpec,
    ticks_per_s: f64,
    /// Rising edge of the pulse being measured.
    rise: Option<u64>,
    pin_down: bool,
    /// The pin has finished moving at this clock.
    moved_at: u64,
    touch_mode: bool,
    alarm: bool,
    /// A `pin_down` was received (the `Stuck` fault strikes from then on).
    deployed_once: bool,
    /// Start of the contact pulse (pin-down mode).
    touched_at: Option<u64>,
    /// Commands decoded so far (for tests and diagnostics).
    pub commands: u32,
}

impl BlTouch {
    /// A stowed, alarm-free probe on an MCU of `clock_freq` ticks per second.
    pub fn new(spec: BlTouchSpec, clock_freq: u32) -> BlTouch {
        BlTouch {
            spec,
            ticks_per_s: f64::from(clock_freq.max(1)),
            rise: None,
            pin_down: false,
            moved_at: 0,
            touch_mode: false,
            alarm: false,
            deployed_once: false,
            touched_at: None,
            commands: 0,
        }
    }

    fn ticks(&self, s: f64) -> u64 {
        (s * self.ticks_per_s) as u64
    }

    /// The control pin changed to `level` at `clock`.
    pub fn control(&mut self, level: bool, clock: u64) {
        match (level, self.rise) {
            (true, _) => self.rise = Some(clock),
            (false, Some(r)) => {
                self.rise = None;
                let width_us = clock.saturating_sub(r) as f64 / self.ticks_per_s * 1e6;
                if let Some(c) = decode(width_us) {
                    self.command(c, clock);
                }
            }
            (false, None) => {}
        }
    }

    /// Applies command `c` at `clock`. Repeated pulses of one command (sent every 20 ms)
    /// do not restart a move.
    pub fn command(&mut self, c: Command, clock: u64) {
        self.commands += 1;
        let move_ticks = self.ticks(MOVE_TIME_S);
        match c {
            Command::PinDown if !self.alarm && !self.pin_down => {
                self.pin_down = true;
                self.deployed_once = true;
                self.touch_mode = false;
                self.touched_at = None;
                self.moved_at = clock + move_ticks;
            }
            Command::TouchMode => self.touch_mode = true,
            Command::PinUp => {
                if self.pin_down || self.touch_mode {
                    self.moved_at = clock + move_ticks;
                }
                self.pin_down = false;
                self.touch_mode = false;
                if self.spec.fault == Some(Fault::Stuck) && self.deployed_once {
                    self.alarm = true;
                }
            }
            Command::Reset | Command::SelfTest => {
                self.alarm = false;
                self.pin_down = false;
                self.touch_mode = false;
                self.touched_at = None;
                self.moved_at = clock + move_ticks;
            }
            Command::PinDown | Command::OutputMode => {}
        }
    }

    /// The sensor output (before `active_low`) at `clock`, the pin's tip at coordinate `z`
    /// (`None`: unknown, the pin in the air).
    pub fn sense(&mut self, clock: u64, z: Option<f64>) -> bool {
        if self.alarm {
            return true;
        }
        let mute = self.spec.fault == Some(Fault::Mute);
        let contact = z.is_some_and(|z| z <= self.spec.surface_mm);
        if let Some(t) = self.touched_at {
            if clock < t + self.ticks(PULSE_S) {
                return !mute;
            }
            // The pulse is over: the pin stowed itself.
            self.touched_at = None;
        }
        if !self.pin_down {
            return self.touch_mode && !mute;
        }
        if clock < self.moved_at {
            if contact {
                // Deploying into the bed.
                self.alarm = true;
                return true;
            }
            return false;
        }
        if !contact || mute {
            return false;
        }
        if self.touch_mode {
            return true;
        }
        self.touched_at = Some(clock);
        self.pin_down = false;
        true
    }

    /// Whether the pin is down (deployed or deploying).
    pub fn is_down(&self) -> bool {
        self.pin_down
    }

    /// Whether the probe is in alarm.
    pub fn in_alarm(&self) -> bool {
        self.alarm
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const F: u32 = 1_000_000;

    fn probe(fault: Option<Fault>) -> BlTouch {
        BlTouch::new(
            BlTouchSpec {
                sensor_pin: 1,
                control_pin: 2,
                coord: Coord::axis("z"),
                surface_mm: 0.0,
                active_low: false,
                fault,
            },
            F,
        )
    }

    /// A servo pulse of `us` µs starting at `at` µs.
    fn pulse(b: &mut BlTouch, at: u64, us: u64) {
        b.control(true, at);
        b.control(false, at + us);
    }

    #[test]
    fn pulses_decode_to_the_nearest_command() {
        assert_eq!(decode(650.0), Some(Command::PinDown));
        assert_eq!(decode(1470.0), Some(Command::PinUp));
        assert_eq!(decode(2200.0), Some(Command::Reset));
        assert_eq!(decode(2091.0), Some(Command::OutputMode));
        assert_eq!(decode(900.0), None);
        assert_eq!(decode(0.0), None);
        assert_eq!(decode(f64::NAN), None);
    }

    #[test]
    fn deploys_touches_and_stows_itself() {
        let mut b = probe(None);
        assert!(!b.sense(0, Some(5.0)));
        pulse(&mut b, 1000, 650);
        // Repeated pulses of the same command do not restart the move.
        pulse(&mut b, 21_000, 650);
        assert!(b.is_down());
        assert!(!b.sense(200_000, Some(5.0)), "moving, in the air");
        assert!(!b.sense(400_000, Some(0.1)), "deployed, in the air");
        assert!(b.sense(500_000, Some(0.0)), "contact");
        assert!(b.sense(505_000, Some(-0.05)), "within the pulse");
        assert!(!b.sense(511_000, Some(-0.05)), "stowed itself after the pulse");
        assert!(!b.is_down());
    }

    #[test]
    fn touch_mode_follows_contact_and_reports_when_up() {
        let mut b = probe(None);
        pulse(&mut b, 0, 1165);
        assert!(b.sense(10_000, Some(5.0)), "pin up + touch mode: triggered");
        pulse(&mut b, 20_000, 1475);
        assert!(!b.sense(30_000, Some(5.0)));
        pulse(&mut b, 40_000, 650);
        pulse(&mut b, 400_000, 1165);
        assert!(!b.sense(450_000, Some(1.0)));
        assert!(b.sense(460_000, Some(0.0)));
        assert!(
            b.sense(600_000, Some(-0.1)),
            "touch mode: as long as the contact lasts"
        );
        assert!(!b.sense(700_000, Some(0.5)));
        assert!(b.is_down());
    }

    #[test]
    fn deploying_into_the_bed_is_an_alarm_until_reset() {
        let mut b = probe(None);
        pulse(&mut b, 0, 650);
        assert!(b.sense(100_000, Some(-1.0)));
        assert!(b.in_alarm());
        pulse(&mut b, 200_000, 1475);
        assert!(b.sense(600_000, Some(5.0)), "pin_up does not clear the alarm");
        pulse(&mut b, 700_000, 2190);
        assert!(!b.sense(1_100_000, Some(5.0)));
        assert!(!b.in_alarm());
    }

    #[test]
    fn faults() {
        let mut b = probe(Some(Fault::Stuck));
        pulse(&mut b, 0, 1475);
        assert!(!b.sense(400_000, Some(5.0)), "stuck: up until first deployed");
        pulse(&mut b, 500_000, 650);
        pulse(&mut b, 900_000, 1475);
        assert!(b.sense(1_300_000, Some(5.0)), "stuck: alarm after pin_up");
        pulse(&mut b, 1_400_000, 2190);
        pulse(&mut b, 1_800_000, 1475);
        assert!(b.sense(2_200_000, Some(5.0)), "stuck: again after a reset");
        let mut b = probe(Some(Fault::Mute));
        pulse(&mut b, 0, 1165);
        assert!(!b.sense(10_000, Some(5.0)), "mute: the self-test reads nothing");
        pulse(&mut b, 20_000, 650);
        assert!(!b.sense(400_000, Some(-1.0)));
    }
}
