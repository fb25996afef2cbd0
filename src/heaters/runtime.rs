//! The heater loop of a live print, on its own thread (`heaters`): it starts each ADC's
//! periodic reports (`query_analog_in` with Klipper's oversampling and the range check that
//! lets the MCU shut itself down on an open or shorted sensor), turns each report into a
//! temperature (smoothed over `smooth_time`), runs the heater's control (PID or watermark) and
//! schedules the PWM on the MCU clock (`queue_digital_out`, refreshed well within the
//! `max_duration` the MCU enforces), runs `[verify_heater]` once a second of MCU time, and
//! drives the fans. Time is the heater MCU's clock in seconds (`clock / CLOCK_FREQ`), so a
//! simulated printer with `--time-scale` heats in scaled time like everything else.
//!
//! The planner thread and the API reach it through [`HeaterShared`] (atomics and one mutex
//! for the fault text): targets and fan speeds in, temperatures, powers and settled flags out.
//! A thermal runaway sets the fault (`Heater NAME not heating at expected rate`), turns every
//! heater off and shuts every MCU down (`emergency_stop`: their outputs fall to their default,
//! off), as Klipper does.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::Duration;

use links::dict::Dictionary;
use links::mcu::McuLink;

use super::adc_scaled::ScaledRefs;
use super::calibrate::RelayTuner;
use super::control::{Control, Pid, PidGains, SmithPredictor, Smoothed, Watermark};
use super::objects::{
    adc_range, FanRole, MultiOutput, Thermal, ThermalObject, RANGE_CHECK_COUNT, REPORT_TIME, SAMPLE_COUNT,
    SAMPLE_TIME,
};
use super::spi_sensor::SpiReader;
use super::tachometer::Tachometer;
use super::verify::{VerifyHeater, CHECK_INTERVAL_S};
use crate::mcus::Mcus;
use sysconfig::printer::HeaterControl;

/// An `f64` in an atomic.
#[derive(Debug, Default)]
pub struct AtomicF64(AtomicU64);

impl AtomicF64 {
    fn new(v: f64) -> AtomicF64 {
        AtomicF64(AtomicU64::new(v.to_bits()))
    }
    /// The value.
    pub fn get(&self) -> f64 {
        f64::from_bits(self.0.load(Ordering::Acquire))
    }
    pub(crate) fn set(&self, v: f64) {
        self.0.store(v.to_bits(), Ordering::Release)
    }
}

/// One heater's state as the other threads see it.
#[derive(Debug)]
pub struct HeaterCell {
    /// `extruder`, `heater_bed`, …
    pub name: String,
    /// Target (°C, 0 = off).
    pub target: AtomicF64,
    /// Smoothed temperature (°C; NaN before the first report).
    pub temp: AtomicF64,
    /// Power applied (0..=max_power).
    pub power: AtomicF64,
    /// Its control says it has not settled at the target (M109/M190 keep waiting).
    pub busy: AtomicBool,
    /// MCU seconds of the latest report.
    pub time: AtomicF64,
    /// Highest temperature seen during the print.
    pub max_seen: AtomicF64,
}

/// One fan's state.
#[derive(Debug)]
pub struct FanCell {
    /// `fan` or the NAME of its section.
    pub name: String,
    /// Klipper's object kind: `fan`, `heater_fan`, `controller_fan`, `fan_generic`,
    /// `temperature_fan`.
    pub kind: &'static str,
    /// Requested speed (0..=1): M106/M107 for `[fan]`, SET_FAN_SPEED for `[fan_generic]`.
    pub requested: AtomicF64,
    /// Speed applied (0..=1, before `max_power`).
    pub speed: AtomicF64,
    /// A temperature fan's target (°C; NaN for other fans) and speed range.
    pub target: AtomicF64,
    pub min_speed: AtomicF64,
    pub max_speed: AtomicF64,
    /// A temperature fan's sensor (index in [`HeaterShared::sensors`]).
    pub sensor: Option<usize>,
    /// The tachometer's speed (rev/min; NaN without `tachometer_pin` or before its first
    /// measure).
    pub rpm: AtomicF64,
}

/// One temperature sensor's state (`[temperature_sensor]`, a `[temperature_fan]`'s sensor).
#[derive(Debug)]
pub struct SensorCell {
    pub name: String,
    /// `temperature_sensor` or `temperature_fan`.
    pub kind: &'static str,
    /// `gcode_id`: its M105 name.
    pub gcode_id: Option<String>,
    /// Smoothed temperature (°C; NaN before the first report).
    pub temp: AtomicF64,
    /// Lowest and highest temperature seen (Klipper's `measured_min_temp`/`measured_max_temp`).
    pub min_seen: AtomicF64,
    pub max_seen: AtomicF64,
    /// MCU seconds of the latest report.
    pub time: AtomicF64,
}

/// A PID_CALIBRATE between the G-code and the heater thread.
#[derive(Debug, Clone, PartialEq)]
pub enum Calibration {
    /// Asked for: heater `heater`'s relay test at `target`.
    Requested { heater: usize, target: f64 },
    /// The heater thread runs it.
    Running { heater: usize },
    /// Over: the gains (`None`: the heater loop ended first) and the samples, as Klipper's
    /// WRITE_FILE keeps them: (time, power) at each power change, (time, temperature) of
    /// each report.
    Done {
        heater: usize,
        gains: Option<PidGains>,
        pwm: Vec<(f64, f64)>,
        temps: Vec<(f64, f64)>,
    },
}

/// What the heater thread shares with the planner thread and the API.
#[derive(Debug)]
pub struct HeaterShared {
    pub heaters: Vec<HeaterCell>,
    pub fans: Vec<FanCell>,
    pub sensors: Vec<SensorCell>,
    /// Motion is being planned (a print runs, a session is not idle): `[controller_fan]`
    /// counts the steppers as enabled.
    pub motors_on: AtomicBool,
    /// The PID_CALIBRATE in progress, if any.
    pub calibration: Mutex<Option<Calibration>>,
    fault: Mutex<Option<String>>,
    /// The latest SPI temperature chip fault (see [`HeaterShared::chip_fault`]).
    chip_fault: Mutex<Option<String>>,
    faulted: AtomicBool,
    /// Ends the heater thread (every heater off first).
    pub stop: AtomicBool,
}

impl HeaterShared {
    /// The shared state of `thermal`'s heaters and fans (cold, off).
    pub fn new(thermal: &Thermal) -> HeaterShared {
        HeaterShared {
            heaters: thermal
                .heaters
                .iter()
                .map(|h| HeaterCell {
                    name: h.name.clone(),
                    target: AtomicF64::new(0.0),
                    temp: AtomicF64::new(f64::NAN),
                    power: AtomicF64::new(0.0),
                    busy: AtomicBool::new(false),
                    time: AtomicF64::new(0.0),
                    max_seen: AtomicF64::new(f64::NAN),
                })
                .collect(),
            fans: thermal
                .fans
                .iter()
                .map(|f| {
                    let (target, min_speed, max_speed, sensor) = match f.role {
                        FanRole::Temperature {
                            target_temp,
                            min_speed,
                            max_speed,
                            sensor,
                            ..
                        } => (target_temp, min_speed, max_speed, Some(sensor)),
                        _ => (f64::NAN, 0.0, 1.0, None),
                    };
                    FanCell {
                        name: f.name.clone(),
                        kind: f.role.kind(),
                        requested: AtomicF64::new(0.0),
                        speed: AtomicF64::new(0.0),
                        target: AtomicF64::new(target),
                        min_speed: AtomicF64::new(min_speed),
                        max_speed: AtomicF64::new(max_speed),
                        sensor,
                        rpm: AtomicF64::new(f64::NAN),
                    }
                })
                .collect(),
            sensors: thermal
                .sensors
                .iter()
                .map(|s| SensorCell {
                    name: s.name.clone(),
                    kind: if s.fan.is_some() {
                        "temperature_fan"
                    } else {
                        "temperature_sensor"
                    },
                    gcode_id: s.gcode_id.clone(),
                    temp: AtomicF64::new(f64::NAN),
                    min_seen: AtomicF64::new(f64::NAN),
                    max_seen: AtomicF64::new(f64::NAN),
                    time: AtomicF64::new(0.0),
                })
                .collect(),
            motors_on: AtomicBool::new(false),
            calibration: Mutex::new(None),
            fault: Mutex::new(None),
            chip_fault: Mutex::new(None),
            faulted: AtomicBool::new(false),
            stop: AtomicBool::new(false),
        }
    }

    /// The thermal runaway (or other heater fault) that shut the printer down, if any.
    pub fn fault(&self) -> Option<String> {
        if !self.faulted.load(Ordering::Acquire) {
            return None;
        }
        self.fault.lock().ok().and_then(|f| f.clone())
    }

    /// The latest fault an SPI temperature chip reported (its fault bits' meaning), if any.
    pub fn chip_fault(&self) -> Option<String> {
        self.chip_fault.lock().ok().and_then(|f| f.clone())
    }

    fn note_chip_fault(&self, why: String) {
        if let Ok(mut f) = self.chip_fault.lock() {
            *f = Some(why);
        }
    }

    fn set_fault(&self, why: String) {
        if let Ok(mut f) = self.fault.lock() {
            if f.is_none() {
                *f = Some(why);
            }
        }
        self.faulted.store(true, Ordering::Release);
    }

    /// Sets every heater's target to 0 (TURN_OFF_HEATERS, M112).
    pub fn turn_off_all(&self) {
        self.heaters.iter().for_each(|h| h.target.set(0.0));
    }

    /// Sets heater `i`'s target.
    pub fn set_target(&self, i: usize, target: f64) {
        if let Some(h) = self.heaters.get(i) {
            h.target.set(target);
            std::sync::atomic::fence(Ordering::SeqCst);
            // Busy at once: a wait that follows must not see the old settled state (the
            // heater loop's next update keeps it so: see `update_heater`).
            h.busy.store(target > 0.0, Ordering::Release);
        }
    }

    /// Starts PID_CALIBRATE on heater `i` at `target` (its target set at once, as Klipper
    /// does); false when one is already running.
    pub fn start_calibration(&self, i: usize, target: f64) -> bool {
        let Ok(mut c) = self.calibration.lock() else {
            return false;
        };
        if matches!(
            *c,
            Some(Calibration::Requested { .. } | Calibration::Running { .. })
        ) {
            return false;
        }
        *c = Some(Calibration::Requested { heater: i, target });
        self.set_target(i, target);
        true
    }

    /// The finished calibration, taken (`None` while one runs or when there is none).
    pub fn take_calibration(&self) -> Option<Calibration> {
        let mut c = self.calibration.lock().ok()?;
        if matches!(*c, Some(Calibration::Done { .. })) {
            c.take()
        } else {
            None
        }
    }

    /// True while a calibration is asked for or running.
    pub fn calibrating(&self) -> bool {
        self.calibration.lock().is_ok_and(|c| {
            matches!(
                *c,
                Some(Calibration::Requested { .. } | Calibration::Running { .. })
            )
        })
    }

    /// Sets the part fan's speed (M106/M107; 0..=1).
    pub fn set_fan(&self, name: &str, speed: f64) {
        if let Some(f) = self.fans.iter().find(|f| f.name == name && f.kind == "fan") {
            f.requested.set(speed.clamp(0.0, 1.0));
        }
    }

    /// Sets fan `i`'s requested speed (SET_FAN_SPEED; 0..=1).
    pub fn set_fan_index(&self, i: usize, speed: f64) {
        if let Some(f) = self.fans.get(i) {
            f.requested.set(speed.clamp(0.0, 1.0));
        }
    }
}

/// Sets [`HeaterShared::stop`] when dropped (ends the heater loop on every way out of a print).
#[derive(Debug)]
pub struct StopOnDrop<'a>(pub &'a HeaterShared);

impl Drop for StopOnDrop<'_> {
    fn drop(&mut self) {
        self.0.stop.store(true, Ordering::Release);
    }
}

/// Klipper's M105 report: `ID:current /target` of every heater and sensor with a G-code id
/// (`T0` the extruder, `B` the bed, a sensor's `gcode_id`), sorted by id; `T:0` when none.
pub fn m105_text(shared: &HeaterShared) -> String {
    let shown = |t: f64| if t.is_nan() { 0.0 } else { t };
    let mut parts: Vec<(String, f64, f64)> = Vec::new();
    for h in &shared.heaters {
        let id = match h.name.as_str() {
            "heater_bed" => "B".to_string(),
            name => match planner::extruders::extruder_index(name) {
                Some(k) => format!("T{k}"),
                None => continue,
            },
        };
        parts.push((id, shown(h.temp.get()), h.target.get()));
    }
    for (i, s) in shared.sensors.iter().enumerate() {
        let Some(id) = &s.gcode_id else {
            continue;
        };
        let target = shared
            .fans
            .iter()
            .find(|f| f.sensor == Some(i))
            .map_or(0.0, |f| f.target.get());
        parts.push((id.clone(), shown(s.temp.get()), target));
    }
    if parts.is_empty() {
        return "T:0".to_string();
    }
    parts.sort_by(|a, b| a.0.cmp(&b.0));
    parts
        .iter()
        .map(|(id, t, target)| format!("{id}:{t:.1} /{target:.1}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// One heater's loop state.
struct Running {
    /// Further outputs of a `[multi_pin]` heater (oid, inverted): they get the same updates.
    extra: Vec<(u8, bool)>,
    link_index: usize,
    pwm_oid: u8,
    /// The MCU (index in the list) and oid of its sensor.
    adc_link: usize,
    adc_oid: u8,
    cycle_ticks: f64,
    invert: bool,
    max_power: f64,
    smooth: Smoothed,
    control: Box<dyn Control + Send>,
    verify: VerifyHeater,
    next_check: f64,
    last_count: u16,
    /// (MCU clock, on_ticks) of the last update sent.
    last_sent: Option<(u64, u32)>,
    /// Seconds per sensor fraction: ADC full scale of one report.
    full_scale: f64,
    sensor: super::thermistor::Sensor,
    /// PID_CALIBRATE's relay in place of the control while it runs.
    relay: Option<Relay>,
    /// An SPI temperature chip read in place of the ADC.
    spi: Option<SpiReader>,
    /// On a time-scaled simulated MCU: the reading as it would be without the update's lead,
    /// and the sum and count of the powers decided since the last update (it sends their mean).
    smith: Option<SmithPredictor>,
    decided: (f64, f64),
}

/// A running PID_CALIBRATE: the tuner and its samples.
struct Relay {
    tuner: RelayTuner,
    pwm: Vec<(f64, f64)>,
    temps: Vec<(f64, f64)>,
}

struct RunningFan {
    /// Further outputs of a `[multi_pin]` fan (oid, inverted): they get the same updates.
    extra: Vec<(u8, bool)>,
    /// `hardware_pwm`: `cycle_ticks` is then PWM_MAX and updates are `queue_pwm_out`.
    hardware: bool,
    link_index: usize,
    oid: u8,
    cycle_ticks: f64,
    invert: bool,
    last: Option<f64>,
    /// A temperature fan's control (its output is taken from `max_speed`: hotter → faster),
    /// the time of the last reading it saw, and its speed then.
    control: Option<Box<dyn Control + Send>>,
    last_reading: f64,
    temp_speed: f64,
    /// MCU seconds a controller fan was last active at.
    last_active: Option<f64>,
}

/// One sensor's loop state.
struct RunningSensor {
    link_index: usize,
    oid: u8,
    smooth: Smoothed,
    full_scale: f64,
    sensor: super::thermistor::Sensor,
    last_count: u16,
    /// An SPI temperature chip read in place of the ADC.
    spi: Option<SpiReader>,
}

/// Seconds of wall time a PWM update is sent ahead of its clock at least (and 0.1 s of MCU
/// time): host pauses of this VM's kind (~10–100 ms) must not make an update late, which the
/// MCU would take as a missed update and shut down. On a time-scaled simulator this is more MCU
/// time, capped at half the heaters' `max_duration` ([`Thermal::max_heat_time`]), so refreshes
/// keep within it; the control makes up for the long lead ([`SmithPredictor`]).
const WALL_LEAD_S: f64 = 0.25;

/// Why the heater loop stopped (every heater is off by then).
#[derive(Debug, thiserror::Error)]
pub enum HeaterLoopError {
    /// More objects than a u8 oid can number.
    #[error("too many objects")]
    TooManyObjects,
    /// A command does not encode.
    #[error(transparent)]
    Dictionary(#[from] links::dict::DictError),
    /// The MCU link refused a message.
    #[error(transparent)]
    Link(#[from] links::mcu::LinkError),
    /// `temperature_mcu` on an MCU it cannot be calibrated for.
    #[error(transparent)]
    McuSensor(#[from] super::mcu_sensor::McuSensorError),
    /// An SPI temperature chip's reports could not be started.
    #[error(transparent)]
    SpiSensor(#[from] super::spi_sensor::SpiQueryError),
}

/// Runs the heater loop until `shared.stop` (then every heater off) or an MCU shutdown. Errors
/// (a missing command, a dead link) end the loop and are returned after every heater is off.
pub fn run(mcus: &Mcus, thermal: &Thermal, shared: &HeaterShared) -> Result<(), HeaterLoopError> {
    if thermal.heaters.is_empty() && thermal.fans.is_empty() && thermal.sensors.is_empty() {
        return Ok(());
    }
    let mut heaters = Vec::new();
    let mut fans = Vec::new();
    let mut sensors = Vec::new();
    let mut scaled: Vec<Option<ScaledRefs>> = thermal.scaled.iter().map(|_| None).collect();
    let mut tachs = Vec::new();
    // Heater sensors: (heater, link, oid, first report clock), started once every heater's
    // state exists (a sensor's MCU may come before its heater's).
    let mut sensor_starts: Vec<(usize, usize, u8, f64)> = Vec::new();
    for (li, conn) in mcus.list.iter().enumerate() {
        let objects = thermal.objects_on(&conn.name);
        if objects.is_empty() {
            continue;
        }
        let dict = conn.link.dictionary();
        let freq = conn.clock_freq;
        // Right after the trsync (see crate::mcus::config_commands).
        let oid0 = usize::from(conn.trsync_oid) + 1;
        let adc_max = dict.config_f64("ADC_MAX").unwrap_or(4095.0);
        // The first round starts once the query has surely arrived (0.1 s of MCU time past
        // the update lead).
        let start = lead_clock(&conn.link, freq, thermal.max_heat_time()) as f64 + 0.1 * freq;
        for (k, obj) in objects.iter().enumerate() {
            let oid = u8::try_from(oid0 + k).map_err(|_| HeaterLoopError::TooManyObjects)?;
            match *obj {
                ThermalObject::HeaterPwm(i) => {
                    heaters.push((i, running_heater(thermal, i, li, oid, freq, adc_max)))
                }
                ThermalObject::HeaterAdc(i) => sensor_starts.push((i, li, oid, start)),
                ThermalObject::SensorAdc(i) => {
                    let s = &thermal.sensors[i];
                    let sensor = s.sensor_on(&dict.config_str("MCU").unwrap_or_default())?;
                    let range = (s.min_temp.max(-273.0), s.max_temp.min(1e4));
                    let spi = match &s.spi {
                        Some(spi) => Some(SpiReader::start(
                            &conn.link,
                            dict,
                            spi,
                            oid,
                            start,
                            freq,
                            REPORT_TIME,
                            range,
                        )?),
                        None => {
                            let (lo, hi) = adc_range(&sensor, range.0, range.1, adc_max);
                            query_analog(&conn.link, dict, oid, start, freq, lo, hi, 0)?;
                            None
                        }
                    };
                    sensors.push((
                        i,
                        RunningSensor {
                            link_index: li,
                            oid,
                            smooth: Smoothed::new(s.smooth_time),
                            full_scale: adc_max * f64::from(SAMPLE_COUNT),
                            sensor,
                            last_count: 0,
                            spi,
                        },
                    ));
                }
                // Read through their readers (`HeaterAdc`, `SensorAdc`).
                ThermalObject::HeaterSpi(_) | ThermalObject::SensorSpi(_) => {}
                ThermalObject::Fan(i) => fans.push((i, running_fan(thermal, i, li, oid, dict, freq)?)),
                ThermalObject::MultiPwm(k, j) => {
                    let (output, pins) = &thermal.multi_outputs[k];
                    let invert = pins.get(j).is_some_and(|p| p.invert);
                    match *output {
                        MultiOutput::Heater(i) => {
                            if let Some((_, r)) = heaters.iter_mut().find(|(h, _)| *h == i) {
                                r.extra.push((oid, invert));
                            }
                        }
                        MultiOutput::Fan(i) => {
                            if let Some((_, f)) = fans.iter_mut().find(|(n, _)| *n == i) {
                                f.extra.push((oid, invert));
                            }
                        }
                    }
                }
                ThermalObject::Tach(i) => {
                    let opts = &thermal.fans[i].opts;
                    let t = Tachometer::new(i, li, oid, opts.tachometer_ppr);
                    t.start(&conn.link, start as u64, freq, opts.tachometer_poll_interval)?;
                    tachs.push(t);
                }
                ThermalObject::ScaledVref(k) | ThermalObject::ScaledVssa(k) => {
                    query_analog(&conn.link, dict, oid, start, freq, 0, u16::MAX, 0)?;
                    let smooth_time = thermal.scaled[k].smooth_time;
                    if let Some(refs) = scaled.get_mut(k) {
                        let r = refs
                            .get_or_insert_with(|| ScaledRefs::new(li, adc_max * f64::from(SAMPLE_COUNT)));
                        match *obj {
                            ThermalObject::ScaledVref(_) => r.set_vref(oid, smooth_time),
                            _ => r.set_vssa(oid, smooth_time),
                        }
                    }
                }
            }
        }
    }
    for (i, li, oid, start) in sensor_starts {
        if let Some((_, r)) = heaters.iter_mut().find(|(h, _)| *h == i) {
            start_heater_sensor(&mcus.list[li], &thermal.heaters[i], r, li, oid, start)?;
        }
    }
    let mut outputs = Outputs {
        fans: &mut fans,
        scaled: &mut scaled,
        tachs: &mut tachs,
    };
    let result = heater_loop(mcus, thermal, shared, &mut heaters, &mut sensors, &mut outputs);
    wind_down(mcus, thermal, shared, &heaters);
    result
}

/// Heater `i`'s running state: its PWM output `oid` on link `li`; its sensor (set by the
/// loop's start from the sensor's own MCU, see [`start_heater_sensor`]).
fn running_heater(thermal: &Thermal, i: usize, li: usize, oid: u8, freq: f64, adc_max: f64) -> Running {
    let h = &thermal.heaters[i];
    Running {
        extra: Vec::new(),
        link_index: li,
        pwm_oid: oid,
        adc_link: li,
        adc_oid: oid,
        cycle_ticks: h.pwm_cycle_time * freq,
        invert: h.heater_pin.invert,
        max_power: h.max_power,
        smooth: Smoothed::new(h.smooth_time),
        control: heater_control(h.control, h.max_power, h.smooth_time),
        verify: VerifyHeater::new(&h.name, h.verify),
        next_check: 0.0,
        last_count: 0,
        last_sent: None,
        full_scale: adc_max * f64::from(SAMPLE_COUNT),
        sensor: h.sensor,
        relay: None,
        spi: None,
        smith: (thermal.sim_time_scale > 1.0).then(|| SmithPredictor::new(h.sim.model())),
        decided: (0.0, 0.0),
    }
}

/// Starts heater `h`'s sensor reports (its ADC or SPI chip `oid` on `conn`, link `li`, from
/// clock `start`), the MCU's range check guarding `min_temp`..`max_temp` (it shuts itself
/// down outside).
fn start_heater_sensor(
    conn: &crate::mcus::McuConn,
    h: &super::objects::HeaterOut,
    r: &mut Running,
    li: usize,
    oid: u8,
    start: f64,
) -> Result<(), HeaterLoopError> {
    let dict = conn.link.dictionary();
    let freq = conn.clock_freq;
    let adc_max = dict.config_f64("ADC_MAX").unwrap_or(4095.0);
    r.adc_link = li;
    r.adc_oid = oid;
    r.full_scale = adc_max * f64::from(SAMPLE_COUNT);
    match &h.spi {
        Some(spi) => {
            let range = (h.min_temp, h.max_temp);
            r.spi = Some(SpiReader::start(
                &conn.link,
                dict,
                spi,
                oid,
                start,
                freq,
                REPORT_TIME,
                range,
            )?);
        }
        None => {
            let (lo, hi) = adc_range(&h.sensor, h.min_temp, h.max_temp, adc_max);
            query_analog(&conn.link, dict, oid, start, freq, lo, hi, RANGE_CHECK_COUNT)?;
        }
    }
    Ok(())
}

/// Fan `i`'s running state: its output `oid` on link `li`.
fn running_fan(
    thermal: &Thermal,
    i: usize,
    li: usize,
    oid: u8,
    dict: &Dictionary,
    freq: f64,
) -> Result<RunningFan, HeaterLoopError> {
    let f = &thermal.fans[i];
    Ok(RunningFan {
        extra: Vec::new(),
        link_index: li,
        oid,
        // A hardware PWM's duty is in 0..=PWM_MAX (Klipper's pwm_max).
        hardware: f.opts.hardware_pwm,
        cycle_ticks: if f.opts.hardware_pwm {
            dict.config_f64("PWM_MAX")?
        } else {
            f.opts.cycle_time * freq
        },
        invert: f.opts.pin.invert,
        last: None,
        control: match f.role {
            FanRole::Temperature {
                control, max_speed, ..
            } => Some(fan_control(control, max_speed)),
            _ => None,
        },
        last_reading: f64::NEG_INFINITY,
        temp_speed: 0.0,
        last_active: None,
    })
}

/// The heater's control as configured: watermark or PID.
fn heater_control(control: HeaterControl, max_power: f64, smooth_time: f64) -> Box<dyn Control + Send> {
    match control {
        HeaterControl::Watermark { max_delta } => Box::new(Watermark::new(max_delta, max_power)),
        HeaterControl::Pid { kp, ki, kd } => {
            Box::new(Pid::new(PidGains { kp, ki, kd }, max_power, smooth_time))
        }
    }
}

/// After the loop, whatever ended it: a calibration cut short ends without gains (the G-code
/// waiting for it goes on) and every heater goes off (an MCU that shut down has them off
/// already).
fn wind_down(mcus: &Mcus, thermal: &Thermal, shared: &HeaterShared, heaters: &[(usize, Running)]) {
    if let Ok(mut c) = shared.calibration.lock() {
        if let Some(Calibration::Requested { heater, .. } | Calibration::Running { heater }) = *c {
            *c = Some(Calibration::Done {
                heater,
                gains: None,
                pwm: Vec::new(),
                temps: Vec::new(),
            });
        }
    }
    for (_, r) in heaters {
        let conn = &mcus.list[r.link_index];
        let at = lead_clock(&conn.link, conn.clock_freq, thermal.max_heat_time());
        let _ = send_pwm(&conn.link, r.pwm_oid, at, 0, r.invert, r.cycle_ticks);
        for &(oid, invert) in &r.extra {
            let _ = send_pwm(&conn.link, oid, at, 0, invert, r.cycle_ticks);
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn query_analog(
    link: &McuLink,
    dict: &Dictionary,
    oid: u8,
    start: f64,
    freq: f64,
    min: u16,
    max: u16,
    range_check: u8,
) -> Result<(), HeaterLoopError> {
    let cmd = dict.encode(
        "query_analog_in",
        &[
            i64::from(oid),
            (start as u64 & 0xFFFF_FFFF) as i64,
            (SAMPLE_TIME * freq).round() as i64,
            i64::from(SAMPLE_COUNT),
            (REPORT_TIME * freq).round() as i64,
            i64::from(min),
            i64::from(max),
            i64::from(range_check),
        ],
    )?;
    Ok(link.send(cmd)?)
}

/// The lead (MCU ticks) of an update sent now.
fn lead_ticks(link: &McuLink, nominal: f64, max_heat_time: f64) -> f64 {
    (0.1 * nominal)
        .max(WALL_LEAD_S * link.clock().freq())
        .min(0.5 * max_heat_time * nominal)
}

/// The earliest MCU clock an update sent now may be scheduled at.
fn lead_clock(link: &McuLink, nominal: f64, max_heat_time: f64) -> u64 {
    let now = link.clock().clock_at(McuLink::system_now());
    (now + lead_ticks(link, nominal, max_heat_time)) as u64
}

fn send_pwm(
    link: &McuLink,
    oid: u8,
    clock: u64,
    on_ticks: u32,
    invert: bool,
    cycle: f64,
) -> Result<(), HeaterLoopError> {
    let dict = link.dictionary();
    let on = if invert {
        (cycle.round() as u32).saturating_sub(on_ticks)
    } else {
        on_ticks
    };
    let cmd = dict.encode(
        "queue_digital_out",
        &[i64::from(oid), (clock & 0xFFFF_FFFF) as i64, i64::from(on)],
    )?;
    Ok(link.send_clocked(cmd, 0, clock)?)
}

/// Fan `f`'s output at `clock`: `value` on ticks of its cycle (software PWM), or its duty in
/// 0..=PWM_MAX through `queue_pwm_out` (hardware PWM).
fn send_fan(link: &McuLink, f: &RunningFan, clock: u64, value: u32) -> Result<(), HeaterLoopError> {
    if !f.hardware {
        for &(oid, invert) in &f.extra {
            send_pwm(link, oid, clock, value, invert, f.cycle_ticks)?;
        }
        return send_pwm(link, f.oid, clock, value, f.invert, f.cycle_ticks);
    }
    let duty = if f.invert {
        (f.cycle_ticks.round() as u32).saturating_sub(value)
    } else {
        value
    };
    let cmd = link.dictionary().encode(
        "queue_pwm_out",
        &[i64::from(f.oid), (clock & 0xFFFF_FFFF) as i64, i64::from(duty)],
    )?;
    Ok(link.send_clocked(cmd, 0, clock)?)
}

/// On ticks of `power` (0..=1) in a cycle of `cycle` ticks: 0 off, the whole cycle on.
fn on_ticks(power: f64, cycle: f64) -> u32 {
    if power <= 0.0 {
        0
    } else if power >= 1.0 {
        cycle.round() as u32
    } else {
        (power * cycle).round().max(1.0) as u32
    }
}

/// A temperature fan's control: Klipper's watermark or PID on the fan's sensor, whose output
/// (0..=max_speed, "heat wanted") is taken from `max_speed`.
fn fan_control(control: HeaterControl, max_speed: f64) -> Box<dyn Control + Send> {
    match control {
        HeaterControl::Watermark { max_delta } => Box::new(Watermark::new(max_delta, max_speed)),
        HeaterControl::Pid { kp, ki, kd } => Box::new(Pid::new(PidGains { kp, ki, kd }, max_speed, 2.0)),
    }
}

/// The speed a fan wants now (before `off_below`).
fn fan_speed(
    spec: &super::objects::FanOut,
    cell: &FanCell,
    f: &mut RunningFan,
    shared: &HeaterShared,
    now: f64,
) -> f64 {
    match &spec.role {
        FanRole::Part | FanRole::Generic => cell.requested.get(),
        FanRole::Heater {
            heaters: names,
            heater_temp,
            fan_speed,
        } => {
            let hot = shared
                .heaters
                .iter()
                .any(|h| names.contains(&h.name) && (h.target.get() > 0.0 || h.temp.get() > *heater_temp));
            if hot {
                *fan_speed
            } else {
                0.0
            }
        }
        FanRole::Controller {
            heaters: names,
            fan_speed,
            idle_speed,
            idle_timeout,
        } => {
            let active = shared.motors_on.load(Ordering::Acquire)
                || shared
                    .heaters
                    .iter()
                    .any(|h| names.contains(&h.name) && h.target.get() > 0.0);
            if active {
                f.last_active = Some(now);
                *fan_speed
            } else if f.last_active.is_some_and(|t| now - t < *idle_timeout) {
                *idle_speed
            } else {
                0.0
            }
        }
        FanRole::Temperature { sensor, .. } => {
            let Some(s) = shared.sensors.get(*sensor) else {
                return 0.0;
            };
            let (time, temp) = (s.time.get(), s.temp.get());
            if time > f.last_reading && !temp.is_nan() {
                f.last_reading = time;
                let target = cell.target.get();
                let max_speed = cell.max_speed.get();
                let out = f
                    .control
                    .as_mut()
                    .map_or(0.0, |c| c.update(time, temp, target))
                    .clamp(0.0, max_speed);
                let mut speed = (max_speed - out).max(0.0);
                if speed > 0.0 && speed < cell.min_speed.get() {
                    speed = cell.min_speed.get();
                }
                if target <= 0.0 {
                    speed = 0.0;
                }
                f.temp_speed = speed;
            }
            f.temp_speed
        }
    }
}

fn heater_loop(
    mcus: &Mcus,
    thermal: &Thermal,
    shared: &HeaterShared,
    heaters: &mut [(usize, Running)],
    sensors: &mut [(usize, RunningSensor)],
    outputs: &mut Outputs<'_>,
) -> Result<(), HeaterLoopError> {
    let Outputs { fans, scaled, tachs } = outputs;
    loop {
        if shared.stop.load(Ordering::Acquire) {
            return Ok(());
        }
        if mcus.list.iter().any(|m| m.link.shutdown_reason().is_some()) {
            // The MCU's own outputs fell to their defaults (off); nothing more to drive.
            shared.turn_off_all();
            return Ok(());
        }
        start_calibration(shared, heaters);
        let now_sys = McuLink::system_now();
        for c in scaled.iter_mut().flatten() {
            let conn = &mcus.list[c.link_index];
            c.update(&conn.link, conn.clock_freq, now_sys);
        }
        for (i, r) in heaters.iter_mut() {
            let scale = thermal.heaters[*i]
                .sensor_scale
                .map(|k| scaled.get(k).and_then(Option::as_ref));
            if !update_heater(mcus, thermal, shared, *i, r, now_sys, scale) {
                return Ok(());
            }
        }
        for (i, r) in sensors.iter_mut() {
            let scale = thermal.sensors[*i]
                .scale
                .map(|k| scaled.get(k).and_then(Option::as_ref));
            update_sensor(mcus, shared, *i, r, now_sys, scale);
        }
        for (i, f) in fans.iter_mut() {
            update_fan(mcus, thermal, shared, *i, f, now_sys);
        }
        for t in tachs.iter_mut() {
            let conn = &mcus.list[t.link_index];
            if let Some(rpm) = t.update(&conn.link, conn.clock_freq, now_sys) {
                if let Some(cell) = shared.fans.get(t.fan) {
                    cell.rpm.set(rpm);
                }
            }
        }
        // Reports come every 0.3 s of MCU time: look four times per report (every 50 ms at
        // most; every 2 ms at least, on a fast time-scaled simulator).
        let scale = mcus
            .list
            .first()
            .map_or(1.0, |m| m.link.clock().freq() / m.clock_freq)
            .max(1.0);
        std::thread::sleep(Duration::from_secs_f64(
            (REPORT_TIME / scale / 4.0).clamp(0.002, 0.05),
        ));
    }
}

/// The fans, `[adc_scaled]` chips and tachometers of the loop.
struct Outputs<'a> {
    fans: &'a mut [(usize, RunningFan)],
    scaled: &'a mut [Option<ScaledRefs>],
    tachs: &'a mut [Tachometer],
}

/// The ADC fraction of a report `value` summed to `full_scale`, rescaled between the
/// references of its `[adc_scaled]` chip if it has one (`None` until they have read).
fn fraction(value: u16, full_scale: f64, scale: Option<Option<&ScaledRefs>>) -> Option<f64> {
    let raw = f64::from(value) / full_scale;
    match scale {
        None => Some(raw),
        Some(chip) => chip?.scale(raw),
    }
}

/// A heater's sensor clock and output clock: the same MCU's, or two MCUs' mapped through
/// system time (each link's clock estimate).
struct CrossClock {
    same: bool,
    sensor: links::clocksync::ClockEstimate,
    output: links::clocksync::ClockEstimate,
}

impl CrossClock {
    fn new(same: bool, sensor: &crate::mcus::McuConn, output: &crate::mcus::McuConn) -> CrossClock {
        CrossClock {
            same,
            sensor: sensor.link.clock(),
            output: output.link.clock(),
        }
    }

    /// The output MCU's clock at sensor MCU clock `c`.
    fn to_output(&self, c: f64) -> f64 {
        match self.same {
            true => c,
            false => self.output.clock_at(self.sensor.system_time_at(c)),
        }
    }

    /// The sensor MCU's clock at output MCU clock `c`.
    fn to_sensor(&self, c: f64) -> f64 {
        match self.same {
            true => c,
            false => self.sensor.clock_at(self.output.system_time_at(c)),
        }
    }
}

/// Analog input `oid`'s newest report not seen yet (`last_count` the one seen before):
/// `(next_clock, °C)` through `sensor`, rescaled by its `[adc_scaled]` chip if it has one.
fn adc_reading(
    link: &McuLink,
    oid: u8,
    last_count: &mut u16,
    full_scale: f64,
    sensor: &super::thermistor::Sensor,
    scale: Option<Option<&ScaledRefs>>,
) -> Option<(u32, f64)> {
    let (count, next_clock, value) = link.analog_report(oid)?;
    if count == *last_count {
        return None;
    }
    *last_count = count;
    let adc = fraction(value, full_scale, scale)?;
    Some((next_clock, sensor.temperature(adc)))
}

/// Heater `i`'s new reading, if any: temperature, control output, verify_heater's check and
/// the PWM update. False once the check shut the printer down.
fn update_heater(
    mcus: &Mcus,
    thermal: &Thermal,
    shared: &HeaterShared,
    i: usize,
    r: &mut Running,
    now_sys: f64,
    scale: Option<Option<&ScaledRefs>>,
) -> bool {
    let conn = &mcus.list[r.link_index];
    // The sensor may be on another MCU than the heater's output: its readings are in its
    // own clock, converted through system time to the output's.
    let sensor_conn = &mcus.list[r.adc_link];
    let reading = match r.spi.as_mut() {
        Some(spi) => spi.poll(&sensor_conn.link, |f| shared.note_chip_fault(f)),
        None => adc_reading(
            &sensor_conn.link,
            r.adc_oid,
            &mut r.last_count,
            r.full_scale,
            &r.sensor,
            scale,
        ),
    };
    let Some((next_clock, temp)) = reading else {
        return true;
    };
    let sensor_est = sensor_conn.link.clock();
    let sensor_freq = sensor_conn.clock_freq;
    let read_clock = sensor_est
        .extend(next_clock, now_sys)
        .saturating_sub((REPORT_TIME * sensor_freq) as u64);
    let time = read_clock as f64 / sensor_freq;
    let cell = &shared.heaters[i];
    let target = cell.target.get();
    let smoothed = r.smooth.update(time, temp);
    let freq = conn.clock_freq;
    let clocks = CrossClock::new(r.link_index == r.adc_link, sensor_conn, conn);
    let next_read = clocks.to_output(read_clock as f64 + REPORT_TIME * sensor_freq);
    let at = (next_read as u64).max(lead_clock(&conn.link, freq, thermal.max_heat_time()));
    let seen = r.smith.as_mut().map_or(temp, |s| s.predict(time, temp));
    let power = match r.relay.as_mut() {
        Some(relay) => relay_update(relay, shared, i, time, temp, r.max_power),
        None => r.control.update(time, seen, target),
    }
    .clamp(0.0, r.max_power);
    if r.relay.as_ref().is_some_and(|relay| relay.tuner.done()) {
        r.relay = None;
    }
    cell.temp.set(smoothed);
    cell.time.set(time);
    cell.power.set(power);
    let seen = cell.max_seen.get();
    if seen.is_nan() || smoothed > seen {
        cell.max_seen.set(smoothed);
    }
    cell.busy.store(
        target > 0.0 && r.control.busy(smoothed, target),
        Ordering::Release,
    );
    // A target set since it was read above (an M109 as this update ran): its setter marked the
    // heater busy, which the store above may have undone, and the new target is not reached
    // yet. With the fence here and in `set_target`, one of the two sees the other's write.
    std::sync::atomic::fence(Ordering::SeqCst);
    let now_target = cell.target.get();
    if now_target != target && now_target > 0.0 {
        cell.busy.store(true, Ordering::Release);
    }
    if time >= r.next_check {
        r.next_check = time + CHECK_INTERVAL_S;
        if let Err(fault) = r.verify.check(time, temp, target) {
            shutdown(mcus, shared, &fault.to_string());
            return false;
        }
    }
    // The MCU queues few updates (8): with a long lead (a time-scaled simulator) a new
    // value waits until a fifth of the lead has passed since the last one, and is the
    // mean of the powers decided meanwhile.
    let sent_power = match r.smith.as_mut() {
        Some(s) => {
            s.decided(power, time);
            r.decided.0 += power;
            r.decided.1 += 1.0;
            r.decided.0 / r.decided.1
        }
        None => power,
    };
    let on = on_ticks(sent_power, r.cycle_ticks);
    let min_gap = (lead_ticks(&conn.link, freq, thermal.max_heat_time()) / 5.0) as u64;
    let send = r.last_sent.is_none_or(|(c, o)| {
        let gap = at.saturating_sub(c);
        ((o != on || r.smith.is_some()) && gap >= min_gap)
            || gap as f64 > 0.25 * thermal.max_heat_time() * freq
    });
    if send {
        let extra_failed = r
            .extra
            .iter()
            .any(|&(oid, invert)| send_pwm(&conn.link, oid, at, on, invert, r.cycle_ticks).is_err());
        if extra_failed || send_pwm(&conn.link, r.pwm_oid, at, on, r.invert, r.cycle_ticks).is_err() {
            // The MCU shut down or the link died: the check above ends the loop.
            return true;
        }
        if let Some(s) = r.smith.as_mut() {
            s.sent(
                f64::from(on) / r.cycle_ticks,
                clocks.to_sensor(at as f64) / sensor_freq,
            );
            r.decided = (0.0, 0.0);
        }
        r.last_sent = Some((at, on));
    }
    true
}

/// Sensor `i`'s new reading, if any, into its shared cell.
fn update_sensor(
    mcus: &Mcus,
    shared: &HeaterShared,
    i: usize,
    r: &mut RunningSensor,
    now_sys: f64,
    scale: Option<Option<&ScaledRefs>>,
) {
    let conn = &mcus.list[r.link_index];
    let reading = match r.spi.as_mut() {
        Some(spi) => spi.poll(&conn.link, |f| shared.note_chip_fault(f)),
        None => adc_reading(
            &conn.link,
            r.oid,
            &mut r.last_count,
            r.full_scale,
            &r.sensor,
            scale,
        ),
    };
    let Some((next_clock, temp)) = reading else {
        return;
    };
    let freq = conn.clock_freq;
    let read_clock = conn
        .link
        .clock()
        .extend(next_clock, now_sys)
        .saturating_sub((REPORT_TIME * freq) as u64);
    let time = read_clock as f64 / freq;
    let smoothed = r.smooth.update(time, temp);
    let cell = &shared.sensors[i];
    cell.temp.set(smoothed);
    cell.time.set(time);
    if cell.min_seen.get().is_nan() || smoothed < cell.min_seen.get() {
        cell.min_seen.set(smoothed);
    }
    if cell.max_seen.get().is_nan() || smoothed > cell.max_seen.get() {
        cell.max_seen.set(smoothed);
    }
}

/// Fan `i`'s speed now, sent when it changed (with a kick start from off).
fn update_fan(
    mcus: &Mcus,
    thermal: &Thermal,
    shared: &HeaterShared,
    i: usize,
    f: &mut RunningFan,
    now_sys: f64,
) {
    let spec = &thermal.fans[i];
    let cell = &shared.fans[i];
    let now = {
        let conn = &mcus.list[f.link_index];
        conn.link.clock().clock_at(now_sys) / conn.clock_freq
    };
    let want = fan_speed(spec, cell, f, shared, now);
    let speed = if want < spec.opts.off_below { 0.0 } else { want };
    if f.last == Some(speed) {
        return;
    }
    let conn = &mcus.list[f.link_index];
    let at = lead_clock(&conn.link, conn.clock_freq, thermal.max_heat_time());
    let value = on_ticks(speed * spec.opts.max_power, f.cycle_ticks);
    let kick = spec.opts.kick_start_time;
    let from_off = f.last.is_none_or(|l| l == 0.0);
    let ok = if kick > 0.0 && from_off && speed > 0.0 && speed < 1.0 {
        let full = on_ticks(spec.opts.max_power, f.cycle_ticks);
        send_fan(&conn.link, f, at, full).is_ok()
            && send_fan(&conn.link, f, at + (kick * conn.clock_freq) as u64, value).is_ok()
    } else {
        send_fan(&conn.link, f, at, value).is_ok()
    };
    if ok {
        f.last = Some(speed);
        cell.speed.set(speed);
    }
}

/// Hands a requested PID_CALIBRATE to its heater's loop state.
fn start_calibration(shared: &HeaterShared, heaters: &mut [(usize, Running)]) {
    let Ok(mut c) = shared.calibration.try_lock() else {
        return;
    };
    let Some(Calibration::Requested { heater, target }) = *c else {
        return;
    };
    match heaters.iter_mut().find(|(i, _)| *i == heater) {
        Some((_, r)) => {
            r.relay = Some(Relay {
                tuner: RelayTuner::new(target, r.max_power),
                pwm: Vec::new(),
                temps: Vec::new(),
            });
            *c = Some(Calibration::Running { heater });
        }
        None => {
            *c = Some(Calibration::Done {
                heater,
                gains: None,
                pwm: Vec::new(),
                temps: Vec::new(),
            })
        }
    }
}

/// One report through PID_CALIBRATE's relay: the power to apply; once the tuner is done the
/// result goes to the shared state (the heater keeps its target under its own control).
fn relay_update(
    relay: &mut Relay,
    shared: &HeaterShared,
    heater: usize,
    time: f64,
    temp: f64,
    max_power: f64,
) -> f64 {
    let power = relay.tuner.update(time, temp).min(max_power);
    relay.temps.push((time, temp));
    if relay.pwm.last().is_none_or(|(_, p)| *p != power) {
        relay.pwm.push((time, power));
    }
    if relay.tuner.done() {
        if let Ok(mut c) = shared.calibration.lock() {
            *c = Some(Calibration::Done {
                heater,
                gains: relay.tuner.result(),
                pwm: std::mem::take(&mut relay.pwm),
                temps: std::mem::take(&mut relay.temps),
            });
        }
    }
    power
}

/// A heater fault: every heater off and every MCU shut down (their outputs fall to off).
fn shutdown(mcus: &Mcus, shared: &HeaterShared, why: &str) {
    shared.set_fault(why.to_string());
    shared.turn_off_all();
    for m in &mcus.list {
        if let Ok(cmd) = m.link.dictionary().encode("emergency_stop", &[]) {
            let _ = m.link.send(cmd);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn on_ticks_cover_off_pwm_and_full() {
        assert_eq!(on_ticks(0.0, 1000.0), 0);
        assert_eq!(on_ticks(0.25, 1000.0), 250);
        assert_eq!(on_ticks(1.0, 1000.0), 1000);
        assert_eq!(on_ticks(1e-9, 1000.0), 1, "any heat is at least one tick");
    }

    #[test]
    fn m105_reports_as_klipper() {
        let cfg = sysconfig::builtin_simulated().unwrap();
        let t = Thermal::from_config(&cfg).unwrap();
        let s = HeaterShared::new(&t);
        s.set_target(0, 210.0);
        s.heaters[0].temp.set(25.04);
        s.heaters[1].temp.set(24.96);
        assert_eq!(m105_text(&s), "B:25.0 /0.0 T0:25.0 /210.0");
        s.turn_off_all();
        assert_eq!(s.heaters[0].target.get(), 0.0);
        assert_eq!(s.fault(), None);
        s.set_fault("Heater extruder not heating at expected rate".into());
        assert_eq!(
            s.fault().as_deref(),
            Some("Heater extruder not heating at expected rate")
        );
    }
}
