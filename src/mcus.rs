//! The printer's MCUs: spawning simulated ones, connecting links, configuring objects, and
//! shutting everything down cleanly.
//!
//! Object ids per MCU: that MCU's steppers first (in machine order), then its endstops (the
//! `[probe]` last), its stepper enable pins, one trsync (homing trigger sync) object, then its
//! heaters, sensors and fans (`crate::heaters::objects`).

use std::path::{Path, PathBuf};
use std::time::Duration;

use links::dict::{Cmd, Dictionary};
use links::mcu::{LinkOptions, LinkStats, LinkTuning, McuLink};
use links::transport::{PtyTransport, SerialTransport, Transport};
use sysconfig::printer::PrinterConfig;

use crate::hardware::Machine;
use crate::sim_mcu::{SimMcu, SimOptions};

/// One connected MCU.
#[derive(Debug)]
pub struct McuConn {
    pub name: String,
    pub link: McuLink,
    sim: Option<SimMcu>,
    /// Entries of the MCU's move queue (from `config`).
    pub move_count: usize,
    /// The dictionary's nominal CLOCK_FREQ.
    pub clock_freq: f64,
    /// Oid of this MCU's trsync object.
    pub trsync_oid: u8,
    /// Oid of this MCU's first TMC bus object (`crate::tmc`).
    pub tmc_oid0: u8,
}

/// All MCUs of the printer; `list[0]` is the main `[mcu]`.
#[derive(Debug)]
pub struct Mcus {
    pub list: Vec<McuConn>,
}

/// How to start simulated MCUs.
pub struct ConnectOptions {
    pub time_scale: f64,
    /// Step trace of the main MCU; others get `-<name>` inserted before the extension.
    pub trace: Option<PathBuf>,
    /// Makes the hook each MCU's IO thread calls with the lead margin of each clocked message
    /// (argument: the MCU's index in `[mcu]` order).
    pub lead_hooks: Option<LeadHooks>,
    /// Real-time settings of each link's IO thread (`None`: normal thread).
    pub io_rt: Option<rt_core::os::RtSpec>,
}

impl std::fmt::Debug for ConnectOptions {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ConnectOptions")
            .field("time_scale", &self.time_scale)
            .field("trace", &self.trace)
            .finish_non_exhaustive()
    }
}

/// Why connecting, configuring or running an MCU failed; every variant names the MCU.
#[derive(Debug, thiserror::Error)]
pub enum McuError {
    /// The simulated MCU process did not start.
    #[error("{source}")]
    Start {
        mcu: String,
        #[source]
        source: crate::sim_mcu::SimError,
    },
    /// The serial port or pty did not open.
    #[error("mcu '{mcu}': {port}: {why}")]
    Open { mcu: String, port: String, why: String },
    /// The link did not come up (no identify answer, bad data dictionary).
    #[error("{source}")]
    Link {
        mcu: String,
        #[source]
        source: links::mcu::LinkError,
    },
    /// The MCU's data dictionary lacks what the host needs.
    #[error("mcu '{mcu}': {why}")]
    Dictionary { mcu: String, why: String },
    /// The MCU refused or did not take the configuration.
    #[error("mcu '{mcu}': {source}")]
    Configure {
        mcu: String,
        #[source]
        source: Box<ConfigureError>,
    },
    /// The MCU shut down (its reason, as it reported it).
    #[error("mcu '{mcu}' shut down: {reason}")]
    Shutdown { mcu: String, reason: String },
}

impl McuError {
    /// The MCU the error is about.
    pub fn mcu(&self) -> &str {
        match self {
            McuError::Start { mcu, .. }
            | McuError::Open { mcu, .. }
            | McuError::Link { mcu, .. }
            | McuError::Dictionary { mcu, .. }
            | McuError::Configure { mcu, .. }
            | McuError::Shutdown { mcu, .. } => mcu,
        }
    }
}

/// Why an MCU's configuration could not be built, sent or taken.
#[derive(Debug, thiserror::Error)]
pub enum ConfigureError {
    /// More objects than a u8 oid can number.
    #[error("too many objects")]
    TooManyObjects,
    /// A TMC driver's bus objects.
    #[error(transparent)]
    Tmc(Box<crate::tmc::TmcError>),
    /// A TMC driver's register writes at start (`section`: its `[tmc2209 stepper_x]`).
    #[error("[{section}]: {source}")]
    TmcInit {
        section: String,
        #[source]
        source: Box<crate::tmc::TmcError>,
    },
    /// The dictionary lacks a configuration command (or an argument does not fit it).
    #[error(transparent)]
    Dictionary(#[from] links::dict::DictError),
    /// Endstops on an MCU whose firmware has no endstop or trsync commands.
    #[error("the MCU has no endstop/trsync support in its dictionary")]
    NoEndstopSupport,
    /// A pin the MCU does not have.
    #[error(transparent)]
    Pin(#[from] crate::hardware::PinError),
    /// Heaters, sensors or fans of this MCU.
    #[error(transparent)]
    Thermal(#[from] crate::heaters::objects::ObjectsError),
    /// The link failed while configuring.
    #[error(transparent)]
    Link(#[from] links::mcu::LinkError),
    /// The MCU kept a configuration from an earlier run.
    #[error(
        "already configured with {same} (crc {theirs:#010x}, this printer.cfg gives \
         {ours:#010x}) by an earlier run: restart the MCU before printing"
    )]
    AlreadyConfigured {
        same: &'static str,
        theirs: u32,
        ours: u32,
    },
    /// The MCU restarted by re-executing itself (Klipper's Linux-process MCU on
    /// `config_reset`), which ended the link: it must be connected again.
    #[error("restarted, and the connection to it ended: connect again")]
    Reconnect,
    /// The MCU shut down while configuring (its reason).
    #[error("shut down: {reason} (the configuration was not accepted; restart the MCU)")]
    ShutDown { reason: String },
    /// The MCU answered but is not configured.
    #[error("did not accept the configuration ({reply})")]
    NotAccepted { reply: String },
    /// Too few move queue entries for the step streams.
    #[error("its move queue is too small ({0} entries)")]
    MoveQueueTooSmall(usize),
}

from_boxed!(ConfigureError, Tmc, crate::tmc::TmcError);

/// The CLI's and the older string-typed layers' view (the message as shown).
impl From<McuError> for String {
    fn from(e: McuError) -> String {
        e.to_string()
    }
}

/// Makes the lead-margin hook of the MCU with the given index (see [`ConnectOptions`]).
pub type LeadHooks = Box<dyn Fn(usize) -> links::serialqueue::MarginHook>;

/// SCHED_FIFO priority of simulated MCUs when the host runs real-time (below the host's
/// planner and IO threads).
pub const SIM_FIFO_PRIORITY: i32 = 10;

/// The trace path for MCU `name`.
pub fn trace_path(base: &Path, name: &str, main: bool) -> PathBuf {
    if main {
        return base.to_path_buf();
    }
    let stem = base.file_stem().and_then(|s| s.to_str()).unwrap_or("trace");
    let file = match base.extension().and_then(|e| e.to_str()) {
        Some(ext) => format!("{stem}-{name}.{ext}"),
        None => format!("{stem}-{name}"),
    };
    base.with_file_name(file)
}

/// The transport of MCU `i` of `cfg`: its serial port, or the pseudo-terminal of the
/// simulated MCU started for it (returned too) in the printer's simulated world `world`.
fn open_transport(
    cfg: &PrinterConfig,
    i: usize,
    machine: &Machine,
    opts: &ConnectOptions,
    world: &str,
) -> Result<(Box<dyn Transport>, Option<SimMcu>), McuError> {
    let mcu_cfg = &cfg.mcus[i];
    let name = &mcu_cfg.name;
    if !mcu_cfg.is_simulated() {
        return Ok((open_serial(name, &mcu_cfg.serial, mcu_cfg.baud)?, None));
    }
    let mut extra = machine.sim_world_args(name, world);
    // Each heater of this MCU gets the simulator's thermal model; a heater and its sensor on
    // two MCUs share its temperature through the world.
    let thermal = machine.thermal.sim_args(name);
    if thermal
        .iter()
        .any(|a| a == "--heater-export" || a == "--remote-sensor")
        && !extra.iter().any(|a| a == "--world")
    {
        extra.extend(["--world".to_string(), world.to_string()]);
    }
    extra.extend(thermal);
    // Its `[adc_scaled]` chips' ADC references.
    extra.extend(machine.thermal.sim_adc_ref_args(name));
    // Its fans with tachometers.
    extra.extend(machine.thermal.sim_fan_args(name));
    // A simulated MCU stands in for hardware that is never descheduled: when the host's
    // threads run SCHED_FIFO, it runs SCHED_FIFO too, below them (they preempt it) but above
    // ordinary processes. Refused: it says so once and runs anyway.
    if opts.io_rt.as_ref().is_some_and(|s| s.fifo_priority.is_some()) {
        extra.extend(["--fifo".to_string(), SIM_FIFO_PRIORITY.to_string()]);
    }
    // And its memory locked like the host's: a page of its code that the kernel dropped while
    // idle (homing code, between homings) would otherwise be read back from a busy disk in the
    // middle of a homing.
    if opts.io_rt.as_ref().is_some_and(|s| s.lock_memory) {
        extra.push("--lock-memory".to_string());
    }
    extra.extend(sim_env_args(name));
    let sim_opts = SimOptions {
        clock_freq: cfg.simulator.clock_freq,
        time_scale: opts.time_scale,
        trace: opts.trace.as_deref().map(|t| trace_path(t, name, i == 0)),
        extra,
    };
    let s = SimMcu::spawn(name, &sim_opts).map_err(|source| McuError::Start {
        mcu: name.clone(),
        source,
    })?;
    let t = PtyTransport::open(&s.pty).map_err(|e| McuError::Open {
        mcu: name.clone(),
        port: s.pty.display().to_string(),
        why: e.to_string(),
    })?;
    Ok((Box::new(t), Some(s)))
}

/// The link's lead-margin hook and its IO thread's real-time set-up (`io-NAME`).
fn link_tuning(opts: &ConnectOptions, i: usize, name: &str) -> LinkTuning {
    let io_rt = opts.io_rt.clone().map(|mut spec| {
        spec.name = format!("io-{name}");
        spec
    });
    LinkTuning {
        margin_hook: opts.lead_hooks.as_ref().map(|make| make(i)),
        thread_setup: io_rt.map(|spec| -> Box<dyn FnOnce() + Send> {
            Box::new(move || {
                rt_core::os::apply_rt(&spec);
            })
        }),
        ..LinkTuning::default()
    }
}

impl Mcus {
    /// Starts (for `serial: simulator`) and connects every MCU, then configures its objects.
    pub fn connect(cfg: &PrinterConfig, machine: &Machine, opts: ConnectOptions) -> Result<Mcus, McuError> {
        let world = format!("cadence-{}", std::process::id());
        let mut mcus = Mcus { list: Vec::new() };
        for (i, mcu_cfg) in cfg.mcus.iter().enumerate() {
            let name = mcu_cfg.name.clone();
            let (transport, sim) = open_transport(cfg, i, machine, &opts, &world)?;
            let (link_opts, tuning) = link_settings(&name, &opts, i);
            let link = match McuLink::connect_with(transport, link_opts, tuning) {
                Ok(l) => l,
                Err(e) => {
                    mcus.close();
                    if let Some(s) = sim {
                        s.finish(Duration::from_secs(2));
                    }
                    return Err(McuError::Link { mcu: name, source: e });
                }
            };
            let clock_freq = match link.dictionary().clock_freq() {
                Ok(f) => f,
                Err(e) => {
                    mcus.close();
                    return Err(McuError::Dictionary {
                        mcu: name,
                        why: e.to_string(),
                    });
                }
            };
            mcus.list.push(McuConn {
                name,
                link,
                sim,
                move_count: 0,
                clock_freq,
                trsync_oid: 0,
                tmc_oid0: 0,
            });
        }
        for i in 0..mcus.list.len() {
            let mut result = mcus.configure(i, machine);
            if let Err(ConfigureError::Reconnect) = result {
                // Restarted by re-executing itself (Klipper's Linux-process MCU): connect to
                // its new instance and configure that.
                let serial = cfg.mcus.get(i).map(|m| (m.serial.clone(), m.baud));
                result = match serial {
                    Some((port, baud)) => match mcus.reconnect(i, &port, baud, &opts) {
                        Ok(()) => mcus.configure(i, machine),
                        Err(e) => {
                            mcus.close();
                            return Err(e);
                        }
                    },
                    None => Err(ConfigureError::Reconnect),
                };
            }
            if let Err(source) = result {
                let mcu = mcus.list[i].name.clone();
                mcus.close();
                return Err(McuError::Configure {
                    mcu,
                    source: Box::new(source),
                });
            }
        }
        mcus.init_drivers(machine)?;
        Ok(mcus)
    }

    /// The drivers' registers, once every MCU is configured (as Klipper at connect); the MCUs
    /// are closed when one fails.
    fn init_drivers(&mut self, machine: &Machine) -> Result<(), McuError> {
        for d in &machine.tmc {
            let result =
                crate::tmc::gcode::io_for(self, &machine.tmc, &d.cfg.stepper).and_then(|io| io.init());
            if let Err(source) = result {
                let mcu = d.mcu().to_string();
                self.close();
                return Err(McuError::Configure {
                    mcu,
                    source: Box::new(ConfigureError::TmcInit {
                        section: d.cfg.section_name(),
                        source: Box::new(source),
                    }),
                });
            }
        }
        Ok(())
    }

    /// Sends one MCU its configuration and checks that it took it.
    fn configure(&mut self, i: usize, machine: &Machine) -> Result<(), ConfigureError> {
        let conn = &self.list[i];
        let name = conn.name.clone();
        let dict = conn.link.dictionary();
        let get_config = dict.encode("get_config", &[])?;
        let reply = query_config(&conn.link, get_config)?;
        let (cmds, trsync_oid, crc) = config_commands(dict, machine, &name)?;
        let tmc_oid0 = tmc_oid0(dict, machine, &name);
        if dict.command("config_digital_out").is_err()
            && machine
                .steppers
                .iter()
                .any(|s| s.mcu == name && s.enable_pin.is_some())
        {
            eprintln!(
                "cadence: warning: mcu '{name}' has no config_digital_out in its dictionary: \
                 stepper enable pins are not driven"
            );
        }
        let was_shut_down = reply.get("is_shutdown") == Some(1);
        let reply = if reply.get("is_config") == Some(1) || was_shut_down {
            // A long-running MCU (a board, or Klipper's Linux-process MCU) keeps its
            // configuration, or its shutdown, between runs: restart it as Klipper's
            // FIRMWARE_RESTART does.
            let theirs = reply.get("crc").unwrap_or(-1) as u32;
            let same = if theirs == crc {
                "this printer.cfg's configuration"
            } else {
                "another configuration"
            };
            let why = match (was_shut_down, conn.link.shutdown_reason()) {
                (true, Some(reason)) => format!("was shut down by an earlier run ({reason})"),
                (true, None) => "was shut down by an earlier run".to_string(),
                (false, _) => format!("was configured by an earlier run (with {same}, crc {theirs:#010x})"),
            };
            match restart(&conn.link, get_config, &name, &why)? {
                Restarted::Reply(reply) => reply,
                Restarted::Reconnect => return Err(ConfigureError::Reconnect),
                Restarted::Unsupported if was_shut_down => {
                    return Err(ConfigureError::ShutDown {
                        reason: conn.link.shutdown_reason().unwrap_or_default(),
                    })
                }
                Restarted::Unsupported => {
                    return Err(ConfigureError::AlreadyConfigured {
                        same,
                        theirs,
                        ours: crc,
                    })
                }
            }
        } else {
            reply
        };
        if reply.get("is_config") == Some(1) {
            return Err(ConfigureError::NotAccepted {
                reply: format!("still configured after config_reset: {reply}"),
            });
        }
        let reply = {
            for c in cmds {
                conn.link.send(c)?;
            }
            query_config(&conn.link, get_config)?
        };
        if reply.get("is_config") != Some(1) {
            // A shut-down MCU answers every configuration command with `is_shutdown` and its
            // reason (Klipper's Linux MCU without GPIO: "GPIO chip device not found"): say it
            // as the MCU did.
            if let Some(reason) = conn.link.shutdown_reason() {
                return Err(ConfigureError::ShutDown { reason });
            }
            return Err(ConfigureError::NotAccepted {
                reply: reply.to_string(),
            });
        }
        let move_count = reply.get("move_count").unwrap_or(0).max(0) as usize;
        if move_count < 64 {
            return Err(ConfigureError::MoveQueueTooSmall(move_count));
        }
        let conn = &mut self.list[i];
        conn.move_count = move_count;
        conn.trsync_oid = trsync_oid;
        conn.tmc_oid0 = tmc_oid0;
        Ok(())
    }

    /// The main MCU.
    pub fn main(&self) -> &McuConn {
        &self.list[0]
    }

    /// The MCU called `name`.
    pub fn get(&self, name: &str) -> Option<&McuConn> {
        self.list.iter().find(|m| m.name == name)
    }

    /// What a step stream needs of each MCU that gets one (see `streams::stream_mcus`).
    pub fn stream_params(&self, machine: &Machine) -> Vec<crate::step_stream::McuParams<'_>> {
        let names: Vec<&str> = self.list.iter().map(|m| m.name.as_str()).collect();
        crate::step_stream::stream_mcus(machine, &names)
            .into_iter()
            .map(|i| {
                let m = &self.list[i];
                crate::step_stream::McuParams {
                    name: &m.name,
                    mcu_index: i,
                    dict: m.link.dictionary(),
                    clock_freq: m.clock_freq,
                    move_count: m.move_count,
                }
            })
            .collect()
    }

    /// The first MCU that reported a shutdown, as an error.
    pub fn check(&self) -> Result<(), McuError> {
        for m in &self.list {
            if let Some(reason) = m.link.shutdown_reason() {
                return Err(McuError::Shutdown {
                    mcu: m.name.clone(),
                    reason,
                });
            }
        }
        Ok(())
    }

    /// Connects MCU `i` again at `port` after it restarted by re-executing itself: waits (up
    /// to 5 s) for the port to come back, identifies the new instance and replaces the link.
    fn reconnect(&mut self, i: usize, port: &str, baud: u32, opts: &ConnectOptions) -> Result<(), McuError> {
        let Some(conn) = self.list.get_mut(i) else {
            return Ok(());
        };
        let name = conn.name.clone();
        let deadline = std::time::Instant::now() + Duration::from_secs(5);
        let link = loop {
            // The old instance's port may linger for a moment: try until one identifies.
            std::thread::sleep(Duration::from_millis(100));
            let attempt = open_serial(&name, port, baud).and_then(|t| {
                let (link_opts, tuning) = link_settings(&name, opts, i);
                McuLink::connect_with(t, link_opts, tuning).map_err(|source| McuError::Link {
                    mcu: name.clone(),
                    source,
                })
            });
            match attempt {
                Ok(link) => break link,
                Err(e) if std::time::Instant::now() >= deadline => return Err(e),
                Err(_) => continue,
            }
        };
        let old = std::mem::replace(&mut conn.link, link);
        let _ = old.close();
        Ok(())
    }

    /// Closes every link and waits (bounded) for simulated MCUs to exit.
    pub fn close(&mut self) -> Vec<(String, LinkStats)> {
        let mut out = Vec::new();
        for m in self.list.drain(..) {
            let stats = m.link.close();
            if let Some(s) = m.sim {
                s.finish(Duration::from_secs(5));
            }
            out.push((m.name, stats));
        }
        out
    }
}

/// Environment variable with extra `cadence-mcu` arguments for simulated MCU `name` (fault
/// injection in tests and benches, e.g. `CADENCE_SIM_ARGS_PROBE_MCU="--tx-delay-ms 30"`): the
/// name upper-cased, other characters than letters and digits as `_`.
pub fn sim_env_var(name: &str) -> String {
    let tail: String = name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() {
                c.to_ascii_uppercase()
            } else {
                '_'
            }
        })
        .collect();
    format!("CADENCE_SIM_ARGS_{tail}")
}

/// The extra simulator arguments of [`sim_env_var`], split at whitespace (none when unset).
fn sim_env_args(name: &str) -> Vec<String> {
    std::env::var(sim_env_var(name))
        .map(|v| v.split_whitespace().map(str::to_string).collect())
        .unwrap_or_default()
}

/// Where each kind of object of one MCU starts (see the module's doc).
struct OidLayout<'m> {
    /// Driver enable pins, once each (several steppers often share one), after the endstops.
    enables: Vec<&'m sysconfig::printer::PinRef>,
    /// A BLTouch's servo output right after the endstops (its oid: crate::hardware).
    bltouch: Option<&'m crate::hardware::BlTouchOut>,
    /// A Smart Effector's control output right after the endstops (its oid: crate::hardware).
    smart_effector: Option<(&'m sysconfig::printer::PinRef, u8)>,
    enable_oid0: usize,
    trsync_oid: u8,
    /// Heaters, sensors and fans (crate::heaters::objects) right after the trsync.
    thermal_oid0: usize,
    /// The TMC drivers' buses last (crate::tmc).
    tmc_oid0: usize,
    count: usize,
}

fn oid_layout<'m>(
    dict: &Dictionary,
    machine: &'m Machine,
    mcu: &str,
) -> Result<OidLayout<'m>, ConfigureError> {
    let steppers: Vec<_> = machine.steppers.iter().filter(|s| s.mcu == mcu).collect();
    let endstops = machine.mcu_endstops(mcu);
    let mut enables: Vec<&sysconfig::printer::PinRef> = Vec::new();
    // A firmware built without digital outputs (a stripped test build) cannot drive them;
    // `configure` warns about that.
    let has_outputs = dict.command("config_digital_out").is_ok();
    for s in steppers.iter().filter(|_| has_outputs) {
        if let Some(p) = &s.enable_pin {
            if p.mcu == mcu && !enables.iter().any(|e| e.pin == p.pin) {
                enables.push(p);
            }
        }
    }
    let bltouch = machine.mcu_bltouch(mcu).filter(|_| has_outputs);
    let smart_effector = machine.mcu_smart_effector(mcu).filter(|_| has_outputs);
    let enable_oid0 = steppers.len()
        + endstops.len()
        + usize::from(bltouch.is_some())
        + usize::from(smart_effector.is_some());
    let trsync_oid = u8::try_from(enable_oid0 + enables.len()).map_err(|_| ConfigureError::TooManyObjects)?;
    let thermal_oid0 = usize::from(trsync_oid) + 1;
    let tmc_oid0 = thermal_oid0 + machine.thermal.objects_on(mcu).len();
    let count = tmc_oid0 + crate::tmc::object_count(&machine.tmc, mcu);
    Ok(OidLayout {
        enables,
        bltouch,
        smart_effector,
        enable_oid0,
        trsync_oid,
        thermal_oid0,
        tmc_oid0,
        count,
    })
}

/// The driver enable pins of MCU `mcu`, once each (several steppers often share one), and the
/// oid of the first: they follow the steppers, endstops and BLTouch servo. None on a firmware
/// built without digital outputs (a stripped test build; `configure` warns about that).
pub fn enable_pins<'m>(
    dict: &Dictionary,
    machine: &'m Machine,
    mcu: &str,
) -> Result<(usize, Vec<&'m sysconfig::printer::PinRef>), ConfigureError> {
    oid_layout(dict, machine, mcu).map(|l| (l.enable_oid0, l.enables))
}

/// Encodes one MCU's configuration: oids, endstops, trsync, steppers, enable pins, finalize
/// with the config CRC (CRC-32 of the configuration messages). Returns the commands and the
/// trsync oid. Endstops come before steppers as Klipper's host sends them: Klipper's
/// Linux-process MCU without GPIO crashes (SIGSEGV) on a `config_stepper` it cannot set up,
/// where a `config_endstop` first gives a clean shutdown with its reason.
pub fn config_commands(
    dict: &Dictionary,
    machine: &Machine,
    mcu: &str,
) -> Result<(Vec<Cmd>, u8, u32), ConfigureError> {
    let steppers: Vec<_> = machine.steppers.iter().filter(|s| s.mcu == mcu).collect();
    let endstops = machine.mcu_endstops(mcu);
    let OidLayout {
        enables,
        bltouch,
        smart_effector,
        enable_oid0,
        trsync_oid,
        thermal_oid0,
        tmc_oid0,
        count,
    } = oid_layout(dict, machine, mcu)?;
    if count > 255 {
        return Err(ConfigureError::TooManyObjects);
    }
    let clock_freq = dict.clock_freq()?;
    let mut cmds = vec![dict.encode("allocate_oids", &[count as i64])?];
    let has_endstops = dict.command("config_endstop").is_ok() && dict.command("config_trsync").is_ok();
    if !endstops.is_empty() && !has_endstops {
        return Err(ConfigureError::NoEndstopSupport);
    }
    for e in &endstops {
        let pin = dict.pin(&e.pin.pin).map_err(|source| {
            let option = if e.stepper == "probe" {
                "pin"
            } else {
                "endstop_pin"
            };
            pin_error(format!("[{}] {option}", e.stepper), source)
        })?;
        cmds.push(dict.encode("config_endstop", &[e.oid as i64, pin as i64, e.pin.pullup as i64])?);
    }
    if has_endstops {
        cmds.push(dict.encode("config_trsync", &[trsync_oid as i64])?);
    } else {
        // Without trsync support the last oid is simply unused.
    }
    for s in &steppers {
        let step_pin = dict
            .pin(&s.step_pin.pin)
            .map_err(|e| pin_error(format!("[{}] step_pin", s.name), e))?;
        let dir_pin = dict
            .pin(&s.dir_pin.pin)
            .map_err(|e| pin_error(format!("[{}] dir_pin", s.name), e))?;
        let pulse_ticks = (s.step_pulse_duration * clock_freq).round().max(0.0) as i64;
        cmds.push(dict.encode(
            "config_stepper",
            &[
                s.oid as i64,
                step_pin as i64,
                dir_pin as i64,
                s.step_pin.invert as i64,
                pulse_ticks,
            ],
        )?);
    }
    for (i, p) in enables.iter().enumerate() {
        // Drivers off from configuration on and when the MCU shuts down (value and
        // default_value inactive; `!` pins are active low), as Klipper's host configures them:
        // the step stream turns them on before a stepper's first step and M84 off
        // (crate::step_stream::sink).
        let pin = dict
            .pin(&p.pin)
            .map_err(|x| pin_error(format!("enable_pin {}", p.pin), x))?;
        let off = p.invert as i64;
        cmds.push(dict.encode(
            "config_digital_out",
            &[(enable_oid0 + i) as i64, pin as i64, off, off, 0],
        )?);
    }
    if let Some(b) = bltouch {
        cmds.extend(crate::homing::bltouch::config_commands(dict, b)?);
    }
    if let Some((pin, oid)) = smart_effector {
        cmds.extend(crate::homing::smart_effector::config_commands(dict, pin, oid)?);
    }
    cmds.extend(machine.thermal.config_commands(dict, mcu, thermal_oid0)?);
    cmds.extend(crate::tmc::config_commands(
        dict,
        &machine.tmc,
        mcu,
        tmc_oid0,
        clock_freq,
    )?);
    let mut crc = crc32fast::Hasher::new();
    for c in &cmds {
        crc.update(c.as_bytes());
    }
    let crc = crc.finalize();
    cmds.push(dict.encode("finalize_config", &[crc as i64])?);
    Ok((cmds, trsync_oid, crc))
}

fn pin_error(what: String, source: links::dict::DictError) -> ConfigureError {
    crate::hardware::PinError { what, source }.into()
}

/// Oid of MCU `mcu`'s first TMC bus object.
fn tmc_oid0(dict: &Dictionary, machine: &Machine, mcu: &str) -> u8 {
    oid_layout(dict, machine, mcu).map_or(0, |l| l.tmc_oid0.min(255) as u8)
}

/// `get_config` → `config`, retried: MCU → host traffic is not retransmitted, so on a noisy line
/// an answer can be lost; the query itself is idempotent. Bounded: 4 tries of 1 s.
/// Restarts an MCU left configured or shut down by an earlier run, the way Klipper's
/// FIRMWARE_RESTART does it with no `reset` command: `emergency_stop` (unless already shut
/// down; its `shutdown` awaited), then `config_reset`, which Klipper's MCUs and Cadence's
/// accept only while shut down and which leaves them unconfigured and running on the same
/// link, or (Klipper's Linux-process MCU) re-execute themselves. Says so on stderr (`why`).
fn restart(
    link: &McuLink,
    get_config: Cmd,
    name: &str,
    why: &str,
) -> Result<Restarted, links::mcu::LinkError> {
    let dict = link.dictionary();
    let (Ok(stop), Ok(reset)) = (
        dict.encode("emergency_stop", &[]),
        dict.encode("config_reset", &[]),
    ) else {
        return Ok(Restarted::Unsupported);
    };
    eprintln!("cadence: mcu '{name}' {why}: restarting it (emergency_stop, config_reset)");
    if link.shutdown_reason().is_none() {
        link.send(stop)?;
        let deadline = std::time::Instant::now() + Duration::from_secs(1);
        while link.shutdown_reason().is_none() && std::time::Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(5));
        }
    }
    link.send(reset)?;
    // Answers the MCU sent before it took config_reset (an `is_shutdown`) arrive meanwhile;
    // an MCU that restarts by re-executing itself closes its end of the link.
    let deadline = std::time::Instant::now() + Duration::from_millis(300);
    while std::time::Instant::now() < deadline {
        if link.error().is_some() {
            return Ok(Restarted::Reconnect);
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    link.clear_shutdown();
    match query_config(link, get_config) {
        Ok(reply) => Ok(Restarted::Reply(reply)),
        Err(_) if link.error().is_some() => Ok(Restarted::Reconnect),
        Err(e) => Err(e),
    }
}

/// What [`restart`] left.
enum Restarted {
    /// The dictionary has no `config_reset`.
    Unsupported,
    /// The same link, the MCU's fresh `get_config` reply.
    Reply(links::dict::Message),
    /// The MCU closed the link to restart: connect again.
    Reconnect,
}

/// Opens a board's serial port (or a pty a Linux-process MCU made) as a transport.
fn open_serial(name: &str, port: &str, baud: u32) -> Result<Box<dyn Transport>, McuError> {
    let t = SerialTransport::open(port, baud).map_err(|e| McuError::Open {
        mcu: name.to_string(),
        port: port.to_string(),
        why: e.to_string(),
    })?;
    Ok(Box::new(t))
}

/// The link settings of MCU `name`, the `i`-th in `[mcu]` order.
fn link_settings(name: &str, opts: &ConnectOptions, i: usize) -> (LinkOptions, LinkTuning) {
    let link_opts = LinkOptions {
        name: name.to_string(),
        identify_timeout: Duration::from_secs(5),
        response_timeout: Duration::from_secs(2),
        queue_capacity: 4096,
    };
    (link_opts, link_tuning(opts, i, name))
}

fn query_config(link: &McuLink, get_config: Cmd) -> Result<links::dict::Message, links::mcu::LinkError> {
    let mut tries = 1;
    loop {
        match link.query(get_config, "config", None, Duration::from_secs(1)) {
            Ok(reply) => return Ok(reply),
            Err(_) if tries < 4 && link.error().is_none() && link.shutdown_reason().is_none() => tries += 1,
            Err(e) => return Err(e),
        }
    }
}
