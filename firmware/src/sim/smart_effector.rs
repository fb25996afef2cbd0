//! A simulated Duet3D Smart Effector's programming input: decodes the bit stream the host
//! writes on its control pin and keeps the sensitivity it was last programmed with.
//!
//! The line idles low. It carries [`BIT_S`]-long bits; each byte is 14 bits,
//! `0 0 1 0 b7 b6 b5 b4 !b4 b3 b2 b1 b0 !b0`, bytes back to back; a message ends when the
//! line stays low where the next byte's third bit (the `1`) would be. Messages: `105 s 255−s`
//! programs sensitivity `s`; `131 131` resets it to [`DEFAULT_SENSITIVITY`].
//!
//! The decoder sees only the pin's level changes (the clocks of the scheduled digital-out
//! updates the firmware core applies through `set_pin`). The first rise after idle is a
//! message's first `1` bit, two bits after the byte's start; it fixes the bit grid. Every
//! later change must fall on the grid within [`TIMING_TOLERANCE`] of a bit, else the message
//! is dropped and counted in [`SmartEffector::errors`]; so are a wrong start pattern, a
//! complement bit that does not complement, and a message that is neither command. A slot's
//! level is the level at its middle, filled in lazily when the next change comes (or at
//! [`SmartEffector::finish`]).

/// One bit on the control line (s): Klipper's 1000 bits/s.
pub const BIT_S: f64 = 0.001;
/// Largest distance of a level change from the bit grid, in bits.
pub const TIMING_TOLERANCE: f64 = 0.05;
/// Bits per byte on the line.
pub const BYTE_BITS: u32 = 14;
/// The sensitivity after a reset (the effector's factory setting).
pub const DEFAULT_SENSITIVITY: u8 = 50;
/// Commands kept for the report.
pub const LOG_LEN: usize = 32;
/// Longest message (bytes).
const MAX_MESSAGE: usize = 8;
/// The sensitivity command's first byte.
const CMD_SENSITIVITY: u8 = 105;
/// The reset command's bytes.
const CMD_RESET: u8 = 131;

/// `--smart-effector`: where the control input is wired.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SmartEffectorSpec {
    /// The control input (an output pin of this MCU).
    pub control_pin: u8,
    /// The line's logical 1 is a low pin (a `!` control pin).
    pub active_low: bool,
}

/// A decoded command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Command {
    /// Sensitivity programmed.
    Sensitivity(u8),
    /// Back to the factory sensitivity.
    Reset,
}

/// The byte sequence being received.
#[derive(Debug, Clone, Copy)]
struct Frame {
    /// Clock of the current byte's first bit.
    byte_start: f64,
    /// Bits of the current byte so far, first bit in the highest position.
    raw: u16,
    nbits: u32,
    bytes: [u8; MAX_MESSAGE],
    len: usize,
}

/// The effector's programming state.
#[derive(Debug, Clone)]
pub struct SmartEffector {
    pub spec: SmartEffectorSpec,
    bit_ticks: f64,
    /// The line's logical level.
    level: bool,
    frame: Option<Frame>,
    /// The current sensitivity.
    pub sensitivity: u8,
    /// Resets received.
    pub resets: u32,
    /// Messages dropped: off the bit grid, malformed, or unknown.
    pub errors: u32,
    /// The first [`LOG_LEN`] commands decoded.
    log: [Option<Command>; LOG_LEN],
    logged: usize,
}

impl SmartEffector {
    /// An effector at its factory sensitivity on an MCU of `clock_freq` ticks per second.
    pub fn new(spec: SmartEffectorSpec, clock_freq: u32) -> SmartEffector {
        SmartEffector {
            spec,
            bit_ticks: BIT_S * f64::from(clock_freq.max(1)),
            level: false,
            frame: None,
            sensitivity: DEFAULT_SENSITIVITY,
            resets: 0,
            errors: 0,
            log: [None; LOG_LEN],
            logged: 0,
        }
    }

    /// The commands decoded so far (the first [`LOG_LEN`]).
    pub fn commands(&self) -> impl Iterator<Item = Command> + '_ {
        self.log.iter().flatten().copied()
    }

    /// The control pin changed to `pin_level` at `clock`.
    pub fn control(&mut self, pin_level: bool, clock: u64) {
        let level = pin_level != self.spec.active_low;
        if level == self.level {
            return;
        }
        let clock = clock as f64;
        self.advance(clock);
        match self.frame {
            None if level => {
                // The first `1` of a message: its byte started two bits earlier.
                self.frame = Some(Frame {
                    byte_start: clock - 2.0 * self.bit_ticks,
                    raw: 0,
                    nbits: 2,
                    bytes: [0; MAX_MESSAGE],
                    len: 0,
                });
            }
            None => {}
            Some(f) => {
                let bits = (clock - f.byte_start) / self.bit_ticks;
                if (bits - bits.round()).abs() > TIMING_TOLERANCE {
                    self.drop_message();
                }
            }
        }
        self.level = level;
    }

    /// Fills in the bits up to `clock` (the report's end): a message the line went idle after
    /// is taken.
    pub fn finish(&mut self, clock: u64) {
        self.advance(clock as f64);
    }

    /// Takes the level of every bit slot whose middle is before `clock`.
    fn advance(&mut self, clock: f64) {
        while let Some(f) = self.frame {
            let mid = f.byte_start + (f64::from(f.nbits) + 0.5) * self.bit_ticks;
            if mid >= clock {
                return;
            }
            self.push_bit(f, self.level);
        }
    }

    /// One more bit of frame `f`.
    fn push_bit(&mut self, mut f: Frame, bit: bool) {
        f.raw = (f.raw << 1) | u16::from(bit);
        f.nbits += 1;
        self.frame = Some(f);
        match f.nbits {
            // A new byte's `0 0 0`: the message ended (the line idles low).
            3 if f.raw & 0b111 == 0 && f.len > 0 => self.end_message(f),
            // The start pattern is `0 0 1 0`.
            4 if f.raw & 0b1111 != 0b0010 => self.drop_message(),
            BYTE_BITS => self.end_byte(f),
            _ => {}
        }
    }

    /// A complete byte: checked and kept; the next one starts at once.
    fn end_byte(&mut self, mut f: Frame) {
        let r = f.raw;
        let bit = |i: u32| (r >> (BYTE_BITS - 1 - i)) & 1;
        let high = (r >> 6) & 0xf;
        let low = (r >> 1) & 0xf;
        if bit(8) == bit(7) || bit(13) == bit(12) || f.len == MAX_MESSAGE {
            self.drop_message();
            return;
        }
        f.bytes[f.len] = ((high << 4) | low) as u8;
        f.len += 1;
        f.byte_start += f64::from(BYTE_BITS) * self.bit_ticks;
        f.raw = 0;
        f.nbits = 0;
        self.frame = Some(f);
    }

    /// The line went idle after `f`'s bytes: the command they are.
    fn end_message(&mut self, f: Frame) {
        self.frame = None;
        let cmd = match f.bytes[..f.len] {
            [CMD_SENSITIVITY, s, c] if c == 255 - s => Command::Sensitivity(s),
            [CMD_RESET, CMD_RESET] => Command::Reset,
            _ => {
                self.errors += 1;
                return;
            }
        };
        match cmd {
            Command::Sensitivity(s) => self.sensitivity = s,
            Command::Reset => {
                self.sensitivity = DEFAULT_SENSITIVITY;
                self.resets += 1;
            }
        }
        if let Some(slot) = self.log.get_mut(self.logged) {
            *slot = Some(cmd);
            self.logged += 1;
        }
    }

    fn drop_message(&mut self) {
        self.frame = None;
        self.errors += 1;
    }

    /// One line for the simulator's exit report.
    pub fn report(&self) -> String {
        let cmds: Vec<String> = self
            .commands()
            .map(|c| match c {
                Command::Sensitivity(s) => format!("sensitivity {s}"),
                Command::Reset => "reset".to_string(),
            })
            .collect();
        format!(
            "smart effector on pin {}: commands [{}]; sensitivity {}, resets {}, bad messages {}",
            self.spec.control_pin,
            cmds.join(", "),
            self.sensitivity,
            self.resets,
            self.errors
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const F: u32 = 1_000_000;

    /// The line's bits for `bytes`, as the host sends them.
    fn bits(bytes: &[u8]) -> Vec<bool> {
        let mut out = Vec::new();
        for &b in bytes {
            let bit = |i: u8| (b >> i) & 1 == 1;
            out.extend([false, false, true, false, bit(7), bit(6), bit(5), bit(4), !bit(4)]);
            out.extend([bit(3), bit(2), bit(1), bit(0), !bit(0)]);
        }
        out
    }

    /// Sends `line` from `start` µs with bits of `bit_us` µs, as level changes (back to idle
    /// after the last bit); returns the end.
    fn send(e: &mut SmartEffector, start: u64, bit_us: f64, line: &[bool]) -> u64 {
        let mut last = false;
        let at = |k: usize| start + (k as f64 * bit_us).round() as u64;
        for (k, &b) in line.iter().enumerate() {
            if b != last {
                e.control(b != e.spec.active_low, at(k));
                last = b;
            }
        }
        if last {
            e.control(e.spec.active_low, at(line.len()));
        }
        at(line.len() + 1)
    }

    fn effector(active_low: bool) -> SmartEffector {
        SmartEffector::new(
            SmartEffectorSpec {
                control_pin: 7,
                active_low,
            },
            F,
        )
    }

    #[test]
    fn decodes_sensitivity_and_reset() {
        for active_low in [false, true] {
            let mut e = effector(active_low);
            for s in [0u8, 1, 42, 127, 128, 254, 255] {
                let end = send(
                    &mut e,
                    1_000_000 * u64::from(s) + 5000,
                    1000.0,
                    &bits(&[105, s, 255 - s]),
                );
                e.finish(end + 100_000);
                assert_eq!((e.sensitivity, e.errors), (s, 0), "{s}");
            }
            let end = send(&mut e, 900_000_000, 1000.0, &bits(&[131, 131]));
            e.finish(end + 50_000);
            assert_eq!((e.sensitivity, e.resets, e.errors), (DEFAULT_SENSITIVITY, 1, 0));
            assert_eq!(e.commands().count(), 8);
            assert_eq!(e.commands().nth(2), Some(Command::Sensitivity(42)));
        }
    }

    #[test]
    fn a_message_is_taken_when_the_next_one_starts() {
        let mut e = effector(false);
        send(&mut e, 0, 1000.0, &bits(&[105, 42, 213]));
        send(&mut e, 100_000, 1000.0, &bits(&[131, 131]));
        assert_eq!(e.commands().collect::<Vec<_>>(), [Command::Sensitivity(42)]);
        e.finish(200_000);
        assert_eq!(e.resets, 1);
    }

    #[test]
    fn wrong_timing_is_an_error() {
        // 10 % long bits drift off the grid; a single late edge does too.
        let mut e = effector(false);
        let end = send(&mut e, 0, 1100.0, &bits(&[105, 42, 213]));
        e.finish(end + 100_000);
        assert_eq!((e.sensitivity, e.commands().count()), (DEFAULT_SENSITIVITY, 0));
        assert!(e.errors >= 1);
        let mut e = effector(false);
        e.control(true, 2000);
        e.control(false, 3000);
        e.control(true, 5100);
        assert_eq!(e.errors, 1);
        // Half-speed bits decode to other bits: not a command.
        let mut e = effector(false);
        let end = send(&mut e, 0, 2000.0, &bits(&[105, 42, 213]));
        e.finish(end + 100_000);
        assert_eq!(e.sensitivity, DEFAULT_SENSITIVITY);
        assert!(e.errors >= 1);
    }

    #[test]
    fn wrong_bits_are_errors() {
        let good = bits(&[105, 42, 213]);
        for k in 0..good.len() {
            let mut line = good.clone();
            line[k] = !line[k];
            let mut e = effector(false);
            let end = send(&mut e, 10_000, 1000.0, &line);
            e.finish(end + 100_000);
            assert_eq!(e.sensitivity, DEFAULT_SENSITIVITY, "bit {k} flipped");
            assert!(e.errors >= 1, "bit {k} flipped");
        }
        // A wrong check byte, an unknown command.
        let mut e = effector(false);
        let end = send(&mut e, 0, 1000.0, &bits(&[105, 42, 212]));
        let end = send(&mut e, end + 50_000, 1000.0, &bits(&[7]));
        e.finish(end + 50_000);
        assert_eq!((e.sensitivity, e.errors), (DEFAULT_SENSITIVITY, 2));
    }

    #[test]
    fn a_line_left_high_is_an_error() {
        let mut e = effector(false);
        let mut line = bits(&[131, 131]);
        line.extend([true; 20]);
        let mut last = false;
        for (k, &b) in line.iter().enumerate() {
            if b != last {
                e.control(b, 1000 * k as u64);
                last = b;
            }
        }
        e.finish(100_000);
        assert_eq!((e.resets, e.errors), (0, 1));
        assert!(e.report().contains("bad messages 1"));
    }
}
