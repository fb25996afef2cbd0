//! Why a homing or probing command failed: the wiring, the MCUs (a dead link, a lost reply, a
//! timeout of the trigger relay), the endstop or probe (no trigger, still triggered), a late
//! step, a bad command parameter or a BLTouch that does not answer as it should.

use links::dict::DictError;
use links::mcu::LinkError;
use links::trsync::{TrsyncError, COMM_TIMEOUT_MSG};
use planner::kinematics::KinError;
use planner::machine::PlanError;

use crate::mcus::McuError;
use crate::step_stream::StreamError;

/// Why G28 with motion, a probe command or a homing query failed. The messages are the ones
/// the printer shows (several exactly as Klipper words them).
#[derive(Debug, thiserror::Error)]
pub enum HomingError {
    /// The planner cannot stop and resync (a separate planner thread or pressure advance).
    #[error("G28: homing needs the inline planner without pressure advance")]
    NeedsInlinePlanner,
    /// The steppers of one axis on several MCUs, its endstop on yet another.
    #[error(transparent)]
    Wiring(Box<WiringError>),
    /// Delta: its towers home together.
    #[error(
        "homing {axis}: {kinematics} kinematics is not supported: its towers home together, \
         which Cadence does not do yet (cartesian, corexy and corexz axes can be homed)"
    )]
    UnsupportedKinematics { axis: char, kinematics: &'static str },
    /// The endstop still reads triggered once the axis moved away from it.
    #[error("Endstop {axis} still triggered after retract")]
    StillTriggered { axis: char },
    /// A further motor's own endstop (`z1`: `[stepper_z1]`'s, Klipper's name) still reads
    /// triggered once the motors retracted from the rail's endstop.
    #[error("Endstop {endstop} still triggered after retract")]
    MotorStillTriggered { endstop: String },
    /// A further motor's own endstop on a rail whose motors move more than one toolhead axis.
    #[error(
        "homing {axis}: [{stepper}] endstop_pin: a motor's own endstop is supported on a rail that moves \
         its axis alone (cartesian rails, corexz Y), not on {kinematics}"
    )]
    OwnEndstopKinematics {
        axis: char,
        stepper: String,
        kinematics: &'static str,
    },
    /// The trigger relay timed out (an MCU's trsync expired or went silent).
    #[error("{}", COMM_TIMEOUT_MSG)]
    CommTimeout,
    /// The move ended without a trigger (`what`: the axis letter or `probe`).
    #[error("No trigger on {what} after full movement")]
    NoTrigger { what: String },
    /// The group stopped for another reason than the endstop.
    #[error("homing {axis}: the move stopped with trigger reason {reason}")]
    StoppedWithReason { axis: char, reason: u8 },
    /// An MCU reported a trigger but the endstop has no trigger clock.
    #[error("homing {axis}: '{reporter}' reported a trigger but the endstop did not trigger")]
    FalseTrigger { axis: char, reporter: String },
    /// The trigger outcome carried no clock.
    #[error("homing {axis}: no trigger clock")]
    NoTriggerClock { axis: char },
    /// No stepper moves the axis.
    #[error("homing {axis}: the axis has no stepper")]
    NoStepper { axis: char },
    /// A stepper of the axis has no kinematics.
    #[error("homing {axis}: {stepper}: {source}")]
    StepperKinematics {
        axis: char,
        stepper: String,
        #[source]
        source: KinError,
    },
    /// The homing move is empty (already at the target).
    #[error("homing {axis}: the homing move has no length")]
    NoMoveLength { axis: char },
    /// The halt position cannot be computed.
    #[error("homing {axis}: the kinematics is not linear")]
    NotLinear { axis: char },
    /// A step command of a homing move would reach its MCU with less than the minimum lead.
    #[error(
        "homing: a step for {stepper} on mcu '{mcu}' was ready only {ready_ms:.1} ms before it is due (at least {min_ms:.0} ms \
         required)"
    )]
    LateStep {
        stepper: String,
        mcu: String,
        ready_ms: f64,
        min_ms: f64,
    },
    /// An MCU's clock did not reach the end of the planned moves.
    #[error("homing: the clock of mcu '{mcu}' did not reach the end of the planned moves in time")]
    ClockStalled { mcu: String },
    /// The wiring names an MCU that is not connected.
    #[error("homing: no MCU called '{name}'")]
    NoMcu { name: String },
    /// A query's reply lacks a field.
    #[error("{response} without {field}")]
    MissingField {
        response: &'static str,
        field: &'static str,
    },
    /// An MCU's dictionary cannot encode a homing command.
    #[error("mcu '{mcu}': {source}")]
    Encode {
        mcu: String,
        #[source]
        source: DictError,
    },
    /// An MCU's link failed.
    #[error("mcu '{mcu}': {source}")]
    McuLink {
        mcu: String,
        #[source]
        source: LinkError,
    },
    /// A link error that names its MCU itself.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// The trigger group could not be set up.
    #[error(transparent)]
    Trsync(#[from] TrsyncError),
    /// An MCU shut down or its IO failed.
    #[error(transparent)]
    Mcu(#[from] McuError),
    /// The homing move's steps could not be streamed.
    #[error(transparent)]
    Stream(#[from] StreamError),
    /// The planner refused the homing move or the resync.
    #[error(transparent)]
    Plan(#[from] PlanError),
    /// A dictionary without a command the BLTouch needs.
    #[error(transparent)]
    Dictionary(#[from] DictError),
    /// A probe command's parameter.
    #[error("Error on '{raw}': {problem}")]
    BadParameter { raw: String, problem: ParamProblem },
    /// A probe or BLTouch command on a printer without that section.
    #[error("Unknown command: {name} (the printer config has no [{section}] section)")]
    NoSection { name: String, section: &'static str },
    /// A bed levelling command (`BED_MESH_*`, `Z_TILT_ADJUST`, `QUAD_GANTRY_LEVEL`,
    /// `SCREWS_TILT_CALCULATE`…) failed for a reason of its own.
    #[error(transparent)]
    Leveling(#[from] LevelingError),
    /// A TMC driver's command or register traffic.
    #[error(transparent)]
    Tmc(#[from] crate::tmc::TmcError),
    /// A sensorless endstop whose driver is not among the printer's TMC drivers (a bug).
    #[error("sensorless endstop without its driver")]
    NoSensorlessDriver,
    /// PROBE: the samples spread more than `samples_tolerance`, retries exhausted.
    #[error("Probe samples exceed samples_tolerance")]
    SamplesOutOfTolerance,
    /// PROBE before Z is homed.
    #[error("Must home before probe")]
    NotHomed,
    /// The probe reads triggered before the probing move.
    #[error("Probe triggered prior to movement")]
    TriggeredBeforeMove,
    /// A BLTouch command name that does not exist.
    #[error("bltouch: unknown command '{name}'")]
    BlTouchUnknownCommand { name: String },
    /// The BLTouch pin did not go up.
    #[error("BLTouch failed to raise probe")]
    BlTouchRaise,
    /// The BLTouch did not report the expected state in touch mode.
    #[error("BLTouch failed to verify sensor state")]
    BlTouchSensor,
    /// SET_SMART_EFFECTOR SENSITIVITY= without a control pin (Klipper's words).
    #[error("control_pin must be set in [smart_effector] for sensitivity programming")]
    SmartEffectorNoControlPin,
    /// The main MCU's clock did not reach the end of a BLTouch command.
    #[error("bltouch: the main MCU's clock did not reach the end of the probe's command")]
    BlTouchClock,
}

/// The steppers of one axis on several MCUs while its endstop is on yet another: the trigger
/// relay cannot serve that.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error(
    "[{section}] {option} '{pin}': the steppers of axis {axis} are on MCUs '{}' while its endstop is on \
     yet another MCU '{endstop_mcu}': put the endstop on one of the steppers' MCUs or all steppers of the \
     axis on one MCU",
    .mcus.join("', '")
)]
pub struct WiringError {
    pub section: String,
    pub option: &'static str,
    pub pin: String,
    pub axis: char,
    pub mcus: Vec<String>,
    pub endstop_mcu: String,
}

/// What is wrong with a probe command's parameter.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ParamProblem {
    #[error("malformed parameter '{word}' (expected KEY=VALUE)")]
    Malformed { word: String },
    #[error("unable to parse '{value}' for {key}")]
    Unparsable { value: String, key: String },
    #[error("{key} must be above {min}")]
    NotAbove { key: String, min: f64 },
    #[error("{key} must have minimum of {min}")]
    BelowMinimum { key: String, min: f64 },
    #[error("{key} must have maximum of {max}")]
    AboveMaximum { key: String, max: f64 },
    #[error("{key} is too large")]
    TooLarge { key: String },
    #[error("SAMPLES_RESULT must be median or average, got '{value}'")]
    SamplesResult { value: String },
    #[error("{key} must be 'X,Y', got '{value}'")]
    NotPair { key: String, value: String },
    #[error("only METHOD=automatic (the probe) is supported")]
    OnlyAutomatic,
    #[error("ADAPTIVE meshes are not supported by Cadence yet")]
    Adaptive,
    #[error("PROBE_COUNT must be whole numbers from 3 to 99")]
    ProbeCount,
    #[error("ROUND_PROBE_COUNT must be odd, from 3 to 99")]
    RoundProbeCount,
    #[error("MESH_MAX must be above MESH_MIN")]
    MeshMaxBelowMin,
    #[error("ALGORITHM must be lagrange or bicubic, got '{value}'")]
    Algorithm { value: String },
    #[error("give LOAD=, SAVE= or REMOVE= and a profile name")]
    ProfileAction,
    #[error("DIRECTION must be CW or CCW, got '{value}'")]
    Direction { value: String },
}

/// Why a bed levelling command failed for a reason of its own (its probing and moves fail
/// with the other [`HomingError`]s), in Klipper's words where it has them.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LevelingError {
    /// The command probes, the printer has no `[probe]`/`[bltouch]`.
    #[error("{name} needs a probe")]
    NeedsProbe { name: String },
    /// Levelling before every axis is homed.
    #[error("Must home axes first")]
    NotHomed,
    /// The mesh state's lock was poisoned (a thread panicked holding it).
    #[error("bed_mesh: state lost")]
    MeshStateLost,
    /// `BED_MESH_PROFILE LOAD=`/`REMOVE=` of a profile that does not exist.
    #[error("bed_mesh: Unknown profile [{name}]")]
    UnknownProfile { name: String },
    /// `BED_MESH_PROFILE SAVE=` without a mesh.
    #[error("Unable to save to profile, the bed has not been probed")]
    NotProbed,
    /// A row of the probe grid without a probed point.
    #[error("bed_mesh: a row of the mesh has no probe point")]
    EmptyRow,
    /// The probed heights do not make a mesh.
    #[error(transparent)]
    Mesh(#[from] planner::bed_mesh::MeshError),
    /// `[z_tilt]`/`[quad_gantry_level]` with another number of `z_positions` than Z motors.
    #[error("{name}: {motors} Z motors but {positions} motor positions")]
    MotorCount {
        name: String,
        motors: usize,
        positions: usize,
    },
    /// The probed range stayed above `retry_tolerance` for every retry.
    #[error("Too many retries")]
    TooManyRetries,
    /// The probe points do not determine a plane (or surface).
    #[error("{name}: the probe points do not span the bed")]
    NoSpan { name: String },
    /// A quad gantry correction above `max_adjust`.
    #[error(
        "Aborting quad_gantry_level required adjustment {adjust:.6} is greater than max_adjust {max:.6}"
    )]
    MaxAdjust { adjust: f64, max: f64 },
    /// `SCREWS_TILT_CALCULATE MAX_DEVIATION=`: a screw farther than that from the base.
    #[error("bed level exceeds configured limits ({max}mm)! Adjust screws and restart print.")]
    ExceedsLimits { max: f64 },
}
