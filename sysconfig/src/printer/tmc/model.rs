//! The TMC driver models and their register values as fields: a [`FieldSet`] holds the values
//! the host last wrote (in the order they were first set, the order they are written in), and
//! reads and writes fields by name through the model's masks.
//!
//! A field's value is `(register & mask) >> shift` where `shift` is the mask's lowest set bit;
//! a signed field (`sgt`, `cur_a`…) is sign-extended from the mask's width.

use super::tables::*;
use super::tables_2240::*;
use super::tables_2660::*;

/// A TMC stepper driver model.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TmcModel {
    Tmc2130,
    Tmc2208,
    Tmc2209,
    Tmc2240,
    Tmc2660,
    Tmc5160,
}

/// `[tmcXXXX]` section kinds Cadence drives, and their model.
pub const MODELS: [(&str, TmcModel); 6] = [
    ("tmc2130", TmcModel::Tmc2130),
    ("tmc2208", TmcModel::Tmc2208),
    ("tmc2209", TmcModel::Tmc2209),
    ("tmc2240", TmcModel::Tmc2240),
    ("tmc2660", TmcModel::Tmc2660),
    ("tmc5160", TmcModel::Tmc5160),
];

impl TmcModel {
    /// The model of section kind `kind` (`tmc2209`).
    pub fn of_kind(kind: &str) -> Option<TmcModel> {
        MODELS.iter().find(|(k, _)| *k == kind).map(|&(_, m)| m)
    }

    /// The section kind (`tmc2209`).
    pub fn kind(self) -> &'static str {
        match self {
            TmcModel::Tmc2130 => "tmc2130",
            TmcModel::Tmc2208 => "tmc2208",
            TmcModel::Tmc2209 => "tmc2209",
            TmcModel::Tmc2240 => "tmc2240",
            TmcModel::Tmc2660 => "tmc2660",
            TmcModel::Tmc5160 => "tmc5160",
        }
    }

    /// Register names and addresses (the TMC2209's are the TMC2208's and more).
    pub fn registers(self) -> impl Iterator<Item = &'static (&'static str, u8)> {
        type Registers = &'static [(&'static str, u8)];
        let (base, extra): (Registers, Registers) = match self {
            TmcModel::Tmc2130 => (TMC2130_REGISTERS, &[]),
            TmcModel::Tmc2208 => (TMC2208_REGISTERS, &[]),
            TmcModel::Tmc2209 => (TMC2208_REGISTERS, TMC2209_EXTRA_REGISTERS),
            TmcModel::Tmc2240 => (TMC2240_REGISTERS, &[]),
            TmcModel::Tmc2660 => (TMC2660_REGISTERS, &[]),
            TmcModel::Tmc5160 => (TMC5160_REGISTERS, &[]),
        };
        base.iter().chain(extra)
    }

    /// Registers the driver answers reads of (`DUMP_TMC`'s queried list, in its order).
    pub fn readable(self) -> &'static [&'static str] {
        match self {
            TmcModel::Tmc2130 => TMC2130_READABLE,
            TmcModel::Tmc2208 => TMC2208_READABLE,
            TmcModel::Tmc2209 => TMC2209_READABLE,
            TmcModel::Tmc2240 => TMC2240_READABLE,
            TmcModel::Tmc2660 => TMC2660_READABLE,
            TmcModel::Tmc5160 => TMC5160_READABLE,
        }
    }

    /// (register, field, mask) of every field (the TMC2209's are the TMC2208's and more).
    pub fn fields(self) -> impl Iterator<Item = &'static (&'static str, &'static str, u32)> {
        type Fields = &'static [(&'static str, &'static str, u32)];
        let (base, extra): (Fields, Fields) = match self {
            TmcModel::Tmc2130 => (TMC2130_FIELDS, &[]),
            TmcModel::Tmc2208 => (TMC2208_FIELDS, &[]),
            TmcModel::Tmc2209 => (TMC2208_FIELDS, TMC2209_EXTRA_FIELDS),
            TmcModel::Tmc2240 => (TMC2240_FIELDS, &[]),
            TmcModel::Tmc2660 => (TMC2660_FIELDS, &[]),
            TmcModel::Tmc5160 => (TMC5160_FIELDS, &[]),
        };
        base.iter().chain(extra)
    }

    fn signed(self) -> &'static [&'static str] {
        match self {
            TmcModel::Tmc2130 => TMC2130_SIGNED,
            TmcModel::Tmc2208 => TMC2208_SIGNED,
            TmcModel::Tmc2209 => TMC2209_SIGNED,
            TmcModel::Tmc2240 => TMC2240_SIGNED,
            TmcModel::Tmc2660 => TMC2660_SIGNED,
            TmcModel::Tmc5160 => TMC5160_SIGNED,
        }
    }

    /// Talks UART (single wire, bit-banged by the MCU) rather than SPI.
    pub fn is_uart(self) -> bool {
        matches!(self, TmcModel::Tmc2208 | TmcModel::Tmc2209)
    }

    /// Highest `uart_address` (the TMC2208 has no address pins).
    pub fn max_uart_address(self) -> u8 {
        match self {
            TmcModel::Tmc2209 => 3,
            _ => 0,
        }
    }

    /// Largest `run_current` / `hold_current` accepted (A): the drivers' 2 A, the TMC5160's
    /// external MOSFETs a 10 A sanity bound; the TMC2240's depends on its `rref`
    /// ([`super::current::max_current_2240`]).
    pub fn max_current(self) -> f64 {
        match self {
            TmcModel::Tmc5160 => 10.0,
            TmcModel::Tmc2660 => 2.4,
            _ => 2.0,
        }
    }

    /// Default `sense_resistor` (Ω); for the TMC2240 its `rref` (Ω on its IREF pin).
    pub fn default_sense_resistor(self) -> f64 {
        match self {
            TmcModel::Tmc5160 => 0.075,
            TmcModel::Tmc2240 => 12000.0,
            _ => 0.110,
        }
    }

    /// The driver's internal clock (Hz), the unit of TSTEP-based thresholds.
    pub fn tmc_frequency(self) -> f64 {
        match self {
            TmcModel::Tmc2130 => 13.2e6,
            TmcModel::Tmc2240 => 12.5e6,
            _ => 12e6,
        }
    }

    /// The register at `addr`.
    pub fn register_name(self, addr: u8) -> Option<&'static str> {
        self.registers().find(|(_, a)| *a == addr).map(|&(n, _)| n)
    }

    /// The address of register `name`.
    pub fn register_addr(self, name: &str) -> Option<u8> {
        self.registers().find(|(n, _)| *n == name).map(|&(_, a)| a)
    }

    /// The register and mask of field `field` (lowercase).
    pub fn field(self, field: &str) -> Option<(&'static str, u32)> {
        self.fields()
            .find(|(r, f, _)| *f == field && !r.contains('@'))
            .or_else(|| self.fields().find(|(_, f, _)| *f == field))
            .map(|&(r, _, m)| (r, m))
    }

    /// The fields `driver_*` options may set, with their defaults, in the order they are set
    /// (the drivers' power-on tuning as Klipper configures it).
    pub fn config_fields(self) -> &'static [(&'static str, i64)] {
        match self {
            TmcModel::Tmc2130 => &[
                ("toff", 4),
                ("hstrt", 0),
                ("hend", 7),
                ("tbl", 1),
                ("vhighfs", 0),
                ("vhighchm", 0),
                ("semin", 0),
                ("seup", 0),
                ("semax", 0),
                ("sedn", 0),
                ("seimin", 0),
                ("sgt", 0),
                ("sfilt", 0),
                ("iholddelay", 8),
                ("pwm_ampl", 128),
                ("pwm_grad", 4),
                ("pwm_freq", 1),
                ("pwm_autoscale", 1),
                ("freewheel", 0),
                ("tpowerdown", 0),
            ],
            TmcModel::Tmc2208 => &[
                ("multistep_filt", 1),
                ("toff", 3),
                ("hstrt", 5),
                ("hend", 0),
                ("tbl", 2),
                ("iholddelay", 8),
                ("pwm_ofs", 36),
                ("pwm_grad", 14),
                ("pwm_freq", 1),
                ("pwm_autoscale", 1),
                ("pwm_autograd", 1),
                ("freewheel", 0),
                ("pwm_reg", 8),
                ("pwm_lim", 12),
                ("tpowerdown", 20),
            ],
            TmcModel::Tmc2209 => &[
                ("multistep_filt", 1),
                ("toff", 3),
                ("hstrt", 5),
                ("hend", 0),
                ("tbl", 2),
                ("semin", 0),
                ("seup", 0),
                ("semax", 0),
                ("sedn", 0),
                ("seimin", 0),
                ("iholddelay", 8),
                ("pwm_ofs", 36),
                ("pwm_grad", 14),
                ("pwm_freq", 1),
                ("pwm_autoscale", 1),
                ("pwm_autograd", 1),
                ("freewheel", 0),
                ("pwm_reg", 8),
                ("pwm_lim", 12),
                ("tpowerdown", 20),
                ("sgthrs", 0),
            ],
            TmcModel::Tmc2660 => &[
                ("tbl", 2),
                ("rndtf", 0),
                ("hdec", 0),
                ("chm", 0),
                ("hend", 3),
                ("hstrt", 3),
                ("toff", 4),
                ("seimin", 0),
                ("sedn", 0),
                ("semax", 0),
                ("seup", 0),
                ("semin", 0),
                ("sfilt", 0),
                ("sgt", 0),
                ("slph", 0),
                ("slpl", 0),
                ("diss2g", 0),
                ("ts2g", 3),
            ],
            TmcModel::Tmc2240 => &[
                ("offset_sin90", 0),
                ("multistep_filt", 1),
                ("toff", 3),
                ("hstrt", 5),
                ("hend", 2),
                ("fd3", 0),
                ("disfdcc", 0),
                ("chm", 0),
                ("tbl", 2),
                ("vhighfs", 0),
                ("vhighchm", 0),
                ("tpfd", 4),
                ("diss2g", 0),
                ("diss2vs", 0),
                ("semin", 0),
                ("seup", 0),
                ("semax", 0),
                ("sedn", 0),
                ("seimin", 0),
                ("sgt", 0),
                ("sfilt", 0),
                ("iholddelay", 6),
                ("irundelay", 4),
                ("pwm_ofs", 29),
                ("pwm_grad", 0),
                ("pwm_freq", 0),
                ("pwm_autoscale", 1),
                ("pwm_autograd", 1),
                ("freewheel", 0),
                ("pwm_reg", 4),
                ("pwm_lim", 12),
                ("tpowerdown", 10),
                ("sg4_thrs", 0),
                ("sg4_angle_offset", 1),
                ("slope_control", 0),
            ],
            TmcModel::Tmc5160 => &[
                ("multistep_filt", 1),
                ("toff", 3),
                ("hstrt", 5),
                ("hend", 2),
                ("fd3", 0),
                ("disfdcc", 0),
                ("chm", 0),
                ("tbl", 2),
                ("vhighfs", 0),
                ("vhighchm", 0),
                ("tpfd", 4),
                ("diss2g", 0),
                ("diss2vs", 0),
                ("semin", 0),
                ("seup", 0),
                ("semax", 0),
                ("sedn", 0),
                ("seimin", 0),
                ("sgt", 0),
                ("sfilt", 0),
                ("drvstrength", 0),
                ("bbmclks", 4),
                ("bbmtime", 0),
                ("filt_isense", 0),
                ("iholddelay", 6),
                ("pwm_ofs", 30),
                ("pwm_grad", 0),
                ("pwm_freq", 0),
                ("pwm_autoscale", 1),
                ("pwm_autograd", 1),
                ("freewheel", 0),
                ("pwm_reg", 4),
                ("pwm_lim", 12),
                ("tpowerdown", 10),
            ],
        }
    }

    /// The SPI drivers' sine wave table (`driver_MSLUT0`… options) with its defaults.
    pub fn wave_table_fields(self) -> &'static [(&'static str, i64)] {
        match self {
            TmcModel::Tmc2130 | TmcModel::Tmc2240 | TmcModel::Tmc5160 => &[
                ("mslut0", 0xAAAA_B554),
                ("mslut1", 0x4A95_54AA),
                ("mslut2", 0x2449_2929),
                ("mslut3", 0x1010_4222),
                ("mslut4", 0xFBFF_FFFF),
                ("mslut5", 0xB5BB_777D),
                ("mslut6", 0x4929_5556),
                ("mslut7", 0x0040_4222),
                ("w0", 2),
                ("w1", 1),
                ("w2", 1),
                ("w3", 1),
                ("x1", 128),
                ("x2", 255),
                ("x3", 255),
                ("start_sin", 0),
                ("start_sin90", 247),
            ],
            _ => &[],
        }
    }
}

/// Why a field could not be set.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FieldError {
    /// The model has no field of that name.
    #[error("Unknown field name '{0}'")]
    Unknown(String),
}

/// The register values of one driver, as the host last set them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FieldSet {
    pub model: TmcModel,
    /// (register, value) in the order each register was first set.
    regs: Vec<(&'static str, u32)>,
}

fn shift(mask: u32) -> u32 {
    mask.trailing_zeros()
}

impl FieldSet {
    /// No register set yet.
    pub fn new(model: TmcModel) -> FieldSet {
        FieldSet {
            model,
            regs: Vec::new(),
        }
    }

    /// The registers set, in write order.
    pub fn registers(&self) -> &[(&'static str, u32)] {
        &self.regs
    }

    /// The value of register `reg` as set (0 when never set).
    pub fn register(&self, reg: &str) -> u32 {
        self.regs.iter().find(|(r, _)| *r == reg).map_or(0, |&(_, v)| v)
    }

    /// Field `field` of `value`, a value of register `reg`, sign-extended for a signed field.
    pub fn decode(model: TmcModel, reg: &str, field: &str, value: u32) -> Option<i64> {
        let &(_, _, mask) = model.fields().find(|(r, f, _)| *r == reg && *f == field)?;
        let raw = i64::from((value & mask) >> shift(mask));
        let max = i64::from(mask >> shift(mask));
        if model.signed().contains(&field) && raw > max / 2 {
            return Some(raw - (max + 1));
        }
        Some(raw)
    }

    /// The current value of field `field`.
    pub fn get(&self, field: &str) -> Option<i64> {
        let (reg, _) = self.model.field(field)?;
        FieldSet::decode(self.model, reg, field, self.register(reg))
    }

    /// Sets field `field` to `value` (its bits outside the mask dropped, as the hardware
    /// would); returns the register and its new value.
    pub fn set(&mut self, field: &str, value: i64) -> Result<(&'static str, u32), FieldError> {
        let (reg, mask) = self
            .model
            .field(field)
            .ok_or_else(|| FieldError::Unknown(field.to_string()))?;
        let bits = ((value as u64) << shift(mask)) as u32 & mask;
        let new = (self.register(reg) & !mask) | bits;
        match self.regs.iter_mut().find(|(r, _)| *r == reg) {
            Some(slot) => slot.1 = new,
            None => self.regs.push((reg, new)),
        }
        Ok((reg, new))
    }

    /// `REG:        0000abcd field=v …`: the register's non-zero fields, lowest bits first
    /// (`DUMP_TMC`'s line).
    pub fn pretty(model: TmcModel, reg: &str, value: u32) -> String {
        let mut fields: Vec<_> = model.fields().filter(|(r, _, _)| *r == reg).collect();
        fields.sort_by_key(|(_, _, m)| *m);
        let mut out = format!("{:<11} {value:08x}", format!("{reg}:"));
        for (_, f, _) in fields {
            match FieldSet::decode(model, reg, f, value) {
                Some(0) | None => {}
                Some(v) => out.push_str(&format!(" {f}={}", format_field(f, v))),
            }
        }
        out
    }
}

/// A field's value as `DUMP_TMC` shows it (microstep resolution and the version decoded).
fn format_field(field: &str, v: i64) -> String {
    match field {
        "mres" => format!("{v}({}usteps)", 256 >> v.clamp(0, 8)),
        "version" => format!("{v:#x}"),
        _ => v.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_round_trip_and_signed_fields_sign_extend() {
        let mut f = FieldSet::new(TmcModel::Tmc2130);
        assert_eq!(f.set("sgt", -3), Ok(("COOLCONF", 0x7d << 16)));
        assert_eq!(f.get("sgt"), Some(-3));
        f.set("sgt", 63).unwrap();
        assert_eq!(f.get("sgt"), Some(63));
        f.set("semin", 5).unwrap();
        assert_eq!(f.register("COOLCONF"), (63 << 16) | 5);
        assert_eq!(f.set("nope", 1), Err(FieldError::Unknown("nope".into())));
        let mut f = FieldSet::new(TmcModel::Tmc2209);
        f.set("irun", 16).unwrap();
        f.set("ihold", 8).unwrap();
        f.set("iholddelay", 8).unwrap();
        assert_eq!(f.register("IHOLD_IRUN"), 0x0008_1008);
        assert_eq!(f.set("sgthrs", 0x1ff), Ok(("SGTHRS", 0xff)));
    }

    #[test]
    fn tables_are_consistent() {
        for (_, m) in MODELS {
            for (reg, field, mask) in m.fields() {
                // `REG@VARIANT` is REG as one model variant has it, except for registers whose
                // name has the `@` (the TMC2660's READRSP@RDSELn).
                let base = reg.split('@').next().unwrap_or(reg);
                let known = m.register_addr(reg).or(m.register_addr(base));
                assert!(known.is_some(), "{m:?} {reg}.{field}");
                assert_ne!(*mask, 0);
            }
            for reg in m.readable() {
                assert!(m.register_addr(reg).is_some(), "{m:?} {reg}");
            }
            for (f, _) in m.config_fields().iter().chain(m.wave_table_fields()) {
                assert!(m.field(f).is_some(), "{m:?} {f}");
            }
        }
    }

    #[test]
    fn pretty_formats_like_dump_tmc() {
        let v = (4 << 24) | (1 << 28) | 3;
        assert_eq!(
            FieldSet::pretty(TmcModel::Tmc2209, "CHOPCONF", v),
            "CHOPCONF:   14000003 toff=3 mres=4(16usteps) intpol=1"
        );
    }
}
