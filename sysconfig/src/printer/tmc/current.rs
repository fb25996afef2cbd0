//! Motor current → current-scale register bits, as the drivers' datasheets define them.
//!
//! TMC2130/2208/2209: the RMS current through the sense resistor `R` (plus 20 mΩ of the
//! driver's internal path) is `I = (CS + 1) / 32 · Vfs / (R + 0.02) / √2`, so
//! `CS = ⌊32 · (R + 0.02) · I · √2 / Vfs + ½⌋ − 1` clamped to 0..=31, where the full-scale
//! voltage `Vfs` is 0.32 V, or 0.18 V with `vsense` set (the high-sensitivity range). `vsense`
//! is used unless the run current needs CS = 31 and the low-sensitivity range is nearer the
//! request. The hold current (at most the run current) uses the same range.
//!
//! TMC5160: `I = GLOBALSCALER / 256 · (CS + 1) / 32 · Vfs / R / √2` with Vfs = 0.325 V; the
//! global scaler is first chosen for CS = 31 (`⌊I · 256 · √2 · R / Vfs + ½⌋`, at least 32, and
//! 0 meaning 256 when it would reach 256), then `CS = ⌊I · 256 · 32 · √2 · R / (G · Vfs) − ½⌋`.
//!
//! TMC2660: one current (CS in SGCSCONF, no hold current), `I = (CS + 1) / 32 · Vfs / R / √2`
//! with Vfs 0.31 V, or 0.165 V with `vsense`, chosen as for the TMC2130.
//!
//! TMC2240: no sense resistor; the full scale is `KIFS[current_range] / rref` A peak (KIFS
//! 11750, 24000, 36000, 36000 A·Ω for ranges 0..3), RMS `/ √2`. The range is the smallest whose
//! full scale reaches the run current, then as the TMC5160 with that full scale in place of
//! `Vfs / R`: `G = ⌊I · 256 / Ifs + ½⌋` (at least 32, 0 for 256),
//! `CS = ⌊I · 256 · 32 / (G · Ifs) − ½⌋`.

use super::model::{FieldSet, TmcModel};

/// TMC2240 full-scale constants per `current_range` (A·Ω).
const KIFS_2240: [f64; 4] = [11750.0, 24000.0, 36000.0, 36000.0];

/// TMC2240 RMS full-scale current (A) of `range` with `rref` Ω.
fn ifs_rms_2240(rref: f64, range: usize) -> f64 {
    KIFS_2240[range.min(3)] / rref / SQRT2
}

/// The TMC2240's largest current (A) with `rref` Ω (its highest range's full scale).
pub fn max_current_2240(rref: f64) -> f64 {
    ifs_rms_2240(rref, 3)
}

/// TMC2240: `(current_range, globalscaler, irun, ihold)` for `run` and `hold` A.
fn bits_2240(rref: f64, run: f64, hold: f64) -> (i64, i64, i64, i64) {
    let range = (0..4).find(|&r| run <= ifs_rms_2240(rref, r)).unwrap_or(3);
    let ifs = ifs_rms_2240(rref, range);
    let g = match ((run * 256.0 / ifs) + 0.5).floor() as i64 {
        g if g >= 256 => 0,
        g => g.max(32),
    };
    let cs = |i: f64| {
        let gf = if g == 0 { 256.0 } else { g as f64 };
        ((i * 256.0 * 32.0 / (gf * ifs)) - 1.0 + 0.5)
            .floor()
            .clamp(0.0, 31.0) as i64
    };
    (range as i64, g, cs(run), cs(hold))
}

const SQRT2: f64 = std::f64::consts::SQRT_2;
/// TMC5160 full-scale sense voltage (V).
const VREF_5160: f64 = 0.325;

/// A driver's full-scale sense voltages (low, high sensitivity) and the resistance its
/// sense path adds to the sense resistor.
#[derive(Debug, Clone, Copy)]
struct SenseScale {
    vref: (f64, f64),
    extra_ohm: f64,
}

/// TMC2130/2208/2209.
const SCALE_2130: SenseScale = SenseScale {
    vref: (0.32, 0.18),
    extra_ohm: 0.020,
};
/// TMC2660.
const SCALE_2660: SenseScale = SenseScale {
    vref: (0.31, 0.165),
    extra_ohm: 0.0,
};

impl SenseScale {
    fn vref(self, vsense: bool) -> f64 {
        if vsense {
            self.vref.1
        } else {
            self.vref.0
        }
    }

    /// CS bits for `current` with `vsense`.
    fn cs_bits(self, sense: f64, current: f64, vsense: bool) -> i64 {
        let r = sense + self.extra_ohm;
        let cs = (32.0 * r * current * SQRT2 / self.vref(vsense) + 0.5).floor() as i64 - 1;
        cs.clamp(0, 31)
    }

    /// Current of CS bits `cs` with `vsense`.
    fn cs_current(self, sense: f64, cs: i64, vsense: bool) -> f64 {
        (cs + 1) as f64 * self.vref(vsense) / (32.0 * (sense + self.extra_ohm) * SQRT2)
    }

    /// `(vsense, cs)` for `run`: the high-sensitivity range unless the run current needs
    /// CS = 31 and the other range is nearer.
    fn choose(self, sense: f64, run: f64) -> (bool, i64) {
        let irun = self.cs_bits(sense, run, true);
        if irun == 31 {
            let cur = self.cs_current(sense, irun, true);
            let irun2 = self.cs_bits(sense, run, false);
            let cur2 = self.cs_current(sense, irun2, false);
            if cur < run && (run - cur2).abs() < (run - cur).abs() {
                return (false, irun2);
            }
        }
        (true, irun)
    }
}

fn global_scaler(sense: f64, current: f64) -> i64 {
    let g = ((current * 256.0 * SQRT2 * sense / VREF_5160) + 0.5).floor() as i64;
    match g.max(32) {
        g if g >= 256 => 0,
        g => g,
    }
}

fn cs_bits_5160(sense: f64, current: f64, gscaler: i64) -> i64 {
    let g = if gscaler == 0 { 256 } else { gscaler } as f64;
    let cs = ((current * 256.0 * 32.0 * SQRT2 * sense) / (g * VREF_5160) - 1.0 + 0.5).floor() as i64;
    cs.clamp(0, 31)
}

/// Sets the current fields of `fields` (`vsense` or `globalscaler`, `ihold`, `irun`) for
/// `run` and `hold` amperes through `sense` Ω; returns the registers changed, in write order.
pub fn set_current(fields: &mut FieldSet, sense: f64, run: f64, hold: f64) -> Vec<(&'static str, u32)> {
    let hold = hold.min(run);
    let mut changed: Vec<(&'static str, u32)> = Vec::new();
    let mut note = |r: Result<(&'static str, u32), super::model::FieldError>| {
        if let Ok((reg, v)) = r {
            match changed.iter_mut().find(|(n, _)| *n == reg) {
                Some(slot) => slot.1 = v,
                None => changed.push((reg, v)),
            }
        }
    };
    match fields.model {
        TmcModel::Tmc2240 => {
            let (range, g, irun, ihold) = bits_2240(sense, run, hold);
            note(fields.set("current_range", range));
            note(fields.set("globalscaler", g));
            note(fields.set("ihold", ihold));
            note(fields.set("irun", irun));
        }
        TmcModel::Tmc5160 => {
            let g = global_scaler(sense, run);
            note(fields.set("globalscaler", g));
            note(fields.set("ihold", cs_bits_5160(sense, hold, g)));
            note(fields.set("irun", cs_bits_5160(sense, run, g)));
        }
        TmcModel::Tmc2660 => {
            let (vsense, cs) = SCALE_2660.choose(sense, run);
            note(fields.set("cs", cs));
            note(fields.set("vsense", i64::from(vsense)));
        }
        _ => {
            let (vsense, irun) = SCALE_2130.choose(sense, run);
            note(fields.set("vsense", i64::from(vsense)));
            note(fields.set("ihold", SCALE_2130.cs_bits(sense, hold, vsense)));
            note(fields.set("irun", irun));
        }
    }
    changed
}

/// A TMC2660's `cs` (and `vsense`) for `current` A through `sense` Ω, as Klipper changes them
/// on a running printer (its idle current): returns SGCSCONF, then DRVCONF only when `vsense`
/// changed.
pub fn set_current_2660(fields: &mut FieldSet, sense: f64, current: f64) -> Vec<(&'static str, u32)> {
    let (vsense, cs) = SCALE_2660.choose(sense, current);
    let vsense = i64::from(vsense);
    let vsense_changed = fields.get("vsense") != Some(vsense);
    let mut out: Vec<(&'static str, u32)> = fields.set("cs", cs).into_iter().collect();
    if vsense_changed {
        out.extend(fields.set("vsense", vsense));
    }
    out
}

/// The run and hold currents (A) the fields give through `sense` Ω.
pub fn current(fields: &FieldSet, sense: f64) -> (f64, f64) {
    let irun = fields.get("irun").unwrap_or(0);
    let ihold = fields.get("ihold").unwrap_or(0);
    match fields.model {
        TmcModel::Tmc2240 => {
            let range = usize::try_from(fields.get("current_range").unwrap_or(0)).unwrap_or(0);
            let ifs = ifs_rms_2240(sense, range);
            let g = match fields.get("globalscaler").unwrap_or(0) {
                0 => 256,
                g => g,
            } as f64;
            let of = |bits: i64| g * (bits + 1) as f64 * ifs / (256.0 * 32.0);
            (of(irun), of(ihold))
        }
        TmcModel::Tmc5160 => {
            let g = match fields.get("globalscaler").unwrap_or(0) {
                0 => 256,
                g => g,
            } as f64;
            let of = |bits: i64| g * (bits + 1) as f64 * VREF_5160 / (256.0 * 32.0 * SQRT2 * sense);
            (of(irun), of(ihold))
        }
        TmcModel::Tmc2660 => {
            let vsense = fields.get("vsense").unwrap_or(0) != 0;
            let run = SCALE_2660.cs_current(sense, fields.get("cs").unwrap_or(0), vsense);
            (run, run)
        }
        _ => {
            let vsense = fields.get("vsense").unwrap_or(0) != 0;
            (
                SCALE_2130.cs_current(sense, irun, vsense),
                SCALE_2130.cs_current(sense, ihold, vsense),
            )
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn known_values() {
        // 0.8 A through 0.11 Ω: 32 · 0.13 · 0.8 · √2 / 0.18 = 26.1 → 26 − 1 = 25, vsense on.
        let mut f = FieldSet::new(TmcModel::Tmc2209);
        set_current(&mut f, 0.110, 0.8, 0.5);
        assert_eq!(
            (f.get("vsense"), f.get("irun"), f.get("ihold")),
            (Some(1), Some(25), Some(15))
        );
        // 1.7 A needs the low-sensitivity range: 32 · 0.13 · 1.7 · √2 / 0.32 = 31.25 → 30.
        set_current(&mut f, 0.110, 1.7, 1.7);
        assert_eq!((f.get("vsense"), f.get("irun")), (Some(0), Some(30)));
        // TMC5160, 2 A through 0.075 Ω: G = ⌊2 · 256 · √2 · 0.075 / 0.325 + ½⌋ = 167.
        let mut f = FieldSet::new(TmcModel::Tmc5160);
        let regs = set_current(&mut f, 0.075, 2.0, 1.0);
        assert_eq!(f.get("globalscaler"), Some(167));
        assert_eq!(f.get("irun"), Some(31));
        assert_eq!(f.get("ihold"), Some(15));
        assert_eq!(
            regs.iter().map(|r| r.0).collect::<Vec<_>>(),
            ["GLOBALSCALER", "IHOLD_IRUN"]
        );
    }

    proptest! {
        /// The current the bits give is within one CS step of the request, unless the request
        /// is beyond the range the resistor allows.
        #[test]
        fn bits_give_the_requested_current(run in 0.1f64..1.9, sense in 0.05f64..0.2) {
            for model in [TmcModel::Tmc2209, TmcModel::Tmc5160] {
                let mut f = FieldSet::new(model);
                set_current(&mut f, sense, run, run);
                let (got, hold) = current(&f, sense);
                let irun = f.get("irun").unwrap_or(0);
                prop_assert!((got - hold).abs() < 1e-12);
                if irun > 0 && irun < 31 {
                    prop_assert!((got - run).abs() <= got / (irun + 1) as f64 + 1e-9, "{model:?} {run} {got}");
                }
            }
        }
    }
}
