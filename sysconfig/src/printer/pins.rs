//! Pin descriptions, `[^|~][!][mcu_name:]pin`, and the registry that checks every pin names a
//! declared MCU and is used only once.
//!
//! Prefixes in Klipper's order: `^` (pull-up) or `~` (pull-down) first, then `!` (invert); which
//! of them a pin accepts depends on its use ([`PinKind`]). Without `name:` the pin is on the main
//! `[mcu]`. Stepper enable pins may be shared between steppers (Klipper allows it for boards
//! with one enable line), if every user agrees on `!`; any other reuse is an error.

use std::fmt;

use links::pinmap::{PinFamily, PinName};

use super::board_pins::{Alias, Aliases};
use super::error::ValueProblem;
use super::probe::{PROBE_PIN_MCU, Z_VIRTUAL_ENDSTOP};

/// The main MCU's name: the `[mcu]` section, and pins without a `name:` prefix.
pub const MAIN_MCU: &str = "mcu";

/// A parsed pin description.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct PinRef {
    /// `"mcu"` unless the description was `name:PIN`.
    pub mcu: String,
    pub pin: String,
    /// `!`
    pub invert: bool,
    /// `^`
    pub pullup: bool,
    /// `~`
    pub pulldown: bool,
}

/// What a pin is used for, which decides the prefixes it may carry.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PinKind {
    /// Digital output (step, dir, enable, heater): `!` only.
    Output,
    /// Digital input (endstop): `^` or `~`, and `!`.
    Input,
    /// Analog input (thermistor): no prefixes.
    Analog,
}

impl PinKind {
    fn can_pull(self) -> bool {
        self == PinKind::Input
    }

    fn can_invert(self) -> bool {
        self != PinKind::Analog
    }
}

/// Why a pin description is malformed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PinProblem {
    #[error("empty pin name")]
    Empty,
    #[error("empty mcu name before ':'")]
    EmptyMcu,
    #[error("pull-up '^' / pull-down '~' is not allowed on this pin")]
    PullNotAllowed,
    #[error("inversion '!' is not allowed on this pin")]
    InvertNotAllowed,
    #[error("'^' or '~' must come before '!'")]
    PrefixOrder,
    #[error("'{0}' must not contain whitespace or '^', '~', '!', ':' (format: [^|~][!][mcu_name:]pin)")]
    BadName(String),
}

impl PinRef {
    /// Parses a pin description for a pin used as `kind`.
    pub fn parse(text: &str, kind: PinKind) -> Result<PinRef, PinProblem> {
        let mut rest = text.trim();
        let (mut pullup, mut pulldown, mut invert) = (false, false, false);
        if let Some(r) = rest.strip_prefix('^') {
            pullup = true;
            rest = r.trim_start();
        } else if let Some(r) = rest.strip_prefix('~') {
            pulldown = true;
            rest = r.trim_start();
        }
        if (pullup || pulldown) && !kind.can_pull() {
            return Err(PinProblem::PullNotAllowed);
        }
        if let Some(r) = rest.strip_prefix('!') {
            if !kind.can_invert() {
                return Err(PinProblem::InvertNotAllowed);
            }
            invert = true;
            rest = r.trim_start();
        }
        if invert && rest.starts_with(['^', '~']) {
            return Err(PinProblem::PrefixOrder);
        }
        let (mcu, pin) = match rest.split_once(':') {
            Some((mcu, pin)) => (mcu.trim(), pin.trim()),
            None => (MAIN_MCU, rest),
        };
        if mcu.is_empty() {
            return Err(PinProblem::EmptyMcu);
        }
        if pin.is_empty() {
            return Err(PinProblem::Empty);
        }
        for name in [mcu, pin] {
            if name
                .chars()
                .any(|c| c.is_whitespace() || matches!(c, '^' | '~' | '!' | ':'))
            {
                return Err(PinProblem::BadName(name.to_string()));
            }
        }
        Ok(PinRef {
            mcu: mcu.to_string(),
            pin: pin.to_string(),
            invert,
            pullup,
            pulldown,
        })
    }

    /// True when the pin is on the main `[mcu]`.
    pub fn on_main_mcu(&self) -> bool {
        self.mcu == MAIN_MCU
    }
}

/// The canonical description: `^!PA0`, `~ebb:PB3` (no `mcu:` for the main MCU).
impl fmt::Display for PinRef {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let pull = if self.pullup {
            "^"
        } else if self.pulldown {
            "~"
        } else {
            ""
        };
        let invert = if self.invert { "!" } else { "" };
        if self.on_main_mcu() {
            write!(f, "{pull}{invert}{}", self.pin)
        } else {
            write!(f, "{pull}{invert}{}:{}", self.mcu, self.pin)
        }
    }
}

/// Whether a pin may be shared with other users.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Share {
    Exclusive,
    /// Stepper enable lines: shareable among themselves with the same `!`.
    StepperEnable,
    /// A TMC UART line: shared by the drivers on it (each with its own address).
    TmcUart,
    /// Software SPI clock/data lines: shared by the devices on that bus.
    SpiBus,
    /// The chip select of a TMC SPI daisy chain: shared by the drivers of the chain.
    SpiChain,
}

#[derive(Debug)]
struct Claim {
    pin: PinRef,
    section: String,
    option: String,
    share: Share,
}

/// Every pin used so far, and the declared MCUs they may name.
#[derive(Debug)]
pub(crate) struct PinRegistry {
    mcus: Vec<String>,
    /// MCUs with `serial: simulator`, whose pins must be ones the simulator has.
    simulated: Vec<String>,
    /// A `[probe]` was read: `probe:z_virtual_endstop` exists.
    probe: bool,
    /// The TMC drivers' virtual endstop chips (`tmc2209_stepper_x`).
    tmc_chips: Vec<String>,
    claims: Vec<Claim>,
    /// Per simulated MCU: the pin family its first pin chose, and that pin's use.
    families: Vec<(String, PinFamily, String)>,
    /// Pin providers of ignored sections (`[adc_scaled NAME]`, `[sx1509 NAME]`, `[replicape]`):
    /// chip name and section name.
    unsupported_chips: Vec<(String, String)>,
    /// `[board_pins]` aliases.
    aliases: Aliases,
    /// `[adc_scaled NAME]` chips and the MCU whose pins they scale.
    scaled_chips: Vec<(String, String)>,
    /// `[multi_pin NAME]` groups.
    multi_pins: Vec<(String, Vec<PinRef>)>,
}

/// True when the simulated MCU has `pin` (any family of [`links::pinmap`]: `PA0`, `PF13`,
/// `P1.22`, `gpio17`, `gpio1_23`).
pub fn is_simulator_pin(pin: &str) -> bool {
    PinName::parse(pin).is_some()
}

/// The families the simulated MCU's pins may be named in, for errors.
const SIMULATOR_FAMILIES: &str = "AVR/STM32/SAM style PA0..PL15 and PA16..PD31, LPC176x style \
    P0.0..P4.31, RP2040 style gpio0..gpio63, BeagleBone style gpio0_0..gpio3_31 or Linux MCU style \
    gpiochip0/gpio0..gpiochip6/gpio31 and analog0..analog31";

impl PinRegistry {
    pub(crate) fn new(mcus: Vec<String>) -> Self {
        PinRegistry {
            mcus,
            simulated: Vec::new(),
            probe: false,
            tmc_chips: Vec::new(),
            claims: Vec::new(),
            families: Vec::new(),
            unsupported_chips: Vec::new(),
            aliases: Aliases::new(),
            scaled_chips: Vec::new(),
            multi_pins: Vec::new(),
        }
    }

    /// Declares `[adc_scaled chip]`, whose pins are `mcu`'s.
    pub(crate) fn add_scaled_chip(&mut self, chip: &str, mcu: &str) {
        self.scaled_chips.push((chip.to_string(), mcu.to_string()));
    }

    /// Declares `[multi_pin name]` with its pins.
    pub(crate) fn add_multi_pin(&mut self, name: &str, group: Vec<PinRef>) {
        self.multi_pins.push((name.to_string(), group));
    }

    /// The MCU whose pins `[adc_scaled chip]` scales, if `chip` is one.
    pub(crate) fn scaled_mcu(&self, chip: &str) -> Option<&str> {
        self.scaled_chips
            .iter()
            .find(|(c, _)| c == chip)
            .map(|(_, m)| m.as_str())
    }

    /// True when `name` is a declared MCU.
    pub(crate) fn has_mcu(&self, name: &str) -> bool {
        self.mcus.iter().any(|m| m == name)
    }

    /// Marks `names` as simulated MCUs.
    pub(crate) fn with_simulated(mut self, names: Vec<String>) -> Self {
        self.simulated = names;
        self
    }

    /// Declares the `[board_pins]` aliases pins are resolved through.
    pub(crate) fn with_aliases(mut self, aliases: Aliases) -> Self {
        self.aliases = aliases;
        self
    }

    /// `pin` with a `[board_pins]` alias replaced by the MCU's pin name; a reserved alias
    /// (`<GND>`) is an error.
    pub(crate) fn resolve(&self, mut pin: PinRef) -> Result<PinRef, ValueProblem> {
        match self.aliases.get(&(pin.mcu.clone(), pin.pin.clone())) {
            None => Ok(pin),
            Some(Alias::Pin(real)) => {
                pin.pin = real.clone();
                Ok(pin)
            }
            Some(Alias::Reserved(what)) => Err(ValueProblem::Invalid(format!(
                "pin '{pin}' is the board's reserved <{what}>, not a pin"
            ))),
        }
    }

    /// Declares the pin providers (chip name, section) whose pins Cadence does not drive.
    pub(crate) fn with_unsupported_chips(mut self, chips: Vec<(String, String)>) -> Self {
        self.unsupported_chips = chips;
        self
    }

    /// Declares the TMC drivers' virtual endstop chips (`tmc2209_stepper_x`).
    pub(crate) fn set_tmc_chips(&mut self, chips: Vec<String>) {
        self.tmc_chips = chips;
    }

    /// `tmc2209_stepper_x:virtual_endstop` (Klipper's rules): only `virtual_endstop`, only as
    /// an endstop, without `^`, `~` or `!` (the driver's diag pin carries those). Not a claim:
    /// the diag pin is claimed by the driver's section.
    fn check_tmc_pin(pin: &PinRef, option: &str) -> Result<(), ValueProblem> {
        let invalid = |why: &str| Err(ValueProblem::Invalid(format!("pin '{pin}': {why}")));
        if pin.pin != "virtual_endstop" || option != "endstop_pin" {
            return invalid("tmc virtual endstop only useful as endstop");
        }
        if pin.invert || pin.pullup || pin.pulldown {
            return invalid("Can not pullup/invert tmc virtual pin (set them on the driver's diag pin)");
        }
        Ok(())
    }

    /// Declares that a `[probe]` exists: its virtual endstop `probe:z_virtual_endstop` may be
    /// `[stepper_z] endstop_pin`.
    pub(crate) fn set_probe(&mut self) {
        self.probe = true;
    }

    /// `probe:z_virtual_endstop` (Klipper's rules): only with a `[probe]`, only as the endstop
    /// of Z, without `^`, `~` or `!` (the probe's own pin carries those). Not a claim: the
    /// probe's pin was claimed by `[probe]`.
    fn check_probe_pin(&self, pin: &PinRef, section: &str, option: &str) -> Result<(), ValueProblem> {
        let invalid = |why: String| Err(ValueProblem::Invalid(format!("pin '{pin}': {why}")));
        if matches!(section, "probe" | "bltouch") {
            return Err(ValueProblem::Invalid(format!(
                "pin '{pin}' is the probe's own virtual endstop (only for [stepper_z] endstop_pin)"
            )));
        }
        if !self.probe {
            return invalid("there is no [probe] section".into());
        }
        if pin.pin != Z_VIRTUAL_ENDSTOP {
            return invalid(format!(
                "the probe only provides '{PROBE_PIN_MCU}:{Z_VIRTUAL_ENDSTOP}'"
            ));
        }
        if option != "endstop_pin" || section != "stepper_z" {
            return invalid("the probe virtual endstop can only be [stepper_z] endstop_pin".into());
        }
        if pin.invert || pin.pullup || pin.pulldown {
            return invalid(
                "can not pull up, pull down or invert the probe virtual endstop (set them on [probe] pin)"
                    .into(),
            );
        }
        Ok(())
    }

    /// A simulated MCU's pin must be one of its names, in the one family its first pin chose
    /// (the families' numbers overlap, see [`links::pinmap`]).
    fn check_simulator_pin(&mut self, pin: &PinRef, section: &str, option: &str) -> Result<(), ValueProblem> {
        let Some(name) = PinName::parse(&pin.pin) else {
            return Err(ValueProblem::Invalid(format!(
                "pin '{pin}': the simulated mcu '{}' has no such pin (its pins are named {SIMULATOR_FAMILIES}); \
                 for a real board's pins, batch mode takes that board's data dictionary with --dictionary",
                pin.mcu
            )));
        };
        match self.families.iter().find(|(mcu, _, _)| *mcu == pin.mcu) {
            Some((_, family, first)) if *family != name.family => Err(ValueProblem::Invalid(format!(
                "pin '{pin}' is named {} but the simulated mcu '{}' already uses {} names ({first}); \
                 one MCU's pins are named one way",
                name.family.describe(),
                pin.mcu,
                family.describe()
            ))),
            Some(_) => Ok(()),
            None => {
                let first = format!("[{section}] {option}: {}", pin.pin);
                self.families.push((pin.mcu.clone(), name.family, first));
                Ok(())
            }
        }
    }

    /// Records `pin` as used by `[section] option`, or says why it may not be.
    pub(crate) fn claim(
        &mut self,
        pin: &PinRef,
        section: &str,
        option: &str,
        share: Share,
    ) -> Result<(), ValueProblem> {
        if pin.mcu == PROBE_PIN_MCU {
            return self.check_probe_pin(pin, section, option);
        }
        if self.tmc_chips.contains(&pin.mcu) {
            return Self::check_tmc_pin(pin, option);
        }
        if pin.mcu == super::multi_pin::MULTI_PIN_CHIP {
            // `multi_pin:NAME` claims each pin of `[multi_pin NAME]`.
            let Some((_, group)) = self.multi_pins.iter().find(|(n, _)| *n == pin.pin).cloned() else {
                return Err(ValueProblem::Invalid(format!(
                    "pin '{pin}': there is no [multi_pin {}] section",
                    pin.pin
                )));
            };
            for member in &group {
                self.claim(member, section, option, share)?;
            }
            return Ok(());
        }
        if let Some(mcu) = self.scaled_mcu(&pin.mcu) {
            // `NAME:PIN` of `[adc_scaled NAME]` is PIN of its MCU.
            let real = PinRef {
                mcu: mcu.to_string(),
                ..pin.clone()
            };
            return self.claim(&real, section, option, share);
        }
        if !self.mcus.contains(&pin.mcu) {
            if pin.pin == "virtual_endstop" && pin.mcu.starts_with("tmc") {
                return Err(ValueProblem::Invalid(format!(
                    "pin '{pin}': there is no [{}] section for this virtual endstop",
                    pin.mcu.replacen('_', " ", 1)
                )));
            }
            let unsupported = self.unsupported_chips.iter().find(|(chip, _)| *chip == pin.mcu);
            if let Some((_, section)) = unsupported {
                return Err(ValueProblem::Invalid(format!(
                    "pin '{pin}' is on [{section}], whose pins Cadence does not support yet"
                )));
            }
            return Err(ValueProblem::UnknownMcu {
                pin: pin.to_string(),
                mcu: pin.mcu.clone(),
            });
        }
        if self.simulated.contains(&pin.mcu) {
            self.check_simulator_pin(pin, section, option)?;
        }
        let earlier = self
            .claims
            .iter()
            .find(|c| c.pin.mcu == pin.mcu && c.pin.pin == pin.pin);
        if let Some(c) = earlier {
            let (section, option) = (c.section.clone(), c.option.clone());
            if share != c.share || share == Share::Exclusive {
                return Err(ValueProblem::PinInUse {
                    pin: pin.to_string(),
                    section,
                    option,
                });
            }
            if c.pin.invert != pin.invert {
                return Err(ValueProblem::SharedPinPolarity {
                    pin: pin.to_string(),
                    section,
                    option,
                });
            }
            return Ok(());
        }
        self.claims.push(Claim {
            pin: pin.clone(),
            section: section.to_string(),
            option: option.to_string(),
            share,
        });
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn pin(mcu: &str, name: &str, invert: bool, pullup: bool, pulldown: bool) -> PinRef {
        PinRef {
            mcu: mcu.into(),
            pin: name.into(),
            invert,
            pullup,
            pulldown,
        }
    }

    #[test]
    fn parses_prefixes_and_mcu_names() {
        let cases = [
            ("PA0", PinKind::Output, pin("mcu", "PA0", false, false, false)),
            (" !PD7 ", PinKind::Output, pin("mcu", "PD7", true, false, false)),
            ("^PE5", PinKind::Input, pin("mcu", "PE5", false, true, false)),
            ("~!ebb: PB3", PinKind::Input, pin("ebb", "PB3", true, false, true)),
            ("^ ! PE5", PinKind::Input, pin("mcu", "PE5", true, true, false)),
            (
                "rpi:gpio17",
                PinKind::Output,
                pin("rpi", "gpio17", false, false, false),
            ),
            ("P1.22", PinKind::Analog, pin("mcu", "P1.22", false, false, false)),
        ];
        for (text, kind, want) in cases {
            assert_eq!(PinRef::parse(text, kind), Ok(want), "{text}");
        }
    }

    #[test]
    fn rejects_bad_descriptions() {
        let cases = [
            ("", PinKind::Output, PinProblem::Empty),
            ("!", PinKind::Output, PinProblem::Empty),
            (":PA0", PinKind::Output, PinProblem::EmptyMcu),
            ("ebb:", PinKind::Output, PinProblem::Empty),
            ("^PA0", PinKind::Output, PinProblem::PullNotAllowed),
            ("~PA0", PinKind::Analog, PinProblem::PullNotAllowed),
            ("!PA0", PinKind::Analog, PinProblem::InvertNotAllowed),
            ("!^PA0", PinKind::Input, PinProblem::PrefixOrder),
            ("^^PA0", PinKind::Input, PinProblem::BadName("^PA0".into())),
            ("PA 0", PinKind::Output, PinProblem::BadName("PA 0".into())),
            ("a:b:c", PinKind::Output, PinProblem::BadName("b:c".into())),
        ];
        for (text, kind, want) in cases {
            assert_eq!(PinRef::parse(text, kind), Err(want), "{text}");
        }
        assert_eq!(
            PinProblem::BadName("PA 0".into()).to_string(),
            "'PA 0' must not contain whitespace or '^', '~', '!', ':' (format: [^|~][!][mcu_name:]pin)"
        );
    }

    #[test]
    fn display_is_canonical() {
        assert_eq!(pin("mcu", "PA0", true, true, false).to_string(), "^!PA0");
        assert_eq!(pin("ebb", "PB3", false, false, true).to_string(), "~ebb:PB3");
    }

    #[test]
    fn registry_checks_mcus_and_reuse() {
        let mut reg = PinRegistry::new(vec!["mcu".into(), "ebb".into()]);
        let p = |t: &str| PinRef::parse(t, PinKind::Input).unwrap_or_else(|e| panic!("{t}: {e}"));
        assert_eq!(
            reg.claim(&p("PA0"), "stepper_x", "step_pin", Share::Exclusive),
            Ok(())
        );
        assert_eq!(
            reg.claim(&p("ebb:PA0"), "extruder", "step_pin", Share::Exclusive),
            Ok(())
        );
        assert_eq!(
            reg.claim(&p("!PA0"), "stepper_y", "dir_pin", Share::Exclusive),
            Err(ValueProblem::PinInUse {
                pin: "!PA0".into(),
                section: "stepper_x".into(),
                option: "step_pin".into()
            })
        );
        assert_eq!(
            reg.claim(&p("other:PA1"), "stepper_y", "dir_pin", Share::Exclusive),
            Err(ValueProblem::UnknownMcu {
                pin: "other:PA1".into(),
                mcu: "other".into()
            })
        );
        let z_probe = |reg: &mut PinRegistry, t: &str, section: &str| {
            reg.claim(&p(t), section, "endstop_pin", Share::Exclusive)
                .map_err(|e| e.to_string())
        };
        assert_eq!(
            z_probe(&mut reg, "probe:z_virtual_endstop", "stepper_z"),
            Err("pin 'probe:z_virtual_endstop': there is no [probe] section".into())
        );
        reg.set_probe();
        assert_eq!(z_probe(&mut reg, "probe:z_virtual_endstop", "stepper_z"), Ok(()));
        assert_eq!(
            z_probe(&mut reg, "probe:z_virtual_endstop", "stepper_x"),
            Err("pin 'probe:z_virtual_endstop': the probe virtual endstop can only be [stepper_z] endstop_pin".into())
        );
        assert_eq!(
            z_probe(&mut reg, "probe:x_virtual_endstop", "stepper_z"),
            Err("pin 'probe:x_virtual_endstop': the probe only provides 'probe:z_virtual_endstop'".into())
        );
        assert!(
            z_probe(&mut reg, "^probe:z_virtual_endstop", "stepper_z").is_err_and(|e| e.contains("pull up"))
        );
        assert!(z_probe(&mut reg, "!probe:z_virtual_endstop", "stepper_z").is_err());
        // Shared enable lines.
        assert_eq!(
            reg.claim(&p("!PC3"), "stepper_x", "enable_pin", Share::StepperEnable),
            Ok(())
        );
        assert_eq!(
            reg.claim(&p("!PC3"), "stepper_y", "enable_pin", Share::StepperEnable),
            Ok(())
        );
        assert!(matches!(
            reg.claim(&p("PC3"), "stepper_z", "enable_pin", Share::StepperEnable),
            Err(ValueProblem::SharedPinPolarity { .. })
        ));
        assert!(matches!(
            reg.claim(&p("PC3"), "heater_bed", "heater_pin", Share::Exclusive),
            Err(ValueProblem::PinInUse { .. })
        ));
    }

    #[test]
    fn simulated_mcus_take_every_family_one_at_a_time() {
        for ok in [
            "PA0", "PL7", "PE5", "PA8", "PF13", "PD31", "P1.22", "gpio29", "gpio1_23",
        ] {
            assert!(is_simulator_pin(ok), "{ok}");
        }
        assert!(!is_simulator_pin("PM0") && !is_simulator_pin("pa0") && !is_simulator_pin("PE16"));
        let mut reg = PinRegistry::new(vec!["mcu".into(), "other".into()])
            .with_simulated(vec!["mcu".into(), "other".into()]);
        let p = |t: &str| PinRef::parse(t, PinKind::Output).unwrap_or_else(|e| panic!("{t}: {e}"));
        assert_eq!(reg.claim(&p("PL7"), "s", "a", Share::Exclusive), Ok(()));
        assert_eq!(reg.claim(&p("!PA9"), "s", "b", Share::Exclusive), Ok(()));
        let Err(ValueProblem::Invalid(why)) = reg.claim(&p("!PM9"), "s", "c", Share::Exclusive) else {
            panic!("PM9 accepted")
        };
        assert!(
            why.starts_with("pin '!PM9': the simulated mcu 'mcu' has no such pin"),
            "{why}"
        );
        assert!(
            why.contains("P0.0..P4.31") && why.contains("--dictionary"),
            "{why}"
        );
        assert_eq!(
            reg.claim(&p("P1.2"), "s", "d", Share::Exclusive),
            Err(ValueProblem::Invalid(
                "pin 'P1.2' is named LPC176x style (P0.0..P4.31) but the simulated mcu 'mcu' already \
                 uses AVR/STM32/SAM style (PA0..PL15, PA16..PD31) names ([s] a: PL7); one MCU's pins \
                 are named one way"
                    .into()
            ))
        );
        // Another MCU chooses its own family.
        assert_eq!(reg.claim(&p("other:gpio3"), "s", "e", Share::Exclusive), Ok(()));
    }

    proptest! {
        #[test]
        fn parse_never_panics_and_display_round_trips(text in "[ ^~!:A-Za-z0-9_.]{0,12}") {
            for kind in [PinKind::Output, PinKind::Input, PinKind::Analog] {
                if let Ok(p) = PinRef::parse(&text, kind) {
                    prop_assert_eq!(PinRef::parse(&p.to_string(), kind), Ok(p));
                }
            }
        }
    }
}
