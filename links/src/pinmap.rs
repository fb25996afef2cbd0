//! The simulated MCU's pin names: one table that the firmware's data dictionary, the simulator's
//! command line and printer.cfg validation all read, so a pin accepted by one is accepted by all.
//!
//! Printer boards name pins the way their MCU family does, and a printer.cfg written for a board
//! should run on the simulated MCU with only `serial:` changed. The simulated MCU therefore
//! answers to every common family's names:
//!
//! | family | names | numbers |
//! |---|---|---|
//! | ports (AVR, STM32, SAM) | `PA0`..`PL7` | `port·8 + n` (0..96, unchanged since the first dictionary) |
//! | | `PA8`..`PL15` | `96 + port·8 + (n − 8)` (96..192) |
//! | | `PA16`..`PD31` (SAM) | `192 + port·16 + (n − 16)` (192..256) |
//! | LPC176x | `P0.0`..`P4.31` | `port·32 + n` |
//! | RP2040, Raspberry Pi | `gpio0`..`gpio63` | `n` |
//! | AM335x (BeagleBone) | `gpio0_0`..`gpio3_31` | `bank·32 + n` |
//! | Linux host MCU | `gpiochip0/gpio0`..`gpiochip6/gpio31` | `chip·32 + n` |
//! | | `analog0`..`analog31` | `224 + n` |
//!
//! The wire carries pins as `%c` (one byte), as Klipper's `config_stepper` does, so every name
//! must map below 256 and the families overlap: `PA0`, `P0.0`, `gpio0` and `gpio0_0` are the same
//! pin 0. A real chip has one family; printer.cfg validation keeps one family per simulated MCU
//! ([`PinFamily`] of the first pin used), so overlapping numbers never meet in one config.
//!
//! No allocation, no panic: shared with the `no_std` firmware.

use core::fmt;

/// The naming scheme of a pin (the MCU family that names its pins this way).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PinFamily {
    /// `PA0`, `PC13`, `PB31`: AVR, STM32, SAM (port letter and bit).
    Port,
    /// `P1.22`: NXP LPC176x (port number and bit).
    Lpc,
    /// `gpio17`: RP2040 and other single-bank GPIO numbering.
    Gpio,
    /// `gpio1_23`: banked GPIO (AM335x / BeagleBone).
    GpioBank,
    /// `gpiochip0/gpio20` and `analog4`: Klipper's Linux-process MCU.
    Linux,
}

impl PinFamily {
    /// How users know the family, for error messages.
    pub const fn describe(self) -> &'static str {
        match self {
            PinFamily::Port => "AVR/STM32/SAM style (PA0..PL15, PA16..PD31)",
            PinFamily::Lpc => "LPC176x style (P0.0..P4.31)",
            PinFamily::Gpio => "RP2040 style (gpio0..gpio63)",
            PinFamily::GpioBank => "BeagleBone style (gpio0_0..gpio3_31)",
            PinFamily::Linux => "Linux MCU style (gpiochip0/gpio0..gpiochip6/gpio31, analog0..analog31)",
        }
    }
}

/// A pin name split into its parts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct PinName {
    /// The naming scheme.
    pub family: PinFamily,
    /// Port index (`A` = 0) or LPC port or GPIO bank or gpiochip; 0 for [`PinFamily::Gpio`];
    /// [`ANALOG_PORT`] for the Linux MCU's `analogN`.
    pub port: u8,
    /// Bit within the port (or the GPIO number).
    pub index: u8,
}

/// Port letters of the `P<letter><n>` family.
pub const PORT_LETTERS: &[u8] = b"ABCDEFGHIJKL";
/// Ports with bits 16..31 (SAM's `PA16`..`PD31`).
const WIDE_PORTS: u8 = 4;
/// LPC176x ports `P0`..`P4`.
const LPC_PORTS: u8 = 5;
/// Banks `gpio0_`..`gpio3_`.
const GPIO_BANKS: u8 = 4;
/// `gpio0`..`gpio63`.
const GPIO_PINS: u8 = 64;
/// `gpiochip0/`..`gpiochip6/`.
const GPIO_CHIPS: u8 = 7;
/// The [`PinName::port`] of the Linux MCU's `analogN` pins.
pub const ANALOG_PORT: u8 = 255;

impl PinName {
    /// Parses `name` as one of the families' names (case-sensitive, as the dictionary's
    /// symbols are). `None` when it is not a pin name of any family or is out of the table.
    pub fn parse(name: &str) -> Option<PinName> {
        let b = name.as_bytes();
        let pin = if let Some(rest) = name.strip_prefix("gpiochip") {
            let (chip, n) = rest.split_once("/gpio")?;
            PinName {
                family: PinFamily::Linux,
                port: small_number(chip)?,
                index: small_number(n)?,
            }
        } else if let Some(n) = name.strip_prefix("analog") {
            PinName {
                family: PinFamily::Linux,
                port: ANALOG_PORT,
                index: small_number(n)?,
            }
        } else if let Some(rest) = name.strip_prefix("gpio") {
            match rest.split_once('_') {
                Some((bank, n)) => PinName {
                    family: PinFamily::GpioBank,
                    port: small_number(bank)?,
                    index: small_number(n)?,
                },
                None => PinName {
                    family: PinFamily::Gpio,
                    port: 0,
                    index: small_number(rest)?,
                },
            }
        } else if b.first() == Some(&b'P') && b.get(1).is_some_and(u8::is_ascii_digit) {
            let (port, n) = name[1..].split_once('.')?;
            PinName {
                family: PinFamily::Lpc,
                port: small_number(port)?,
                index: small_number(n)?,
            }
        } else if b.first() == Some(&b'P') && b.len() >= 3 {
            let port = PORT_LETTERS.iter().position(|&l| l == b[1])?;
            PinName {
                family: PinFamily::Port,
                port: port as u8,
                index: small_number(&name[2..])?,
            }
        } else {
            return None;
        };
        pin.number().map(|_| pin)
    }

    /// The pin's number in the simulated MCU's dictionary, `None` beyond the table.
    pub const fn number(self) -> Option<u8> {
        let (port, n) = (self.port as u16, self.index as u16);
        let number = match self.family {
            PinFamily::Port if self.port as usize >= PORT_LETTERS.len() => return None,
            PinFamily::Port if n < 8 => port * 8 + n,
            PinFamily::Port if n < 16 => 96 + port * 8 + (n - 8),
            PinFamily::Port if n < 32 && self.port < WIDE_PORTS => 192 + port * 16 + (n - 16),
            PinFamily::Lpc if self.port < LPC_PORTS && n < 32 => port * 32 + n,
            PinFamily::Gpio if self.index < GPIO_PINS => n,
            PinFamily::GpioBank if self.port < GPIO_BANKS && n < 32 => port * 32 + n,
            PinFamily::Linux if self.port == ANALOG_PORT && n < 32 => 224 + n,
            PinFamily::Linux if self.port < GPIO_CHIPS && n < 32 => port * 32 + n,
            _ => return None,
        };
        if number < 256 {
            Some(number as u8)
        } else {
            None
        }
    }
}

impl fmt::Display for PinName {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.family {
            PinFamily::Port => {
                let letter = PORT_LETTERS.get(self.port as usize).copied().unwrap_or(b'?');
                write!(f, "P{}{}", letter as char, self.index)
            }
            PinFamily::Lpc => write!(f, "P{}.{}", self.port, self.index),
            PinFamily::Gpio => write!(f, "gpio{}", self.index),
            PinFamily::GpioBank => write!(f, "gpio{}_{}", self.port, self.index),
            PinFamily::Linux if self.port == ANALOG_PORT => write!(f, "analog{}", self.index),
            PinFamily::Linux => write!(f, "gpiochip{}/gpio{}", self.port, self.index),
        }
    }
}

/// A decimal number below 256 without sign, spaces or leading zeros (`"07"` is not `7`).
fn small_number(s: &str) -> Option<u8> {
    let ok = !s.is_empty() && s.bytes().all(|c| c.is_ascii_digit()) && (s == "0" || !s.starts_with('0'));
    if ok {
        s.parse().ok()
    } else {
        None
    }
}

/// The number of a simulated-MCU pin name, `None` if no family names it.
pub fn pin_number(name: &str) -> Option<u8> {
    PinName::parse(name).and_then(PinName::number)
}

/// One run of the dictionary's `pin` enumeration: `first` names pin `value`, and the next
/// `count − 1` names (the trailing number counting up) the following pins.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PinRun {
    /// The run's first name.
    pub first: PinName,
    /// Its pin number.
    pub value: u8,
    /// Names in the run.
    pub count: u8,
}

/// Every run of the simulated MCU's `pin` enumeration, in a fixed order (the dictionary's).
pub fn pin_runs() -> impl Iterator<Item = PinRun> {
    let run = |family, port: u8, index: u8, count: u8| {
        let first = PinName { family, port, index };
        first.number().map(|value| PinRun { first, value, count })
    };
    let ports = 0..PORT_LETTERS.len() as u8;
    let low = ports.clone().filter_map(move |p| run(PinFamily::Port, p, 0, 8));
    let high = ports.filter_map(move |p| run(PinFamily::Port, p, 8, 8));
    let wide = (0..WIDE_PORTS).filter_map(move |p| run(PinFamily::Port, p, 16, 16));
    let lpc = (0..LPC_PORTS).filter_map(move |p| run(PinFamily::Lpc, p, 0, 32));
    let gpio = run(PinFamily::Gpio, 0, 0, GPIO_PINS);
    let banks = (0..GPIO_BANKS).filter_map(move |b| run(PinFamily::GpioBank, b, 0, 32));
    let chips = (0..GPIO_CHIPS).filter_map(move |c| run(PinFamily::Linux, c, 0, 32));
    let analog = run(PinFamily::Linux, ANALOG_PORT, 0, 32);
    low.chain(high)
        .chain(wide)
        .chain(lpc)
        .chain(gpio)
        .chain(banks)
        .chain(chips)
        .chain(analog)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn first_dictionary_numbers_are_unchanged() {
        assert_eq!(pin_number("PA0"), Some(0));
        assert_eq!(pin_number("PB3"), Some(11));
        assert_eq!(pin_number("PL7"), Some(95));
    }

    #[test]
    fn families() {
        assert_eq!(pin_number("PA8"), Some(96));
        assert_eq!(pin_number("PA15"), Some(103));
        assert_eq!(pin_number("PL15"), Some(191));
        assert_eq!(pin_number("PA16"), Some(192));
        assert_eq!(pin_number("PD31"), Some(255));
        assert_eq!(pin_number("P0.0"), Some(0));
        assert_eq!(pin_number("P4.31"), Some(159));
        assert_eq!(pin_number("gpio29"), Some(29));
        assert_eq!(pin_number("gpio1_23"), Some(55));
        assert_eq!(pin_number("gpiochip0/gpio20"), Some(20));
        assert_eq!(pin_number("gpiochip6/gpio31"), Some(223));
        assert_eq!(pin_number("analog4"), Some(228));
        for bad in [
            "PE16",
            "PM0",
            "P5.0",
            "P1.32",
            "gpio64",
            "gpio4_0",
            "pa0",
            "PA",
            "P1.",
            "gpio",
            "PA07",
            "PA-1",
            " PA0",
            "PA0 ",
            "P1.2.3",
            "gpio1_2_3",
            "gpiochip7/gpio0",
            "gpiochip0/gpio32",
            "analog32",
            "gpiochip0gpio1",
            "",
        ] {
            assert_eq!(pin_number(bad), None, "{bad}");
        }
    }

    #[test]
    fn runs_expand_to_the_table() {
        // Expanding every run as a dictionary reader does (trailing number counts up) gives
        // exactly the names `pin_number` accepts, with the same numbers.
        let mut names = 0;
        for run in pin_runs() {
            let first = run.first.to_string();
            let root = first.trim_end_matches(|c: char| c.is_ascii_digit());
            let start: u32 = first[root.len()..].parse().unwrap();
            for i in 0..run.count as u32 {
                let name = format!("{root}{}", start + i);
                assert_eq!(pin_number(&name), Some(run.value + i as u8), "{name}");
                names += 1;
            }
        }
        assert_eq!(names, 96 + 96 + 64 + 160 + 64 + 128 + 224 + 32);
    }

    proptest! {
        #[test]
        fn display_parse_round_trip(s in "(P[A-Z][0-9]{1,2}|P[0-9]\\.[0-9]{1,2}|gpio[0-9]{1,2}(_[0-9]{1,2})?|gpiochip[0-9]/gpio[0-9]{1,2}|analog[0-9]{1,2}|.{0,8})") {
            if let Some(pin) = PinName::parse(&s) {
                prop_assert_eq!(pin.to_string(), s);
            }
        }
    }
}
