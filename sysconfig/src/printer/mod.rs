//! Klipper printer.cfg → validated, typed [`PrinterConfig`].
//!
//! Layers: [`crate::ini`] gives sections and options with locations; a consumption-tracking
//! reader (`reader`) hands them out through typed getters with Klipper's bounds; one module per
//! section family builds its typed section (`mcu`, `toolhead`, `stepper`, `extruder`, `heater`);
//! finally every option nobody read is an error ("Option 'foo' is not valid in section …"), and
//! every section nobody read is an error unless [`SECTIONS`] accepts and ignores it (then a
//! warning). Sections [`SECTIONS`] refuses fail the load first, naming the missing feature.
//!
//! Build order (it decides which error is reported first): MCUs (pins are checked against
//! them), `[printer]`, `[probe]`, `[bltouch]` or `[smart_effector]` (its `z_offset` is Z's endstop position with
//! `probe:z_virtual_endstop`), the steppers the kinematics needs, their further motors
//! (`[stepper_z1]`…), `[extruder]`, `[heater_bed]`, the thermal sections (`thermal`),
//! `[simulator]`, `[realtime]`, `[gcode]`, `[gcode_arcs]`, `[firmware_retraction]`,
//! `[input_shaper]`, `[gcode_macro]`s, `[safe_z_home]` / `[homing_override]`, `[bed_mesh]`, then the
//! unused-option/section check.

mod adc_scaled;
mod bed_mesh;
mod bltouch;
mod board_pins;
pub mod check;
mod delta;
mod error;
mod extruder;
mod gcode;
mod heater;
mod homing;
mod host;
mod input_shaper;
mod macros;
mod mcu;
mod multi_pin;
mod pins;
mod probe;
mod reader;
mod realtime;
mod screws;
mod sections;
mod smart_effector;
mod spi_sensor;
mod stepper;
mod thermal;
pub mod tmc;
mod toolhead;
mod z_tilt;

use std::path::{Path, PathBuf};

use crate::ini::{self, ConfigFile};

pub use adc_scaled::AdcScaledSection;
pub use bed_mesh::{
    profile_options as bed_mesh_profile_options, BedMeshSection, MeshProfile, MeshShape,
    ALGORITHMS as BED_MESH_ALGORITHMS,
};
pub use bltouch::{BlTouchSection, OutputMode as BlTouchOutputMode, OUTPUT_MODES as BLTOUCH_OUTPUT_MODES};
pub use delta::{DeltaSection, DEFAULT_ANGLES};
pub use error::{ConfigError, ValueProblem};
pub use extruder::{ExtruderSection, ExtruderStepperSection};
pub use gcode::{FirmwareRetractionSection, GcodeArcsSection, GcodeSection, UnknownCommands};
pub use heater::{HeaterControl, HeaterSection, ABSOLUTE_ZERO_C};
pub use homing::{HomingOverrideSection, SafeZHomeSection, HOMING_OVERRIDE_MACRO};
pub use host::HostSections;
pub use input_shaper::InputShaperSection;
pub use mcu::{McuSection, SimulatorSection, SIMULATOR_SERIAL};
pub use multi_pin::{MultiPinSection, MULTI_PIN_CHIP};
pub use pins::{is_simulator_pin, PinKind, PinProblem, PinRef, MAIN_MCU};
pub use probe::{
    ProbeSection, SamplesResult, PROBE_ACTIVATE_MACRO, PROBE_DEACTIVATE_MACRO, PROBE_PIN_MCU,
    SAMPLES_RESULTS, Z_VIRTUAL_ENDSTOP,
};
pub use realtime::RealtimeSection;
pub use screws::{Screw, ScrewThread, ScrewsSection, SCREW_THREADS};
pub use sections::{is_ignored, support as section_support, Support as SectionSupport, SECTIONS};
pub use smart_effector::{SmartEffectorSection, DEFAULT_RECOVERY_TIME as SMART_EFFECTOR_RECOVERY_TIME};
pub use spi_sensor::{SpiBus, SpiChip, SpiSensorSection, SPI_CHIPS};
pub use stepper::{ExtraStepperSection, MotorSection, StepperSection};
pub use thermal::{
    ControllerFanSection, FanOptions, HeaterFanSection, SensorSection, SensorSource, TemperatureFanSection,
    TemperatureSensorSection, ThermalSections, ThermistorSection, VerifyHeaterSection,
    DRIVEN as THERMAL_DRIVEN,
};
pub use tmc::{TmcBus, TmcModel, TmcSection};
pub use toolhead::{Kinematics, PrinterSection};
pub use z_tilt::ZTiltSection;

use pins::PinRegistry;
use reader::Reader;

/// The built-in simulated printer's config (`examples/simulated-cartesian.cfg`).
pub const SIMULATED_PRINTER_CFG: &str = include_str!("../../../examples/simulated-cartesian.cfg");

/// The name errors in the built-in config are reported under.
pub const SIMULATED_PRINTER_NAME: &str = "<builtin>/simulated-cartesian.cfg";

/// A whole validated printer config.
#[derive(Debug, Clone, PartialEq)]
pub struct PrinterConfig {
    /// The main config file, as given.
    pub source: PathBuf,
    pub printer: PrinterSection,
    /// The kinematics' steppers in axis order: `stepper_x`, `stepper_y`, `stepper_z` (delta:
    /// `stepper_a`, `stepper_b`, `stepper_c`).
    pub steppers: Vec<StepperSection>,
    /// Further motors of those rails (`[stepper_z1]`, `[stepper_z2]`…, `[stepper_x1]`), in rail
    /// order then index order.
    pub extra_steppers: Vec<ExtraStepperSection>,
    /// The geometry, for delta kinematics.
    pub delta: Option<DeltaSection>,
    pub extruder: Option<ExtruderSection>,
    /// `[extruder1]`, `[extruder2]`…, in index order (only with an `[extruder]`).
    pub extra_extruders: Vec<ExtruderSection>,
    /// `[extruder_stepper NAME]` sections, in file order.
    pub extruder_steppers: Vec<ExtruderStepperSection>,
    /// `[mcu]` first, then each `[mcu NAME]` in file order.
    pub mcus: Vec<McuSection>,
    pub heater_bed: Option<HeaterSection>,
    /// `[probe]`, or the probe a `[bltouch]` or `[smart_effector]` is.
    pub probe: Option<ProbeSection>,
    /// `[bltouch]`'s own options (its probe options are in `probe`).
    pub bltouch: Option<BlTouchSection>,
    /// `[smart_effector]`'s own options (its probe options are in `probe`).
    pub smart_effector: Option<SmartEffectorSection>,
    /// `[tmc2130 …]`, `[tmc2208 …]`, `[tmc2209 …]`, `[tmc5160 …]`: the steppers' drivers.
    pub tmc: Vec<TmcSection>,
    /// `[simulator]`, or its defaults.
    pub simulator: SimulatorSection,
    /// `[bed_mesh]` with its saved profiles.
    pub bed_mesh: Option<BedMeshSection>,
    /// `[z_tilt]`.
    pub z_tilt: Option<ZTiltSection>,
    /// `[quad_gantry_level]` (its `z_positions` are the four corners, Klipper's motor order).
    pub quad_gantry_level: Option<ZTiltSection>,
    /// `[screws_tilt_adjust]`.
    pub screws_tilt_adjust: Option<ScrewsSection>,
    /// `[bed_screws]` (BED_SCREWS_ADJUST runs from `host`'s copy: `planner::gcode::bed_screws`).
    pub bed_screws: Option<ScrewsSection>,
    /// `[realtime]`, or its defaults.
    pub realtime: RealtimeSection,
    /// `[gcode]`, or its defaults.
    pub gcode: GcodeSection,
    /// `[gcode_arcs]`, or its defaults.
    pub gcode_arcs: GcodeArcsSection,
    /// `[firmware_retraction]`, or its defaults.
    pub firmware_retraction: FirmwareRetractionSection,
    /// `[input_shaper]`, when there is one.
    pub input_shaper: Option<InputShaperSection>,
    /// The thermal sections the host drives beyond `[extruder]`/`[heater_bed]`
    /// (`[heater_generic]`, `[verify_heater]`, `[thermistor]`, `[temperature_sensor]`, `[fan]`,
    /// `[heater_fan]`).
    pub thermal: ThermalSections,
    /// `[safe_z_home]`: how G28 homes Z.
    pub safe_z_home: Option<SafeZHomeSection>,
    /// `[homing_override]`: the script G28 runs instead.
    pub homing_override: Option<HomingOverrideSection>,
    /// `[gcode_macro NAME]` sections, in file order.
    pub macros: Vec<planner::gcode::macros::MacroDef>,
    /// `[respond]`'s default prefix (`echo:`), when the section is there.
    pub respond: Option<String>,
    /// Whether there is an `[exclude_object]` section (it has no options).
    pub exclude_object: bool,
    /// `[delayed_gcode]`, `[save_variables]`, `[idle_timeout]`, `[display_status]`,
    /// `[force_move]`, `[virtual_sdcard]`.
    pub host: HostSections,
    /// Accepted-but-ignored sections and other things worth telling the user.
    pub warnings: Vec<String>,
}

impl PrinterConfig {
    /// Builds the typed config from a parsed file.
    pub fn from_ini(file: &ConfigFile) -> Result<PrinterConfig, ConfigError> {
        let reader = Reader::new(file);
        let source = file.main_file().to_path_buf();
        refuse_unsupported(file)?;

        let mcus = mcu::read_mcus(&reader)?;
        let names = mcus.iter().map(|m| m.name.clone()).collect();
        let simulated = mcus
            .iter()
            .filter(|m| m.is_simulated())
            .map(|m| m.name.clone())
            .collect();
        let mut pins = PinRegistry::new(names)
            .with_simulated(simulated)
            .with_unsupported_chips(unsupported_chips(file))
            .with_aliases(board_pins::read_board_pins(&reader)?);
        let adc_scaled = adc_scaled::read_adc_scaled(&reader, &mut pins)?;
        let multi_pins = multi_pin::read_multi_pins(&reader, &mut pins)?;

        let printer_section = reader
            .section("printer")
            .ok_or_else(|| ConfigError::MissingSection {
                file: source.clone(),
                section: "printer".to_string(),
                needed_by: None,
            })?;
        let printer = toolhead::read_printer(&printer_section)?;
        let is_delta = printer.kinematics == Kinematics::Delta;
        let delta_printer = match is_delta {
            true => Some(delta::read_printer_delta(&printer_section)?),
            false => None,
        };

        let (probe, bltouch, smart_effector) = read_probe_sections(&reader, &mut pins)?;
        if probe.is_some() {
            pins.set_probe();
        }
        pins.set_tmc_chips(tmc::chips(&reader));

        let mut steppers = Vec::new();
        let mut towers = Vec::new();
        for (i, &name) in printer.kinematics.stepper_sections().iter().enumerate() {
            let s = reader.section(name).ok_or_else(|| ConfigError::MissingSection {
                file: source.clone(),
                section: name.to_string(),
                needed_by: Some(format!("kinematics: {}", printer.kinematics.name())),
            })?;
            // A delta's towers B and C default their endstop position to tower A's.
            let default_endstop = match is_delta {
                true => steppers.first().and_then(|a: &StepperSection| a.position_endstop),
                false => None,
            };
            steppers.push(stepper::read_rail(
                &s,
                &mut pins,
                is_delta,
                probe.as_ref(),
                default_endstop,
            )?);
            if let Some((radius, _, _)) = delta_printer {
                let first_arm = towers.first().map(|&(a, _)| a);
                towers.push(delta::read_tower(&s, i, first_arm, radius)?);
            }
        }
        let extra_steppers = read_extra_steppers(&reader, &printer, &steppers, &mut pins)?;
        let delta = match (delta_printer, towers.as_slice()) {
            (Some((delta_radius, print_radius, minimum_z_position)), &[a, b, c]) => Some(DeltaSection {
                delta_radius,
                print_radius,
                minimum_z_position,
                arm_length: [a.0, b.0, c.0],
                angles: [a.1, b.1, c.1],
            }),
            _ => None,
        };

        let extruder = match reader.section("extruder") {
            Some(s) => Some(extruder::read_extruder(&s, &printer, &mut pins)?),
            None => None,
        };
        let extra_extruders = match extruder {
            Some(_) => extruder::read_extra_extruders(&reader, &printer, &mut pins)?,
            None => Vec::new(),
        };
        let extruder_names: Vec<&str> = extruder
            .iter()
            .chain(&extra_extruders)
            .map(|e| e.name.as_str())
            .collect();
        let extruder_steppers = extruder::read_extruder_steppers(&reader, &extruder_names, &mut pins)?;
        let extruder_motors: Vec<(String, &MotorSection)> = extruder
            .iter()
            .chain(&extra_extruders)
            .map(|e| (e.name.clone(), &e.motor))
            .chain(
                extruder_steppers
                    .iter()
                    .map(|e| (format!("extruder_stepper {}", e.name), &e.motor)),
            )
            .collect();
        let tmc = read_tmc_sections(&reader, &steppers, &extra_steppers, &extruder_motors, &mut pins)?;
        let heater_bed = match reader.section("heater_bed") {
            Some(s) => Some(heater::read_heater(&s, &mut pins)?),
            None => None,
        };
        let mut thermal = thermal::read_thermal(&reader, &mut pins, true)?;
        thermal.adc_scaled = adc_scaled;
        thermal.multi_pins = multi_pins;
        let simulator_section = reader.section("simulator");
        let simulator = match &simulator_section {
            Some(s) => mcu::read_simulator(s)?,
            None => SimulatorSection::default(),
        };

        let realtime = reader.section_or_default("realtime", realtime::read_realtime)?;
        let gcode = reader.section_or_default("gcode", gcode::read_gcode)?;
        let gcode_arcs = reader.section_or_default("gcode_arcs", gcode::read_gcode_arcs)?;
        let firmware_retraction =
            reader.section_or_default("firmware_retraction", gcode::read_firmware_retraction)?;

        let input_shaper = match reader.section("input_shaper") {
            Some(s) => Some(input_shaper::read_input_shaper(&s, is_delta)?),
            None => None,
        };
        let macros = macros::read_gcode_macros(&reader)?;
        let has_stepper_z = steppers.iter().any(|s| s.name == "stepper_z");
        let (safe_z_home, homing_override) = homing::read_homing(&reader, has_stepper_z)?;
        let exclude_object = reader.section("exclude_object").is_some();
        let respond = match reader.section("respond") {
            Some(s) => Some(gcode::read_respond(&s)?),
            None => None,
        };

        let mut host = host::read_host(&reader)?;
        let mut mesh_warnings = Vec::new();
        let has_probe = probe.is_some();
        let bed_mesh = match probing_section(&reader, "bed_mesh", has_probe)? {
            Some(s) => Some(bed_mesh::read_bed_mesh(&reader, &s, &mut mesh_warnings)?),
            None => None,
        };
        let z_tilt = match probing_section(&reader, "z_tilt", has_probe)? {
            Some(s) => {
                let z_motors = 1 + extra_steppers.iter().filter(|e| e.rail == 2).count();
                Some(z_tilt::read_z_tilt(&s, z_motors)?)
            }
            None => None,
        };
        let quad_gantry_level = match probing_section(&reader, "quad_gantry_level", has_probe)? {
            Some(s) => {
                let z_motors = 1 + extra_steppers.iter().filter(|e| e.rail == 2).count();
                Some(z_tilt::read_quad_gantry_level(&s, z_motors)?)
            }
            None => None,
        };
        let screws_tilt_adjust = match probing_section(&reader, "screws_tilt_adjust", has_probe)? {
            Some(s) => Some(screws::read_screws(&s, true)?),
            None => None,
        };
        let bed_screws = match reader.section("bed_screws") {
            Some(s) => Some(screws::read_screws(&s, false)?),
            None => None,
        };
        host.host.bed_screws = bed_screws.as_ref().map(screws::bed_screws_tool);

        let mut warnings = reader.finish(is_ignored)?;
        warnings.extend(mesh_warnings);
        let scripts: Vec<_> = macros
            .iter()
            .chain(homing_override.as_ref().map(|o| &o.script))
            .chain(&host.scripts)
            .cloned()
            .collect();
        if !scripts.is_empty() {
            // A broken template or a non-literal variable fails the load here, not mid-print.
            planner::gcode::macros::Macros::new(scripts).map_err(|e| ConfigError::Macro(Box::new(e)))?;
        }
        if let Some(s) = simulator_section {
            if !mcus.iter().any(McuSection::is_simulated) {
                warnings.push(format!(
                    "{}: [simulator] has no effect: no [mcu] has 'serial: {SIMULATOR_SERIAL}'",
                    s.at()
                ));
            }
        }
        Ok(PrinterConfig {
            source,
            printer,
            steppers,
            extra_steppers,
            delta,
            extruder,
            extra_extruders,
            extruder_steppers,
            mcus,
            heater_bed,
            probe,
            bltouch,
            smart_effector,
            tmc,
            simulator,
            bed_mesh,
            z_tilt,
            quad_gantry_level,
            screws_tilt_adjust,
            bed_screws,
            realtime,
            gcode,
            gcode_arcs,
            firmware_retraction,
            input_shaper,
            thermal,
            safe_z_home,
            homing_override,
            macros,
            respond,
            exclude_object,
            host,
            warnings,
        })
    }

    /// The stepper section named `name` (`stepper_x` …).
    pub fn stepper(&self, name: &str) -> Option<&StepperSection> {
        self.steppers.iter().find(|s| s.name == name)
    }

    /// Every extruder: `[extruder]`, then `[extruder1]`….
    pub fn extruders(&self) -> impl Iterator<Item = &ExtruderSection> {
        self.extruder.iter().chain(&self.extra_extruders)
    }

    /// The MCU named `name` (`mcu` for the main one).
    pub fn mcu(&self, name: &str) -> Option<&McuSection> {
        self.mcus.iter().find(|m| m.name == name)
    }
}

/// The probe section read: the probe, and the own options of a `[bltouch]` or a
/// `[smart_effector]`.
type ProbeSections = (
    Option<ProbeSection>,
    Option<BlTouchSection>,
    Option<SmartEffectorSection>,
);

/// The probe: `[probe]`, `[bltouch]` or `[smart_effector]` (at most one of them), with the
/// own options of the latter two.
fn read_probe_sections(reader: &Reader<'_>, pins: &mut PinRegistry) -> Result<ProbeSections, ConfigError> {
    let kinds = ["probe", "bltouch", "smart_effector"];
    let present: Vec<_> = kinds.iter().filter_map(|k| reader.section(k)).collect();
    if let [first, second, ..] = present.as_slice() {
        return Err(ConfigError::BadSection {
            at: second.at().clone(),
            section: second.name().to_string(),
            reason: format!(
                "is a probe, and there is a [{}] section already: keep one of them",
                first.name()
            ),
        });
    }
    let Some(s) = present.first() else {
        return Ok((None, None, None));
    };
    Ok(match s.name() {
        "bltouch" => {
            let (p, b) = bltouch::read_bltouch(s, pins)?;
            (Some(p), Some(b), None)
        }
        "smart_effector" => {
            let (p, e) = smart_effector::read_smart_effector(s, pins)?;
            (Some(p), None, Some(e))
        }
        _ => (Some(probe::read_probe(s, pins)?), None, None),
    })
}

/// Section `name`, which probes the bed: an error when the printer has no probe.
fn probing_section<'r>(
    reader: &'r Reader<'_>,
    name: &str,
    has_probe: bool,
) -> Result<Option<reader::SectionReader<'r>>, ConfigError> {
    match reader.section(name) {
        Some(s) if !has_probe => Err(ConfigError::BadSection {
            at: s.at().clone(),
            section: name.to_string(),
            reason: "needs a probe: add a [probe], [bltouch] or [smart_effector] section".to_string(),
        }),
        s => Ok(s),
    }
}

/// The further motors of each rail: `[stepper_z1]`, `[stepper_z2]`… up to the first missing
/// index (as Klipper looks them up; a later one is then an unread section). Not on a delta.
fn read_extra_steppers(
    reader: &Reader<'_>,
    printer: &PrinterSection,
    steppers: &[StepperSection],
    pins: &mut PinRegistry,
) -> Result<Vec<ExtraStepperSection>, ConfigError> {
    let mut extras = Vec::new();
    for (rail, primary) in steppers.iter().enumerate() {
        for index in 1.. {
            let name = format!("{}{index}", primary.name);
            let Some(s) = reader.section(&name) else {
                break;
            };
            if printer.kinematics == Kinematics::Delta {
                return Err(ConfigError::BadSection {
                    at: s.at().clone(),
                    section: name,
                    reason: "is not supported by Cadence yet (several motors on a delta tower)".to_string(),
                });
            }
            extras.push(stepper::read_extra(&s, pins, rail, primary)?);
        }
    }
    Ok(extras)
}

/// The TMC driver sections, each for an existing stepper (Klipper: "Could not find config
/// section '[NAME]' required by tmc driver"); a stepper homing on `tmcXXXX_NAME:virtual_endstop`
/// makes its driver claim the diag pin.
fn read_tmc_sections(
    reader: &Reader<'_>,
    steppers: &[StepperSection],
    extras: &[ExtraStepperSection],
    extruders: &[(String, &MotorSection)],
    pins: &mut PinRegistry,
) -> Result<Vec<TmcSection>, ConfigError> {
    let mut out = Vec::new();
    let kinds = tmc::MODELS.map(|(kind, _)| kind);
    for s in reader.sections_of_kinds(&kinds) {
        let kind = s.kind();
        let Some(model) = TmcModel::of_kind(kind) else {
            continue;
        };
        {
            let stepper = s.arg().unwrap_or_default().to_string();
            let motor = steppers
                .iter()
                .map(|r| (&r.name, &r.motor))
                .chain(extras.iter().map(|e| (&e.name, &e.motor)))
                .find(|(n, _)| **n == stepper)
                .map(|(_, m)| m)
                .or_else(|| extruders.iter().find(|(n, _)| *n == stepper).map(|(_, m)| *m));
            let Some(motor) = motor else {
                return Err(ConfigError::BadSection {
                    at: s.at().clone(),
                    section: s.name().to_string(),
                    reason: format!("Could not find config section '[{stepper}]' required by tmc driver"),
                });
            };
            let chip = tmc::chip_name(kind, &stepper);
            let homes_on_it = steppers
                .iter()
                .any(|r| r.endstop_pin.as_ref().is_some_and(|p| p.mcu == chip));
            out.push(tmc::read_tmc(&s, model, &stepper, motor, homes_on_it, pins)?);
        }
    }
    Ok(out)
}

/// Pin providers among the ignored sections: `[sx1509 NAME]` provides
/// chip `NAME`, `[replicape]` chip `replicape` (Klipper's
/// names), as (chip, section name).
fn unsupported_chips(file: &ConfigFile) -> Vec<(String, String)> {
    let chip = |s: &ini::Section| match (s.kind(), s.name().split_whitespace().nth(1)) {
        ("sx1509", Some(name)) => Some(name.to_string()),
        ("replicape", _) => Some("replicape".to_string()),
        _ => None,
    };
    file.sections()
        .iter()
        .filter_map(|s| chip(s).map(|c| (c, s.name().to_string())))
        .collect()
}

/// The first section of a kind [`SECTIONS`] refuses, as an error naming the missing feature.
fn refuse_unsupported(file: &ConfigFile) -> Result<(), ConfigError> {
    for section in file.sections() {
        if let Some(SectionSupport::Refused(feature)) = section_support(section.kind()) {
            return Err(ConfigError::BadSection {
                at: section.at().clone(),
                section: section.name().to_string(),
                reason: format!("is not supported by Cadence yet ({feature})"),
            });
        }
    }
    Ok(())
}

/// Reads, parses and validates the printer config at `path` (includes relative to it).
pub fn load(path: &Path) -> Result<PrinterConfig, ConfigError> {
    PrinterConfig::from_ini(&ini::load(path)?)
}

/// Parses and validates `text` as the file `name`; includes are read relative to `name`'s
/// directory.
pub fn parse_str(text: &str, name: &Path) -> Result<PrinterConfig, ConfigError> {
    PrinterConfig::from_ini(&ini::parse_str(text, name)?)
}

/// The built-in simulated printer ([`SIMULATED_PRINTER_CFG`]).
pub fn builtin_simulated() -> Result<PrinterConfig, ConfigError> {
    parse_str(SIMULATED_PRINTER_CFG, Path::new(SIMULATED_PRINTER_NAME))
}

/// The built-in simulated printer with `section` added after it, parsed (the section
/// modules' tests); an error as its message.
#[cfg(test)]
pub(crate) fn simulated_with(section: &str) -> Result<PrinterConfig, String> {
    let text = format!("{SIMULATED_PRINTER_CFG}\n{section}\n");
    parse_str(&text, Path::new("printer.cfg")).map_err(|e| e.to_string())
}

#[cfg(test)]
pub(crate) mod test_support;
#[cfg(test)]
mod tests;
