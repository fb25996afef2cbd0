//! The `cadence-mcu` command line (docs/contract.md).

use super::bltouch::{BlTouchSpec, Fault as BlTouchFault};
use super::heater::{HeaterFault, ThermalModel};
use super::tmc::{DiagSpec as TmcDiagSpec, Model as TmcModel, TmcSpec};
use super::world::{AxisSpec, Coord, EndstopSpec};
use crate::trace::TraceFormat;
#[cfg(test)]
use clap::CommandFactory;
use clap::{Parser, ValueEnum};
use links::pinmap;
use std::path::PathBuf;

/// Largest `--move-count` (the core's move pool capacity).
pub const MAX_MOVE_COUNT: u16 = super::SIM_MOVES as u16;

/// Trace file format on the command line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum TraceFormatArg {
    /// Binary: 24-byte header, 16-byte records.
    Bin,
    /// Text lines.
    Csv,
}

impl From<TraceFormatArg> for TraceFormat {
    fn from(f: TraceFormatArg) -> TraceFormat {
        match f {
            TraceFormatArg::Bin => TraceFormat::Bin,
            TraceFormatArg::Csv => TraceFormat::Csv,
        }
    }
}

/// Simulated Klipper-protocol MCU on a pseudo-terminal.
#[derive(Debug, Clone, Parser)]
#[command(name = "cadence-mcu", version, about)]
pub struct Cli {
    /// Also make a symlink to the pty slave at PATH.
    #[arg(long, value_name = "PATH")]
    pub pty_link: Option<PathBuf>,
    /// MCU clock frequency (the dictionary's CLOCK_FREQ).
    #[arg(long, value_name = "HZ", default_value_t = 50_000_000,
          value_parser = clap::value_parser!(u32).range(1..))]
    pub clock_freq: u32,
    /// MCU seconds per wall-clock second.
    #[arg(long, value_name = "N", default_value_t = 1.0, value_parser = parse_time_scale)]
    pub time_scale: f64,
    /// Write every step, received queue_step and shutdown to FILE.
    #[arg(long, value_name = "FILE")]
    pub trace: Option<PathBuf>,
    /// Trace file format.
    #[arg(long, value_enum, default_value_t = TraceFormatArg::Bin)]
    pub trace_format: TraceFormatArg,
    /// Size of the move queue reported in `config` (move_count).
    #[arg(long, value_name = "N", default_value_t = 16384,
          value_parser = clap::value_parser!(u16).range(1..=MAX_MOVE_COUNT as i64))]
    pub move_count: u16,
    /// Shut down ("Stepper too far in past", "Rescheduled timer in the past") when a step or
    /// periodic timer runs more than US µs of MCU time late; 0 = never.
    #[arg(long, value_name = "US", default_value_t = 0)]
    pub late_limit_us: u32,
    /// Name of the simulated printer shared by several cadence-mcu processes (iceoryx2).
    #[arg(long, value_name = "ID")]
    pub world: Option<String>,
    /// A stepper (by its step pin) driving an axis: position = START_MM + steps / STEPS_PER_MM.
    #[arg(long = "axis", value_name = "AXIS=STEP_PIN,STEPS_PER_MM,START_MM", value_parser = parse_axis)]
    pub axes: Vec<AxisSpec>,
    /// An endstop input reading 1 while COORD is at or below (min) / at or above (max)
    /// TRIGGER_MM; COORD is an axis (`x`) or a linear combination of axes (`0.5*a+0.5*b`).
    #[arg(long = "endstop", value_name = "PIN=COORD,TRIGGER_MM,min|max", value_parser = parse_endstop)]
    pub endstops: Vec<EndstopSpec>,
    /// A BLTouch: its sensor output on SENSOR_PIN (`!`: reads 0 when triggered), its servo
    /// input on CONTROL_PIN, its pin touching the bed where COORD (the toolhead's Z) reaches
    /// SURFACE_MM; optionally a fault: `stuck` (never raises) or `mute` (never reports).
    #[arg(long = "bltouch", value_name = "[!]SENSOR_PIN=CONTROL_PIN,COORD,SURFACE_MM[,stuck|mute]",
          value_parser = parse_bltouch)]
    pub bltouch: Vec<BlTouchSpec>,
    /// A Duet3D Smart Effector's programming input on CONTROL_PIN (`!`: the line's 1 is a low
    /// pin): it decodes the host's 1000 bit/s commands and reports its sensitivity at exit.
    #[arg(long = "smart-effector", value_name = "[!]CONTROL_PIN", value_parser = parse_smart_effector)]
    pub smart_effectors: Vec<super::smart_effector::SmartEffectorSpec>,
    /// A TMC driver (tmc2130, tmc2208, tmc2209, tmc2240, tmc2660, tmc5160) on UART line BUS_PIN at address ADDR
    /// (behind an analog mux: reached while each SELECT_PIN is high, or low with `!`),
    /// or with chip select BUS_PIN (SPI); optionally its DIAG (or DIAG0 with `diag0:`) wired to
    /// DIAG_PIN, the motor stalling when COORD reaches END_MM (min or max end of travel).
    #[arg(long = "tmc", value_name = "MODEL@BUS_PIN:ADDR[+[!]SELECT_PIN…][=[diag0:]DIAG_PIN,COORD,END_MM,min|max]",
          value_parser = parse_tmc)]
    pub tmc: Vec<TmcSpec>,
    /// The bed surface probe input PIN (an `--endstop` or `--bltouch` sensor) touches: its
    /// trigger coordinate plus `TILT_X·x + TILT_Y·y + WARP·sin(2πx/PERIOD)·sin(2πy/PERIOD)` at
    /// the probe's bed point (toolhead XCOORD, YCOORD plus the offsets).
    #[arg(long = "bed-surface", value_name = "PIN=XCOORD,YCOORD,X_OFFSET,Y_OFFSET,TILT_X,TILT_Y,WARP,PERIOD",
          value_parser = super::surface::SurfaceSpec::parse)]
    pub surfaces: Vec<super::surface::SurfaceSpec>,
    /// The probe on input PIN rides a gantry lifted by 2 to 4 Z motors (world axes AXIS at
    /// X, Y; 4: the corners of a rectangle): its height is the gantry's at the probe (toolhead
    /// XCOORD, YCOORD plus offsets).
    #[arg(long = "gantry", value_name = "PIN=XCOORD,YCOORD,X_OFFSET,Y_OFFSET,AXIS:X:Y,AXIS:X:Y[,AXIS:X:Y[,AXIS:X:Y]]",
          value_parser = super::surface::GantrySpec::parse)]
    pub gantries: Vec<super::surface::GantrySpec>,
    /// A heater output and the thermistor ADC input it warms (100K NTC beta 3950, 4.7k pull-up),
    /// with the thermal model of a 40 W hotend (default) or a 150 W bed; `!HEATER_PIN`: the
    /// heater is on while its pin is low.
    #[arg(long = "heater", value_name = "[!]HEATER_PIN=SENSOR_PIN[,hotend|bed]", value_parser = parse_heater)]
    pub heaters: Vec<HeaterSpec>,
    /// A fan powered by OUT_PIN (software or hardware PWM) whose tachometer drives TACH_PIN
    /// with PPR pulses per revolution (default 2).
    #[arg(long = "fan", value_name = "OUT_PIN=TACH_PIN[,PPR]", value_parser = super::fan::FanSpec::parse)]
    pub fans: Vec<super::fan::FanSpec>,
    /// The ADC's reference inputs (a Duet's `vref_pin` and `vssa_pin`): every analog reading
    /// then carries the ADC's offset and gain error, which the references measure.
    #[arg(long = "adc-ref", value_name = "VREF_PIN=VSSA_PIN", value_parser = super::adc_ref::AdcRefSpec::parse)]
    pub adc_refs: Vec<super::adc_ref::AdcRefSpec>,
    /// The response of the sensor on analog input SENSOR_PIN (a heater's, or one at ambient):
    /// its ADC fraction of full scale at rising temperatures, interpolated (default: a 100K
    /// NTC β3950 under 4.7k). The host passes its configured sensor's.
    #[arg(long = "sensor-curve", value_name = "SENSOR_PIN=T:FRACTION/T:FRACTION/...",
          value_parser = parse_sensor_curve)]
    pub sensor_curves: Vec<SensorCurveSpec>,
    /// Publish heater HEATER_PIN's sensor temperature to the world (`--world`) as NAME, for a
    /// sensor on another MCU (`--remote-sensor`).
    #[arg(long = "heater-export", value_name = "HEATER_PIN=NAME", value_parser = parse_pin_name)]
    pub heater_exports: Vec<(u8, String)>,
    /// Analog input SENSOR_PIN reads the temperature another MCU's heater publishes as NAME
    /// (`--heater-export`), through its `--sensor-curve`.
    #[arg(long = "remote-sensor", value_name = "SENSOR_PIN=NAME", value_parser = parse_pin_name)]
    pub remote_sensors: Vec<(u8, String)>,
    /// An SPI temperature chip (MAX6675, MAX31855, MAX31856, MAX31865) on chip select CS_PIN,
    /// measuring the heater whose sensor pin is CS_PIN (else ambient); a MAX31865's RTD and
    /// reference resistors (Ω, default 100 and 430).
    #[arg(long = "spi-sensor", value_name = "CS_PIN=CHIP[,RTD_NOMINAL,RTD_REFERENCE]",
          value_parser = super::spi_sensor::SpiSensorSpec::parse)]
    pub spi_sensors: Vec<super::spi_sensor::SpiSensorSpec>,
    /// Inject a heater fault from SECONDS of MCU time on: `open` (thermistor open, ADC at
    /// max), `no-heat` (the heater stops heating), `frozen` (the reading stops changing).
    #[arg(long = "heater-fault", value_name = "HEATER_PIN=open|no-heat|frozen@SECONDS",
          value_parser = parse_heater_fault)]
    pub heater_faults: Vec<HeaterFaultSpec>,
    /// Drop this fraction (0..=1) of outgoing bytes.
    #[arg(long, value_name = "RATE", default_value_t = 0.0, value_parser = parse_rate)]
    pub drop_tx: f64,
    /// Seed of the byte-dropping generator.
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub fault_seed: u64,
    /// Hold every outgoing byte this long before writing it.
    #[arg(long, value_name = "MS", default_value_t = 0)]
    pub tx_delay_ms: u64,
    /// Freeze (stop processing entirely) this long after start ...
    #[arg(long, value_name = "MS", requires = "freeze_ms")]
    pub freeze_after_ms: Option<u64>,
    /// ... for this long.
    #[arg(long, value_name = "MS", requires = "freeze_after_ms")]
    pub freeze_ms: Option<u64>,
    /// Busy-wait at most US µs (wall time) before each timer, and at most US µs in a row: the
    /// loop sleeps until US before the next timer, then spins; when timers are denser than
    /// that it sleeps anyway once the US are used up, so it never keeps a core busy. 0 =
    /// never busy-wait (lowest CPU use, later steps).
    #[arg(long, value_name = "US", default_value_t = 50,
          value_parser = clap::value_parser!(u64).range(0..=100_000))]
    pub spin_us: u64,
    /// Keep running when the host closes the pty, as a powered board does: the next host to
    /// open it reconnects (Klipper's host closes and reopens the port for RESTART and
    /// FIRMWARE_RESTART). Default: exit when the host hangs up.
    #[arg(long)]
    pub keep_open: bool,
    /// Real time (off by default): pin the simulator's loop thread to CPU core N.
    #[arg(
        long,
        value_name = "N",
        help_heading = "Real time (refusals are reported once on stderr; the simulator then runs without)"
    )]
    pub cpu: Option<usize>,
    /// Real time: run the loop thread under SCHED_FIFO at priority PRIO (1..=99; needs
    /// CAP_SYS_NICE or RLIMIT_RTPRIO).
    #[arg(long, value_name = "PRIO", help_heading = "Real time (refusals are reported once on stderr; the simulator then runs without)",
          value_parser = clap::value_parser!(i32).range(1..=99))]
    pub fifo: Option<i32>,
    /// Real time: lock all memory in RAM (mlockall; needs CAP_IPC_LOCK or a large
    /// RLIMIT_MEMLOCK) and prefault the loop thread's stack.
    #[arg(
        long,
        help_heading = "Real time (refusals are reported once on stderr; the simulator then runs without)"
    )]
    pub lock_memory: bool,
}

impl Cli {
    /// The real-time requests of `--cpu`, `--fifo` and `--lock-memory` (nothing by default).
    pub fn rt_spec(&self) -> rt_core::os::RtSpec {
        rt_core::os::RtSpec {
            core: self.cpu,
            fifo_priority: self.fifo,
            lock_memory: self.lock_memory,
            prefault_stack: if self.lock_memory { PREFAULT_STACK } else { 0 },
            ..rt_core::os::RtSpec::new("cadence-mcu")
        }
    }

    /// True if any real-time option was given.
    pub fn wants_rt(&self) -> bool {
        self.cpu.is_some() || self.fifo.is_some() || self.lock_memory
    }
}

/// Stack prefaulted by `--lock-memory` (the loop thread's stack is far larger).
pub const PREFAULT_STACK: usize = 1 << 20;

/// A pin by name (any family of [`links::pinmap`]: `PA0`, `PC13`, `P1.22`, `gpio17`,
/// `gpio1_23`) or by number (0..=255).
pub fn parse_pin(s: &str) -> Result<u8, String> {
    let s = s.trim();
    if s.bytes().all(|c| c.is_ascii_digit()) && !s.is_empty() {
        return s
            .parse::<u8>()
            .map_err(|_| format!("pin {s} is out of range (0..256)"));
    }
    pinmap::pin_number(s).ok_or_else(|| {
        format!("`{s}` is not a pin (PA0..PL15, PA16..PD31, P0.0..P4.31, gpio0..gpio63, gpio0_0..gpio3_31, gpiochip0/gpio0..gpiochip6/gpio31, analog0..analog31 or a number)")
    })
}

fn parse_f64(s: &str, what: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        _ => Err(format!("{what} `{s}` is not a number")),
    }
}

fn parse_axis_name(s: &str) -> Result<String, String> {
    let s = s.trim();
    if s.is_empty() || s.len() > super::world::NAME_LEN {
        return Err(format!("axis name `{s}` must have 1 to 8 bytes"));
    }
    Ok(s.to_owned())
}

fn parse_axis(s: &str) -> Result<AxisSpec, String> {
    let (name, rest) = s
        .split_once('=')
        .ok_or("expected AXIS=STEP_PIN,STEPS_PER_MM,START_MM")?;
    let f: Vec<&str> = rest.split(',').collect();
    let [pin, spm, start] = f.as_slice() else {
        return Err("expected AXIS=STEP_PIN,STEPS_PER_MM,START_MM".into());
    };
    let steps_per_mm = parse_f64(spm, "steps per mm")?;
    if steps_per_mm == 0.0 {
        return Err("steps per mm must not be 0".into());
    }
    Ok(AxisSpec {
        name: parse_axis_name(name)?,
        step_pin: parse_pin(pin)?,
        steps_per_mm,
        start_mm: parse_f64(start, "start position")?,
    })
}

fn parse_endstop(s: &str) -> Result<EndstopSpec, String> {
    let (pin, rest) = s
        .split_once('=')
        .ok_or("expected [!]PIN=COORD,TRIGGER_MM,min|max")?;
    let f: Vec<&str> = rest.split(',').collect();
    let [axis, at, side] = f.as_slice() else {
        return Err("expected [!]PIN=COORD,TRIGGER_MM,min|max".into());
    };
    let (active_low, pin) = match pin.trim().strip_prefix('!') {
        Some(p) => (true, p),
        None => (false, pin),
    };
    let at_min = match side.trim() {
        "min" => true,
        "max" => false,
        other => return Err(format!("`{other}` is neither min nor max")),
    };
    Ok(EndstopSpec {
        pin: parse_pin(pin)?,
        axis: Coord::parse(axis).map_err(|e| e.to_string())?,
        trigger_mm: parse_f64(at, "trigger position")?,
        at_min,
        active_low,
    })
}

fn parse_bltouch(s: &str) -> Result<BlTouchSpec, String> {
    const FORM: &str = "expected [!]SENSOR_PIN=CONTROL_PIN,COORD,SURFACE_MM[,stuck|mute]";
    let (pin, rest) = s.split_once('=').ok_or(FORM)?;
    let f: Vec<&str> = rest.split(',').collect();
    let (control, coord, surface, fault) = match f.as_slice() {
        [c, z, s] => (c, z, s, None),
        [c, z, s, f] => (c, z, s, Some(*f)),
        _ => return Err(FORM.into()),
    };
    let (active_low, pin) = match pin.trim().strip_prefix('!') {
        Some(p) => (true, p),
        None => (false, pin),
    };
    let fault = match fault.map(str::trim) {
        None => None,
        Some("stuck") => Some(BlTouchFault::Stuck),
        Some("mute") => Some(BlTouchFault::Mute),
        Some(other) => return Err(format!("`{other}` is neither stuck nor mute")),
    };
    Ok(BlTouchSpec {
        sensor_pin: parse_pin(pin)?,
        control_pin: parse_pin(control)?,
        coord: Coord::parse(coord).map_err(|e| e.to_string())?,
        surface_mm: parse_f64(surface, "surface position")?,
        active_low,
        fault,
    })
}

fn parse_smart_effector(s: &str) -> Result<super::smart_effector::SmartEffectorSpec, String> {
    let (active_low, pin) = match s.trim().strip_prefix('!') {
        Some(p) => (true, p),
        None => (false, s.trim()),
    };
    Ok(super::smart_effector::SmartEffectorSpec {
        control_pin: parse_pin(pin)?,
        active_low,
    })
}

fn parse_tmc(s: &str) -> Result<TmcSpec, String> {
    const FORM: &str = "expected MODEL@BUS_PIN:ADDR[+[!]SELECT_PIN…][=[diag0:]DIAG_PIN,COORD,END_MM,min|max]";
    let (bus, diag) = match s.split_once('=') {
        Some((b, d)) => (b, Some(d)),
        None => (s, None),
    };
    let mut parts = bus.split('+');
    let bus = parts.next().unwrap_or_default();
    let select = parts
        .map(|p| match p.trim().strip_prefix('!') {
            Some(pin) => parse_pin(pin).map(|n| (n, false)),
            None => parse_pin(p.trim()).map(|n| (n, true)),
        })
        .collect::<Result<Vec<_>, _>>()?;
    let (model, rest) = bus.split_once('@').ok_or(FORM)?;
    let (pin, addr) = rest.split_once(':').ok_or(FORM)?;
    let model = TmcModel::parse(model.trim())
        .ok_or_else(|| format!("`{model}` is not tmc2130, tmc2208, tmc2209, tmc2240, tmc2660 or tmc5160"))?;
    let address: u8 = addr.trim().parse().map_err(|_| format!("bad address `{addr}`"))?;
    let diag = match diag {
        None => None,
        Some(d) => {
            let f: Vec<&str> = d.split(',').collect();
            let [pin, coord, end, side] = f.as_slice() else {
                return Err(FORM.into());
            };
            let (diag0, pin) = match pin.trim().strip_prefix("diag0:") {
                Some(p) => (true, p),
                None => (false, *pin),
            };
            let at_min = match side.trim() {
                "min" => true,
                "max" => false,
                other => return Err(format!("`{other}` is neither min nor max")),
            };
            Some(TmcDiagSpec {
                pin: parse_pin(pin)?,
                coord: Coord::parse(coord).map_err(|e| e.to_string())?,
                end_mm: parse_f64(end, "end of travel")?,
                at_min,
                diag0,
            })
        }
    };
    Ok(TmcSpec {
        model,
        bus_pin: parse_pin(pin)?,
        address,
        diag,
        select,
    })
}

/// `--heater`: pins and thermal model.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeaterSpec {
    /// Heater output pin.
    pub heater_pin: u8,
    /// Thermistor ADC pin.
    pub sensor_pin: u8,
    /// Thermal constants.
    pub model: ThermalModel,
    /// `!HEATER_PIN`: the heater is on while the pin is low (an inverted `heater_pin`).
    pub active_low: bool,
}

/// `--sensor-curve`: an analog input and its sensor's response.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorCurveSpec {
    /// The sensor's ADC pin.
    pub sensor_pin: u8,
    /// Its response.
    pub curve: super::sensor_curve::SensorCurve,
}

fn parse_sensor_curve(s: &str) -> Result<SensorCurveSpec, String> {
    let (pin, table) = s
        .split_once('=')
        .ok_or("expected SENSOR_PIN=T:FRACTION/T:FRACTION/...")?;
    Ok(SensorCurveSpec {
        sensor_pin: parse_pin(pin)?,
        curve: super::sensor_curve::SensorCurve::parse(table)?,
    })
}

/// `--heater-fault`: which heater, what, from when.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeaterFaultSpec {
    /// The faulty heater's output pin.
    pub heater_pin: u8,
    /// The fault.
    pub fault: HeaterFault,
    /// MCU seconds from which it applies.
    pub from_s: f64,
}

fn parse_heater(s: &str) -> Result<HeaterSpec, String> {
    let (h, rest) = s
        .split_once('=')
        .ok_or("expected HEATER_PIN=SENSOR_PIN[,hotend|bed]")?;
    let (t, kind) = rest.split_once(',').unwrap_or((rest, "hotend"));
    let model = match kind {
        "hotend" => ThermalModel::HOTEND,
        "bed" => ThermalModel::BED,
        other => return Err(format!("`{other}` is neither hotend nor bed")),
    };
    let (active_low, h) = match h.trim().strip_prefix('!') {
        Some(pin) => (true, pin),
        None => (false, h),
    };
    Ok(HeaterSpec {
        heater_pin: parse_pin(h)?,
        sensor_pin: parse_pin(t)?,
        model,
        active_low,
    })
}

/// `PIN=NAME` (NAME: 1 to 8 bytes, a world value's name).
fn parse_pin_name(s: &str) -> Result<(u8, String), String> {
    let (pin, name) = s.split_once('=').ok_or("expected PIN=NAME")?;
    let name = name.trim();
    if name.is_empty() || name.len() > super::world::NAME_LEN {
        return Err(format!(
            "name `{name}` must be 1 to {} bytes",
            super::world::NAME_LEN
        ));
    }
    Ok((parse_pin(pin)?, name.to_string()))
}

fn parse_heater_fault(s: &str) -> Result<HeaterFaultSpec, String> {
    let (h, rest) = s
        .split_once('=')
        .ok_or("expected HEATER_PIN=open|no-heat|frozen@SECONDS")?;
    let (kind, at) = rest
        .split_once('@')
        .ok_or("expected the fault's start time in MCU seconds after `@`")?;
    let fault = match kind {
        "open" => HeaterFault::OpenThermistor,
        "no-heat" => HeaterFault::NoHeat,
        "frozen" => HeaterFault::FrozenSensor,
        other => return Err(format!("`{other}` is not open, no-heat or frozen")),
    };
    let from_s = parse_f64(at, "fault time")?;
    if from_s.is_nan() || from_s < 0.0 {
        return Err(format!("fault time `{at}` is negative"));
    }
    Ok(HeaterFaultSpec {
        heater_pin: parse_pin(h)?,
        fault,
        from_s,
    })
}

fn parse_rate(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if (0.0..=1.0).contains(&v) => Ok(v),
        _ => Err(format!("`{s}` is not a fraction in 0..=1")),
    }
}

fn parse_time_scale(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("`{s}` is not a positive number")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// `--bltouch` reads its pins, coordinate, surface and fault.
        #[test]
        fn bltouch_spec(z in -10.0f64..10.0) {
            let b = parse_bltouch(&format!("!PA4=PA5,z,{z},stuck")).map_err(TestCaseError::fail)?;
            prop_assert_eq!((b.sensor_pin, b.control_pin, b.active_low), (4, 5, true));
            prop_assert_eq!((b.surface_mm, b.fault), (z, Some(BlTouchFault::Stuck)));
            let b = parse_bltouch("PA4=PA5,z,0").map_err(TestCaseError::fail)?;
            prop_assert_eq!((b.active_low, b.fault), (false, None));
            prop_assert!(parse_bltouch("PA4=PA5,z,0,wobbly").is_err());
            prop_assert!(parse_bltouch("PA4=PA5,z").is_err());
            let e = parse_smart_effector("!PA5").map_err(TestCaseError::fail)?;
            prop_assert!(e.active_low);
            prop_assert!(!parse_smart_effector("PA5").map_err(TestCaseError::fail)?.active_low);
            prop_assert!(parse_smart_effector("nope").is_err());
        }

        /// Pin names round-trip; no input makes a parser panic.
        #[test]
        fn parsers_never_panic(s in ".{0,40}", pin in 0u8..96) {
            let name = format!("P{}{}", pinmap::PORT_LETTERS[(pin / 8) as usize] as char, pin % 8);
            prop_assert_eq!(parse_pin(&name), Ok(pin));
            prop_assert_eq!(parse_pin(&pin.to_string()), Ok(pin));
            let _ = parse_pin(&s);
            let _ = parse_axis(&s);
            let _ = parse_endstop(&s);
            let _ = parse_bltouch(&s);
            let _ = parse_tmc(&s);
            let _ = parse_heater(&s);
            let _ = parse_sensor_curve(&s);
            let _ = parse_rate(&s);
        }
    }

    #[test]
    fn tmc_spec() {
        let t = parse_tmc("tmc2209@PD1:3=PD2,x,0,min").unwrap();
        assert_eq!(
            (
                t.model,
                t.address,
                t.diag.as_ref().map(|d| (d.end_mm, d.at_min, d.diag0))
            ),
            (TmcModel::Tmc2209, 3, Some((0.0, true, false)))
        );
        let t = parse_tmc("tmc5160@PA4:0=diag0:PA5,0.5*a+0.5*b,220,max").unwrap();
        assert!(t.diag.as_ref().is_some_and(|d| d.diag0 && !d.at_min));
        assert!(parse_tmc("tmc2130@PA4:0").is_ok_and(|t| t.diag.is_none()));
        let t = parse_tmc("tmc2209@PA9:0+!PC14+PC16=PD2,x,0,min").unwrap();
        assert_eq!(
            t.select,
            [
                (parse_pin("PC14").unwrap(), false),
                (parse_pin("PC16").unwrap(), true)
            ]
        );
        assert!(t.diag.is_some());
        assert!(parse_tmc("tmc2660@PA4:0").is_ok_and(|t| t.model == TmcModel::Tmc2660));
        for bad in [
            "tmc2661@PA4:0",
            "tmc2209@PA4",
            "tmc2209@PA4:x",
            "tmc2209@PA4:0=PA5,x,0,mid",
            "tmc2209@PA4:0=PA5,x",
        ] {
            assert!(parse_tmc(bad).is_err(), "{bad}");
        }
    }

    fn parse(args: &[&str]) -> Result<Cli, clap::Error> {
        Cli::try_parse_from(std::iter::once("cadence-mcu").chain(args.iter().copied()))
    }

    #[test]
    fn defaults() {
        let c = parse(&[]).unwrap();
        assert_eq!(c.clock_freq, 50_000_000);
        assert_eq!(c.time_scale, 1.0);
        assert_eq!(c.move_count, 16384);
        assert_eq!(c.trace_format, TraceFormatArg::Bin);
        assert!(c.trace.is_none() && c.pty_link.is_none());
        assert_eq!(c.spin_us, 50);
        assert!(!c.wants_rt(), "real time is off by default");
        let spec = c.rt_spec();
        assert_eq!(
            (spec.core, spec.fifo_priority, spec.lock_memory),
            (None, None, false)
        );
        assert_eq!(spec.prefault_stack, 0);
    }

    #[test]
    fn real_time_and_spin_options() {
        let c = parse(&["--cpu", "1", "--fifo", "40", "--lock-memory", "--spin-us", "0"]).unwrap();
        assert!(c.wants_rt());
        let spec = c.rt_spec();
        assert_eq!(spec.core, Some(1));
        assert_eq!(spec.fifo_priority, Some(40));
        assert!(spec.lock_memory);
        assert_eq!(spec.prefault_stack, PREFAULT_STACK);
        assert_eq!(spec.name, "cadence-mcu");
        assert_eq!(c.spin_us, 0);
        assert!(parse(&["--cpu", "1"]).unwrap().wants_rt());
        for bad in [
            &["--fifo", "0"][..],
            &["--fifo", "100"],
            &["--cpu", "-1"],
            &["--spin-us", "100001"],
            &["--lock-memory", "yes"],
        ] {
            assert!(parse(bad).is_err(), "{bad:?}");
        }
        let help = Cli::command().render_long_help().to_string();
        for opt in ["--cpu", "--fifo", "--lock-memory", "--spin-us", "Real time"] {
            assert!(help.contains(opt), "{opt} missing from --help");
        }
    }

    #[test]
    fn all_options() {
        let c = parse(&[
            "--pty-link",
            "/tmp/x",
            "--clock-freq",
            "1000000",
            "--time-scale",
            "10",
            "--trace",
            "t.csv",
            "--trace-format",
            "csv",
            "--move-count",
            "500",
        ])
        .unwrap();
        assert_eq!(c.pty_link.as_deref(), Some(std::path::Path::new("/tmp/x")));
        assert_eq!((c.clock_freq, c.time_scale, c.move_count), (1_000_000, 10.0, 500));
        assert_eq!(c.trace_format, TraceFormatArg::Csv);
    }

    #[test]
    fn world_fault_and_heater_options() {
        let c = parse(&[
            "--world",
            "printer1",
            "--axis",
            "z=PC2,400,5.5",
            "--axis",
            "x=3,80,0",
            "--endstop",
            "PD1=z,0.25,min",
            "--endstop",
            "7=x,200,max",
            "--heater",
            "PE0=PF1",
            "--heater",
            "PE1=PF2,bed",
            "--heater-fault",
            "PE1=frozen@90.5",
            "--drop-tx",
            "0.01",
            "--fault-seed",
            "42",
            "--tx-delay-ms",
            "30",
            "--freeze-after-ms",
            "500",
            "--freeze-ms",
            "100",
            "--late-limit-us",
            "1000",
        ])
        .unwrap();
        assert_eq!(c.world.as_deref(), Some("printer1"));
        assert_eq!(
            c.axes[0],
            AxisSpec {
                name: "z".into(),
                step_pin: 18,
                steps_per_mm: 400.0,
                start_mm: 5.5
            }
        );
        assert_eq!(c.axes[1].step_pin, 3);
        assert_eq!(
            c.endstops[0],
            EndstopSpec {
                pin: 25,
                axis: Coord::axis("z"),
                trigger_mm: 0.25,
                at_min: true,
                active_low: false
            }
        );
        assert!(!c.endstops[1].at_min);
        let inverted = parse(&["--endstop", "!PA15=x,0,min"]).unwrap();
        assert_eq!(
            (inverted.endstops[0].pin, inverted.endstops[0].active_low),
            (103, true)
        );
        assert_eq!(
            (
                c.heaters[0].heater_pin,
                c.heaters[0].sensor_pin,
                c.heaters[0].model
            ),
            (32, 41, ThermalModel::HOTEND)
        );
        assert_eq!(c.heaters[1].model, ThermalModel::BED);
        assert!(!c.heaters[0].active_low);
        let low = parse_heater("!PA20=PC15,hotend").unwrap();
        assert!(low.active_low && low.heater_pin == parse_pin("PA20").unwrap());
        assert_eq!(
            c.heater_faults,
            [HeaterFaultSpec {
                heater_pin: 33,
                fault: HeaterFault::FrozenSensor,
                from_s: 90.5
            }]
        );
        for bad in [
            "PE0=PF1,oven",
            "PE0",
            "PE0=melt@1",
            "PE0=open",
            "PE0=open@-1",
            "PE0=open@x",
        ] {
            let arg = if bad.contains('@') || bad == "PE0" {
                "--heater-fault"
            } else {
                "--heater"
            };
            assert!(parse(&[arg, bad]).is_err(), "{bad}");
        }
        assert_eq!((c.drop_tx, c.fault_seed, c.tx_delay_ms), (0.01, 42, 30));
        assert_eq!((c.freeze_after_ms, c.freeze_ms), (Some(500), Some(100)));
        assert_eq!(c.late_limit_us, 1000);
        let c = parse(&[
            "--endstop",
            "PA3=0.5*a+0.5*b,0,min",
            "--endstop",
            "PB3=0.5*a-0.5*b,0,max",
        ])
        .unwrap();
        assert_eq!(c.endstops[0].axis.to_string(), "0.5*a+0.5*b");
        assert_eq!(c.endstops[1].axis.terms[1], (-0.5, "b".to_string()));
    }

    #[test]
    fn rejects_bad_world_options() {
        for bad in [
            &["--axis", "z=PC2,0,1"][..],
            &["--axis", "z=PZ2,400,1"],
            &["--axis", "averylongname=1,1,1"],
            &["--axis", "z=1,2"],
            &["--endstop", "PA1=z,1,middle"],
            &["--endstop", "PM8=z,1,min"],
            &["--endstop", "PA1=0.5*a+,1,min"],
            &["--endstop", "PA1=half*a,1,min"],
            &["--heater", "PA1"],
            &["--drop-tx", "1.5"],
            &["--freeze-ms", "10"],
            &["--freeze-after-ms", "10"],
        ] {
            assert!(parse(bad).is_err(), "{bad:?}");
        }
        assert_eq!(parse_pin("256"), Err("pin 256 is out of range (0..256)".into()));
        assert_eq!(parse_pin("PL7"), Ok(95));
        assert_eq!(parse_pin("PA15"), Ok(103));
        assert_eq!(parse_pin("P1.22"), Ok(54));
        assert!(parse_pin("PM0").unwrap_err().contains("is not a pin"));
        assert_eq!(
            parse_endstop("PA1=a+2b,1,min").unwrap_err(),
            "coordinate `a+2b`: axis name `2b` must have 1 to 8 bytes, start with a letter or `_` and \
             hold no `+ - * , =` or whitespace"
        );
    }

    #[test]
    fn rejects_bad_values() {
        assert!(parse(&["--time-scale", "0"]).is_err());
        assert!(parse(&["--time-scale", "nan"]).is_err());
        assert!(parse(&["--clock-freq", "0"]).is_err());
        assert!(parse(&["--move-count", "0"]).is_err());
        assert!(parse(&["--move-count", "70000"]).is_err());
        assert!(parse(&["--trace-format", "xml"]).is_err());
    }
}
