//! The steppers' TMC drivers as the host drives them: their buses on the MCUs
//! (`config_tmcuart` per UART line, `config_spi` + `spi_set_sw_bus`/`spi_set_bus` per SPI
//! driver), the register writes at start (`init`), and register reads and writes through the
//! MCU link with Klipper's framing and checks (module `io`).
//!
//! Object ids: a MCU's TMC bus objects come last, after its heaters, sensors and fans
//! (`crate::mcus`), one per UART line (drivers sharing a line share it) and one per SPI driver,
//! in `[tmc…]` section order.
//!
//! The register values the host last wrote live in each driver's [`TmcState`], shared by the
//! G-code commands (module `gcode`) and sensorless homing (module `sensorless`).

mod error;
pub mod gcode;
pub mod idle;
pub mod io;
pub mod sensorless;

pub use error::TmcError;

use std::sync::{Arc, Mutex};

use links::dict::{Cmd, Dictionary};
use sysconfig::printer::tmc::FieldSet;
use sysconfig::printer::{PrinterConfig, TmcBus, TmcModel, TmcSection};

/// Klipper's TMC UART bit rate (bits per second).
pub const TMC_BAUD_RATE: f64 = 40_000.0;
/// SPI mode of the TMC drivers.
pub const SPI_MODE: i64 = 3;

/// What the host knows of a driver between commands.
#[derive(Debug, Clone)]
pub struct TmcState {
    /// Register values as last written.
    pub fields: FieldSet,
    /// The hold current last asked for (A).
    pub req_hold_current: f64,
    /// The run current last asked for (A): the base of a TMC2660's idle current.
    pub req_run_current: f64,
    /// A TMC2660's idle current is in (module `idle`).
    pub idle: bool,
    /// UART: the driver's write counter as last read.
    pub ifcnt: Option<u8>,
}

/// One driver.
#[derive(Debug, Clone)]
pub struct TmcOut {
    pub cfg: TmcSection,
    /// Index of its bus in [`buses_on`] of its MCU.
    pub bus: usize,
    pub state: Arc<Mutex<TmcState>>,
}

impl TmcOut {
    /// The MCU its bus is on.
    pub fn mcu(&self) -> &str {
        self.cfg.bus.mcu()
    }

    /// Locks its state (a poisoned lock still holds the last values).
    pub fn lock(&self) -> std::sync::MutexGuard<'_, TmcState> {
        self.state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }
}

/// The drivers of a config, each with its bus index on its MCU.
pub fn drivers(cfg: &PrinterConfig) -> Vec<TmcOut> {
    let mut out: Vec<TmcOut> = Vec::new();
    for t in &cfg.tmc {
        let mcu = t.bus.mcu();
        let shares = |o: &TmcOut| match (&o.cfg.bus, &t.bus) {
            (
                TmcBus::Uart {
                    uart_pin: a,
                    tx_pin: ta,
                    ..
                },
                TmcBus::Uart {
                    uart_pin: b,
                    tx_pin: tb,
                    ..
                },
            ) => a.mcu == b.mcu && a.pin == b.pin && ta == tb,
            // The drivers of one SPI daisy chain share its chip select.
            (
                TmcBus::Spi {
                    cs_pin: a,
                    chain: Some(_),
                    ..
                },
                TmcBus::Spi {
                    cs_pin: b,
                    chain: Some(_),
                    ..
                },
            ) => a.mcu == b.mcu && a.pin == b.pin,
            _ => false,
        };
        let bus = match out.iter().find(|o| shares(o)) {
            Some(o) => o.bus,
            None => out
                .iter()
                .filter(|o| o.mcu() == mcu)
                .map(|o| o.bus + 1)
                .max()
                .unwrap_or(0),
        };
        out.push(TmcOut {
            cfg: t.clone(),
            bus,
            state: Arc::new(Mutex::new(TmcState {
                fields: t.fields.clone(),
                req_hold_current: t.hold_current,
                req_run_current: t.run_current,
                idle: false,
                ifcnt: None,
            })),
        });
    }
    out
}

/// The number of bus objects on MCU `mcu`.
pub fn bus_count(drivers: &[TmcOut], mcu: &str) -> usize {
    drivers
        .iter()
        .filter(|d| d.mcu() == mcu)
        .map(|d| d.bus + 1)
        .max()
        .unwrap_or(0)
}

/// The analog muxes of MCU `mcu`'s UART lines (`select_pins`), in bus order: each muxed bus
/// with its select pins (as its first driver names them; every driver behind one mux names the
/// same pins). Their outputs are objects after the buses.
pub fn muxes(drivers: &[TmcOut], mcu: &str) -> Vec<(usize, Vec<sysconfig::printer::PinRef>)> {
    (0..bus_count(drivers, mcu))
        .filter_map(|bus| {
            let d = drivers.iter().find(|d| d.mcu() == mcu && d.bus == bus)?;
            match &d.cfg.bus {
                TmcBus::Uart { select_pins, .. } if !select_pins.is_empty() => {
                    Some((bus, select_pins.clone()))
                }
                _ => None,
            }
        })
        .collect()
}

/// The number of TMC objects on MCU `mcu`: its buses, then its muxes' select outputs.
pub fn object_count(drivers: &[TmcOut], mcu: &str) -> usize {
    bus_count(drivers, mcu) + muxes(drivers, mcu).iter().map(|(_, p)| p.len()).sum::<usize>()
}

/// Driver `drv`'s mux selection: each select output's offset from the MCU's first TMC object
/// and the level that selects `drv` (high, low for `!PIN`). Empty without a mux.
pub fn mux_selection(drivers: &[TmcOut], drv: &TmcOut) -> Vec<(usize, bool)> {
    let TmcBus::Uart { select_pins, .. } = &drv.cfg.bus else {
        return Vec::new();
    };
    let mut offset = bus_count(drivers, drv.mcu());
    for (bus, pins) in muxes(drivers, drv.mcu()) {
        if bus == drv.bus {
            return select_pins
                .iter()
                .enumerate()
                .map(|(k, p)| (offset + k, !p.invert))
                .collect();
        }
        offset += pins.len();
    }
    Vec::new()
}

/// The configuration commands of MCU `mcu`'s TMC buses, the first with oid `oid0`.
pub fn config_commands(
    dict: &Dictionary,
    drivers: &[TmcOut],
    mcu: &str,
    oid0: usize,
    clock_freq: f64,
) -> Result<Vec<Cmd>, TmcError> {
    let mut cmds = Vec::new();
    for bus in 0..bus_count(drivers, mcu) {
        let Some(d) = drivers.iter().find(|d| d.mcu() == mcu && d.bus == bus) else {
            continue;
        };
        let oid = (oid0 + bus) as i64;
        let name = d.cfg.section_name();
        let pin = |p: &sysconfig::printer::PinRef, option: &'static str| {
            dict.pin(&p.pin).map(i64::from).map_err(|source| TmcError::Pin {
                section: name.clone(),
                option,
                source,
            })
        };
        match &d.cfg.bus {
            TmcBus::Uart { uart_pin, tx_pin, .. } => {
                let rx = pin(uart_pin, "uart_pin")?;
                let tx = match tx_pin {
                    Some(t) => pin(t, "tx_pin")?,
                    None => rx,
                };
                let bit_time = (clock_freq / TMC_BAUD_RATE).round() as i64;
                cmds.push(dict.encode("config_tmcuart", &[oid, rx, uart_pin.pullup as i64, tx, bit_time])?);
            }
            TmcBus::Spi {
                cs_pin,
                speed,
                software,
                bus,
                ..
            } => {
                let software = match software {
                    Some([sclk, mosi, miso]) => Some((
                        pin(miso, "spi_software_miso_pin")?,
                        pin(mosi, "spi_software_mosi_pin")?,
                        pin(sclk, "spi_software_sclk_pin")?,
                    )),
                    None => None,
                };
                let pins = crate::spi_device::SpiPins {
                    cs: pin(cs_pin, "cs_pin")?,
                    software,
                };
                // The TMC2660 takes SPI mode 0, the others mode 3.
                let mode = match d.cfg.model {
                    TmcModel::Tmc2660 => 0,
                    _ => SPI_MODE,
                };
                cmds.extend(crate::spi_device::config_commands(
                    dict,
                    clock_freq,
                    oid,
                    pins,
                    bus.as_deref(),
                    mode,
                    *speed,
                )?);
            }
        }
    }
    // Each mux's select outputs, low until a transfer selects a driver (Klipper's).
    let mut oid = oid0 + bus_count(drivers, mcu);
    for (bus, pins) in muxes(drivers, mcu) {
        for p in &pins {
            let pin = dict.pin(&p.pin).map(i64::from).map_err(|source| TmcError::Pin {
                section: format!("tmc bus {bus}"),
                option: "select_pins",
                source,
            })?;
            cmds.push(dict.encode("config_digital_out", &[oid as i64, pin, 0, 0, 0])?);
            oid += 1;
        }
    }
    Ok(cmds)
}

/// `--tmc` arguments of the simulated MCU `mcu`: each driver on its bus pin, with its DIAG
/// wired (for a driver a stepper homes on) to its diag pin, stalling where that stepper's
/// endstop would trigger (`coord`, `end_mm`, `min`/`max`, from the caller).
pub fn sim_args(drivers: &[TmcOut], mcu: &str, diag: impl Fn(&TmcOut) -> Option<String>) -> Vec<String> {
    let mut args = Vec::new();
    for d in drivers.iter().filter(|d| d.mcu() == mcu) {
        let (pin, addr, select) = match &d.cfg.bus {
            TmcBus::Uart {
                uart_pin,
                address,
                select_pins,
                ..
            } => (&uart_pin.pin, *address, select_pins.as_slice()),
            TmcBus::Spi { cs_pin, chain, .. } => (&cs_pin.pin, chain.map_or(0, |(_, p)| p), &[][..]),
        };
        let mut spec = format!("{}@{pin}:{addr}", d.cfg.model.kind());
        for s in select {
            spec.push('+');
            if s.invert {
                spec.push('!');
            }
            spec.push_str(&s.pin);
        }
        if let Some(diag) = diag(d) {
            spec.push('=');
            spec.push_str(&diag);
        }
        args.push("--tmc".to_string());
        args.push(spec);
    }
    args
}
