//! `[tmc2130 NAME]`, `[tmc2208 NAME]`, `[tmc2209 NAME]`, `[tmc2240 NAME]`, `[tmc5160 NAME]`: a TMC driver of the
//! stepper `NAME`, Klipper's options, and the register values the host writes at start.
//!
//! The registers are built in Klipper's order (the order each is first set is the order it is
//! written in): UART set-up bits (`pdn_disable`, `senddelay`), the current (see [`current`]),
//! the microstep resolution of the stepper's `microsteps` (`mres = log2(256 / microsteps)`) and
//! `interpolate`, the SPI drivers' wave table, the stealthChop threshold (`TPWMTHRS`, with
//! `en_pwm_mode` / `en_spreadcycle`), `coolstep_threshold` (`TCOOLTHRS`),
//! `high_velocity_threshold` (`THIGH`), then every tuning field with its `driver_*` option or
//! default. A velocity threshold `v` (mm/s) becomes the driver's TSTEP units:
//! `⌊f_clk · step_dist / 2^mres / v + ½⌋` (0xfffff for 0).
//!
//! The driver's `diag_pin` (`diag0_pin`/`diag1_pin` on SPI drivers) is the input of the
//! virtual endstop `tmcXXXX_NAME:virtual_endstop` (sensorless homing); it is claimed only when
//! a stepper homes on it.

pub mod current;
pub mod model;
pub mod tables;
pub mod tables_2240;
pub mod tables_2660;

use super::error::{ConfigError, ValueProblem};
use super::pins::{PinKind, PinRef, PinRegistry, Share};
use super::reader::{Bounds, SectionReader};
use super::stepper::MotorSection;
pub use model::{FieldError, FieldSet, TmcModel, MODELS};

/// How the host reaches the driver.
#[derive(Debug, Clone, PartialEq)]
pub enum TmcBus {
    /// Single-wire UART bit-banged by the MCU (`uart_pin`, optional separate `tx_pin`).
    Uart {
        uart_pin: PinRef,
        tx_pin: Option<PinRef>,
        address: u8,
        /// `select_pins`: the line reaches this driver through an analog mux while each pin is
        /// at its level (high; low when written `!PIN`), as on Duet boards. Empty without a mux.
        select_pins: Vec<PinRef>,
    },
    /// SPI (`cs_pin`), hardware bus `spi_bus` or software pins.
    Spi {
        cs_pin: PinRef,
        speed: u32,
        bus: Option<String>,
        /// `spi_software_sclk_pin`, `spi_software_mosi_pin`, `spi_software_miso_pin`.
        software: Option<[PinRef; 3]>,
        /// A daisy chain on `cs_pin`: `chain_length` and this driver's `chain_position`
        /// (1..=length).
        chain: Option<(u8, u8)>,
    },
}

impl TmcBus {
    /// The MCU the driver's bus is on.
    pub fn mcu(&self) -> &str {
        match self {
            TmcBus::Uart { uart_pin, .. } => &uart_pin.mcu,
            TmcBus::Spi { cs_pin, .. } => &cs_pin.mcu,
        }
    }
}

/// One `[tmcXXXX NAME]` section.
#[derive(Debug, Clone, PartialEq)]
pub struct TmcSection {
    pub model: TmcModel,
    /// The stepper it drives (`stepper_x`, `extruder`).
    pub stepper: String,
    pub bus: TmcBus,
    /// A; requested values.
    pub run_current: f64,
    pub hold_current: f64,
    /// Ω.
    pub sense_resistor: f64,
    /// The DIAG output's input pin (not claimed unless the virtual endstop is used).
    pub diag_pin: Option<PinRef>,
    /// The GCONF field routing stallGuard to that pin (`diag0_stall` / `diag1_stall`; none on
    /// the TMC2209, whose DIAG always reports it).
    pub diag_field: Option<&'static str>,
    /// A stepper homes on its virtual endstop.
    pub virtual_endstop: bool,
    /// The step distance of its stepper (mm), for `VELOCITY=` thresholds.
    pub step_dist: f64,
    /// The registers as configured, in write order.
    pub fields: FieldSet,
    /// TMC2660 `idle_current_percent` (0..=100, default 100): the share of the run current
    /// the driver gets while the printer is idle (the host's `tmc::idle`).
    pub idle_current_percent: u8,
}

impl TmcSection {
    /// `tmc2209 stepper_x`.
    pub fn section_name(&self) -> String {
        format!("{} {}", self.model.kind(), self.stepper)
    }

    /// `tmc2209_stepper_x`: the chip name of its virtual endstop.
    pub fn chip(&self) -> String {
        chip_name(self.model.kind(), &self.stepper)
    }

    /// A velocity (mm/s) as a TSTEP threshold of this driver.
    pub fn tstep(&self, velocity: f64) -> u32 {
        tstep(
            self.model,
            self.step_dist,
            self.fields.get("mres").unwrap_or(0),
            velocity,
        )
    }
}

/// The virtual endstop chip of a driver: `tmc2209_stepper_x`.
pub fn chip_name(kind: &str, stepper: &str) -> String {
    format!("{kind}_{stepper}")
}

/// Virtual endstop chips of every TMC section of the file (for the pin registry).
pub(crate) fn chips(reader: &super::reader::Reader<'_>) -> Vec<String> {
    MODELS
        .iter()
        .flat_map(|(kind, _)| reader.section_names_of_kind(kind))
        .filter_map(|name| {
            let mut words = name.split_whitespace();
            Some(chip_name(words.next()?, words.next()?))
        })
        .collect()
}

/// TSTEP units of `velocity` mm/s for a stepper of `step_dist` mm at microstep setting `mres`.
pub fn tstep(model: TmcModel, step_dist: f64, mres: i64, velocity: f64) -> u32 {
    if velocity <= 0.0 {
        return 0xfffff;
    }
    let step_256 = step_dist / f64::from(1u32 << mres.clamp(0, 8));
    let t = (model.tmc_frequency() * step_256 / velocity + 0.5).floor();
    t.clamp(0.0, f64::from(0xfffffu32)) as u32
}

/// Reads one TMC section for the stepper of `motor` (looked up by the caller from the
/// section's name). `virtual_endstop`: a stepper homes on it (its diag pin is claimed).
pub(crate) fn read_tmc(
    s: &SectionReader<'_>,
    model: TmcModel,
    stepper: &str,
    motor: &MotorSection,
    virtual_endstop: bool,
    pins: &mut PinRegistry,
) -> Result<TmcSection, ConfigError> {
    if model == TmcModel::Tmc2240 && s.value("uart_pin").is_some() {
        return Err(ConfigError::BadSection {
            at: s.at().clone(),
            section: s.name().to_string(),
            reason:
                "option 'uart_pin' is not supported by Cadence yet (a TMC2240 on UART; SPI with cs_pin is)"
                    .to_string(),
        });
    }
    let bus = read_bus(s, model, pins)?;
    // The TMC2240's current is set by the resistor on its IREF pin (`rref`), not a sense
    // resistor: it takes the sense resistor's place in the current calculation.
    let sense_resistor = match model {
        TmcModel::Tmc2240 => s.float_or("rref", 12000.0, Bounds::ANY.min(12000.0).max(60000.0))?,
        // Klipper has no default for the TMC2660's.
        TmcModel::Tmc2660 => s.float("sense_resistor", Bounds::ANY.above(0.0))?,
        _ => s.float_or(
            "sense_resistor",
            model.default_sense_resistor(),
            Bounds::ANY.above(0.0),
        )?,
    };
    let max = match model {
        TmcModel::Tmc2240 => current::max_current_2240(sense_resistor),
        _ => model.max_current(),
    };
    let run_current = s.float("run_current", Bounds::ANY.above(0.0).max(max))?;
    // The TMC2660 has one current (no hold current).
    let hold_current = match model {
        TmcModel::Tmc2660 => run_current,
        _ => s.float_or("hold_current", max, Bounds::ANY.above(0.0).max(max))?,
    };
    let idle_current_percent = match model {
        TmcModel::Tmc2660 => s.int::<u8>("idle_current_percent", Some(100), 0..=100)?,
        _ => 100,
    };
    let (diag_option, diag_field) = match model {
        TmcModel::Tmc2208 | TmcModel::Tmc2660 => (None, None),
        TmcModel::Tmc2209 => (Some("diag_pin"), None),
        _ if s.value("diag0_pin").is_some() => (Some("diag0_pin"), Some("diag0_stall")),
        _ => (Some("diag1_pin"), Some("diag1_stall")),
    };
    let diag_pin = match diag_option {
        Some(option) if virtual_endstop => s.opt_pin(option, PinKind::Input, pins, Share::Exclusive)?,
        Some(option) => match s.value(option) {
            Some(v) => Some(PinRef::parse(&v.text, PinKind::Input).map_err(|problem| {
                s.bad(
                    option,
                    v,
                    super::error::ValueProblem::BadPin {
                        pin: v.text.clone(),
                        problem,
                    },
                )
            })?),
            None => None,
        },
        None => None,
    };
    if virtual_endstop && diag_pin.is_none() {
        return Err(ConfigError::BadSection {
            at: s.at().clone(),
            section: s.name().to_string(),
            reason: format!(
                "tmc virtual endstop requires diag pin config ({})",
                diag_option.unwrap_or("this driver has no diag output")
            ),
        });
    }
    let mut fields = FieldSet::new(model);
    let set = |fields: &mut FieldSet, f: &str, v: i64| {
        fields.set(f, v).map(|_| ()).map_err(|e| ConfigError::BadSection {
            at: s.at().clone(),
            section: s.name().to_string(),
            reason: e.to_string(),
        })
    };
    if model.is_uart() {
        set(&mut fields, "pdn_disable", 1)?;
    }
    if model == TmcModel::Tmc2660 {
        // Step/dir mode (DRVCTRL as microstep settings): DRVCONF is written first.
        set(&mut fields, "sdoff", 0)?;
    }
    if model == TmcModel::Tmc2209 {
        // Room between a reply and the next request on a shared line.
        set(&mut fields, "senddelay", 2)?;
    }
    current::set_current(&mut fields, sense_resistor, run_current, hold_current);
    let mres = match motor.microsteps {
        m if m.is_power_of_two() && m <= 256 => 8 - i64::from(m.trailing_zeros()),
        m => {
            return Err(ConfigError::BadSection {
                at: s.at().clone(),
                section: s.name().to_string(),
                reason: format!("the driver can not do microsteps: {m} of [{stepper}] (1, 2, 4 … 256)"),
            })
        }
    };
    set(&mut fields, "mres", mres)?;
    let interpolate = s.opt_bool("interpolate")?.unwrap_or(true);
    set(&mut fields, "intpol", i64::from(interpolate))?;
    if model.is_uart() {
        set(&mut fields, "mstep_reg_select", 1)?;
    }
    for &(field, default) in model.wave_table_fields() {
        read_field(s, &mut fields, field, default)?;
    }
    let step_dist = motor.step_dist();
    let velocity = |option: &str| s.opt_float(option, Bounds::ANY.min(0.0));
    // The TMC2660 has no velocity thresholds (nor their options).
    let thresholds = model.field("tpwmthrs").is_some();
    if thresholds {
        let stealth = velocity("stealthchop_threshold")?;
        let tpwmthrs = stealth.map_or(0xfffff, |v| tstep(model, step_dist, mres, v));
        set(&mut fields, "tpwmthrs", i64::from(tpwmthrs))?;
        match model.field("en_pwm_mode") {
            Some(_) => set(&mut fields, "en_pwm_mode", i64::from(stealth.is_some()))?,
            None => set(&mut fields, "en_spreadcycle", i64::from(stealth.is_none()))?,
        }
    }
    if thresholds && model != TmcModel::Tmc2208 {
        let t = velocity("coolstep_threshold")?.map_or(0, |v| tstep(model, step_dist, mres, v));
        set(&mut fields, "tcoolthrs", i64::from(t))?;
    }
    if matches!(model, TmcModel::Tmc2130 | TmcModel::Tmc2240 | TmcModel::Tmc5160) {
        let t = velocity("high_velocity_threshold")?.map_or(0, |v| tstep(model, step_dist, mres, v));
        set(&mut fields, "thigh", i64::from(t))?;
    }
    for &(field, default) in model.config_fields() {
        read_field(s, &mut fields, field, default)?;
    }
    // The TMC2660's spreadCycle hysteresis must fit (Klipper's check).
    if model == TmcModel::Tmc2660
        && fields.get("chm") == Some(0)
        && fields.get("hstrt").unwrap_or(0) + fields.get("hend").unwrap_or(0) > 15
    {
        return Err(ConfigError::BadSection {
            at: s.at().clone(),
            section: s.name().to_string(),
            reason: "driver_HEND + driver_HSTRT must be <= 15".to_string(),
        });
    }
    Ok(TmcSection {
        model,
        stepper: stepper.to_string(),
        bus,
        run_current,
        hold_current,
        sense_resistor,
        diag_pin,
        diag_field,
        virtual_endstop,
        step_dist,
        fields,
        idle_current_percent,
    })
}

/// `driver_<FIELD>`: a boolean for a one-bit field, a signed or unsigned integer within the
/// field's width otherwise.
fn read_field(
    s: &SectionReader<'_>,
    fields: &mut FieldSet,
    field: &str,
    default: i64,
) -> Result<(), ConfigError> {
    let Some((_, mask)) = fields.model.field(field) else {
        return Ok(());
    };
    let option = format!("driver_{field}");
    let max = i64::from(mask >> mask.trailing_zeros());
    let value = if max == 1 {
        i64::from(s.opt_bool(&option)?.unwrap_or(default != 0))
    } else if field == "sgt" {
        s.int::<i64>(&option, Some(default), -(max / 2 + 1)..=max / 2)?
    } else {
        s.int::<i64>(&option, Some(default), 0..=max)?
    };
    fields
        .set(field, value)
        .map(|_| ())
        .map_err(|e| ConfigError::BadSection {
            at: s.at().clone(),
            section: s.name().to_string(),
            reason: e.to_string(),
        })
}

/// `select_pins`: outputs on the UART's MCU, shared by the drivers behind the same mux (each
/// with its own levels, so claimed without their `!`).
fn read_select_pins(
    s: &SectionReader<'_>,
    mcu: &str,
    pins: &mut PinRegistry,
) -> Result<Vec<PinRef>, ConfigError> {
    let Some(v) = s.value("select_pins") else {
        return Ok(Vec::new());
    };
    let mut out = Vec::new();
    for text in v.text.split(',').map(str::trim).filter(|t| !t.is_empty()) {
        let bad = |problem| s.bad("select_pins", v, problem);
        let pin = PinRef::parse(text, PinKind::Output).map_err(|problem| {
            bad(ValueProblem::BadPin {
                pin: text.to_string(),
                problem,
            })
        })?;
        let pin = pins.resolve(pin).map_err(bad)?;
        if pin.mcu != mcu {
            return Err(bad(ValueProblem::Invalid(
                "TMC mux pins must be on the same mcu".to_string(),
            )));
        }
        let level_free = PinRef {
            invert: false,
            ..pin.clone()
        };
        pins.claim(&level_free, s.name(), "select_pins", Share::TmcUart)
            .map_err(bad)?;
        out.push(pin);
    }
    Ok(out)
}

fn read_bus(s: &SectionReader<'_>, model: TmcModel, pins: &mut PinRegistry) -> Result<TmcBus, ConfigError> {
    let refuse = |option: &str, what: &str| -> Result<(), ConfigError> {
        match s.value(option) {
            Some(_) => Err(ConfigError::BadSection {
                at: s.at().clone(),
                section: s.name().to_string(),
                reason: format!("option '{option}' is not supported by Cadence yet ({what})"),
            }),
            None => Ok(()),
        }
    };
    if model.is_uart() {
        let uart_pin = s.pin("uart_pin", PinKind::Input, pins, Share::TmcUart)?;
        let tx_pin = s.opt_pin("tx_pin", PinKind::Output, pins, Share::TmcUart)?;
        if let Some(tx) = &tx_pin {
            if tx.mcu != uart_pin.mcu {
                return Err(ConfigError::BadSection {
                    at: s.at().clone(),
                    section: s.name().to_string(),
                    reason: "TMC uart rx and tx pins must be on the same mcu".to_string(),
                });
            }
        }
        let address = s.int::<u8>("uart_address", Some(0), 0..=i64::from(model.max_uart_address()))?;
        let select_pins = read_select_pins(s, &uart_pin.mcu, pins)?;
        return Ok(TmcBus::Uart {
            uart_pin,
            tx_pin,
            address,
            select_pins,
        });
    }
    // At most 9 drivers: 45 bytes, within the MCU's largest SPI transfer.
    let length = match s.value("chain_length") {
        Some(_) => Some(s.int::<u8>("chain_length", None, 2..=9)?),
        None => None,
    };
    let chain = match length {
        Some(length) => Some((
            length,
            s.int::<u8>("chain_position", None, 1..=i64::from(length))?,
        )),
        None => {
            refuse("chain_position", "a chain_position without chain_length")?;
            None
        }
    };
    let share = if chain.is_some() {
        Share::SpiChain
    } else {
        Share::Exclusive
    };
    let spi = super::spi_sensor::read_spi_bus(s, pins, "cs_pin", share, 4_000_000)?;
    Ok(TmcBus::Spi {
        cs_pin: spi.cs_pin,
        speed: spi.speed,
        bus: spi.bus,
        software: spi.software,
        chain,
    })
}

#[cfg(test)]
mod tests;
