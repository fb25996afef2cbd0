//! The simulator's [`Board`]: steps go to the trace file and the lateness histogram, bytes for
//! the host collect in an output buffer the event loop drains into the pty.
//!
//! The core speaks 32-bit clocks; the board knows the simulator's 64-bit clock `now` (set by
//! the event loop before every call into the core) and widens each 32-bit clock with
//! [`McuClock::extend`], valid because every clock the core reports is within 2^31 ticks of now.
//! Lateness and lead are converted to µs of MCU time: `ticks × 10^6 / clock_freq`.
//!
//! Pins: steps move the [`World`]'s axes (and publish them to other processes of the same
//! world); endstop inputs read the world; heater outputs drive [`Heater`]s whose thermistors
//! are the ADC inputs. Triggers go to the trace as kind-3 records.

use super::bltouch::{BlTouch, BlTouchSpec};
use super::cli::{HeaterFaultSpec, HeaterSpec, SensorCurveSpec};
use super::heater::Heater;
use super::tmc::{TmcDriver, TmcSpec};
use super::trace_file::TraceFile;
use super::world::World;
use crate::core::{Board, Lateness, StepperConfig, TriggerSource};
use crate::trace::{ticks_to_us, TraceRecord, TraceWriter, TriggerRecord};
use hdrhistogram::{CreationError, Histogram};
use rt_core::{McuClock, WireClock};
use std::io;

/// Largest lateness the histogram resolves (µs); larger values saturate.
pub const LATENESS_MAX_US: u64 = 60_000_000;
/// Bytes of pending output after which further output is dropped (the host is not reading).
pub const OUTPUT_LIMIT: usize = 1 << 20;

/// Lateness percentiles of executed steps, in µs of MCU time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LatenessSummary {
    /// Steps executed.
    pub steps: u64,
    /// Median.
    pub p50: u64,
    /// 99th percentile.
    pub p99: u64,
    /// 99.9th percentile.
    pub p999: u64,
    /// Maximum.
    pub max: u64,
}

/// The simulated board.
#[derive(Debug)]
pub struct SimBoard {
    /// The simulator's 64-bit MCU clock at the current call into the core.
    pub now: u64,
    /// Blocks waiting to be written to the pty.
    pub out: Vec<u8>,
    /// Bytes dropped because `out` was over [`OUTPUT_LIMIT`].
    pub dropped_output: u64,
    clock_freq: u32,
    trace: Option<TraceWriter<TraceFile>>,
    trace_error: Option<io::Error>,
    lateness: Histogram<u64>,
    queue_steps: u64,
    /// Simulated axes and endstops.
    pub world: World,
    heaters: Vec<Heater>,
    /// The level each output pin was last set to (a TMC UART mux's select pins).
    levels: [bool; 256],
    /// Fans with tachometers (`--fan`).
    fans: Vec<super::fan::Fan>,
    /// The ADC's references (`--adc-ref`): with them every reading has an offset and gain error.
    adc_refs: Vec<super::adc_ref::AdcRefSpec>,
    /// The sensor responses of analog inputs that no heater warms (read at ambient).
    ambient_curves: Vec<SensorCurveSpec>,
    /// Simulated BLTouch probes (their sensor pins read them, their control pins drive them).
    pub bltouch: Vec<BlTouch>,
    /// Simulated Smart Effectors (their control pins drive them).
    smart_effectors: Vec<super::smart_effector::SmartEffector>,
    /// Simulated TMC drivers (on their UART lines or chip selects; their DIAG pins read them).
    pub tmc: Vec<TmcDriver>,
    /// Simulated SPI temperature chips (on their chip selects).
    pub spi_sensors: Vec<super::spi_sensor::SpiSensor>,
    /// Heaters whose sensor is on another MCU: (heater pin, world value name) published.
    heater_exports: Vec<(u8, String)>,
    /// Analog inputs reading a heater of another MCU: (pin, world value name).
    remote_sensors: Vec<(u8, String)>,
}

impl SimBoard {
    /// A board for an MCU at `clock_freq`, tracing to `trace` if given.
    pub fn new(clock_freq: u32, trace: Option<TraceWriter<TraceFile>>) -> Result<SimBoard, CreationError> {
        // Fixed bounds: saturating_record never allocates.
        let lateness = Histogram::new_with_bounds(1, LATENESS_MAX_US, 3)?;
        Ok(SimBoard {
            now: 0,
            out: Vec::with_capacity(4096),
            dropped_output: 0,
            clock_freq,
            trace,
            trace_error: None,
            lateness,
            queue_steps: 0,
            world: World::local(Vec::new(), Vec::new()),
            heaters: Vec::new(),
            adc_refs: Vec::new(),
            fans: Vec::new(),
            levels: [false; 256],
            ambient_curves: Vec::new(),
            bltouch: Vec::new(),
            smart_effectors: Vec::new(),
            tmc: Vec::new(),
            spi_sensors: Vec::new(),
            heater_exports: Vec::new(),
            remote_sensors: Vec::new(),
        })
    }

    /// Uses `world` for axes and endstops.
    pub fn with_world(mut self, world: World) -> SimBoard {
        self.world = world;
        self
    }

    /// Adds fans with tachometers.
    pub fn with_fans(mut self, fans: &[super::fan::FanSpec]) -> SimBoard {
        self.fans = fans.iter().map(|&f| super::fan::Fan::new(f)).collect();
        self
    }

    /// Gives the ADC measurable references (and their offset and gain error).
    pub fn with_adc_refs(mut self, refs: &[super::adc_ref::AdcRefSpec]) -> SimBoard {
        self.adc_refs = refs.to_vec();
        self
    }

    /// Adds heaters, each with the faults injected into it.
    pub fn with_heaters(mut self, heaters: &[HeaterSpec], faults: &[HeaterFaultSpec]) -> SimBoard {
        self.heaters = heaters
            .iter()
            .map(|h| {
                let heater = Heater::new(h.heater_pin, h.sensor_pin, h.model).active_low(h.active_low);
                faults
                    .iter()
                    .filter(|f| f.heater_pin == h.heater_pin)
                    .fold(heater, |heater, f| heater.with_fault(f.fault, f.from_s))
            })
            .collect();
        self
    }

    /// Gives each analog input of `curves` its sensor's response: a heater's sensor, or an
    /// input at ambient temperature.
    pub fn with_sensor_curves(mut self, curves: &[SensorCurveSpec]) -> SimBoard {
        for c in curves {
            match self.heaters.iter_mut().find(|h| h.sensor_pin == c.sensor_pin) {
                Some(h) => *h = h.clone().with_curve(c.curve.clone()),
                None => self.ambient_curves.push(c.clone()),
            }
        }
        self
    }

    /// Adds BLTouch probes; a later one on the same sensor pin replaces the earlier (extra
    /// arguments can so inject a fault into the host's probe).
    pub fn with_bltouch(mut self, probes: &[BlTouchSpec]) -> SimBoard {
        let freq = self.clock_freq;
        for p in probes {
            self.bltouch.retain(|b| b.spec.sensor_pin != p.sensor_pin);
            self.bltouch.push(BlTouch::new(p.clone(), freq));
        }
        self
    }

    /// Adds Smart Effectors.
    pub fn with_smart_effectors(mut self, specs: &[super::smart_effector::SmartEffectorSpec]) -> SimBoard {
        let freq = self.clock_freq;
        self.smart_effectors.extend(
            specs
                .iter()
                .map(|&s| super::smart_effector::SmartEffector::new(s, freq)),
        );
        self
    }

    /// The Smart Effectors, every message that ended before `clock` taken.
    pub fn smart_effectors(&mut self, clock: u64) -> &[super::smart_effector::SmartEffector] {
        for e in &mut self.smart_effectors {
            e.finish(clock);
        }
        &self.smart_effectors
    }

    /// Adds TMC drivers.
    pub fn with_tmc(mut self, drivers: &[TmcSpec]) -> SimBoard {
        self.tmc.extend(drivers.iter().cloned().map(TmcDriver::new));
        self
    }

    /// Adds SPI temperature chips.
    pub fn with_spi_sensors(mut self, chips: &[super::spi_sensor::SpiSensorSpec]) -> SimBoard {
        self.spi_sensors
            .extend(chips.iter().copied().map(super::spi_sensor::SpiSensor::new));
        self
    }

    /// Heaters (by output pin) whose sensor temperature is published in the world under a
    /// name, and analog inputs that read such a temperature (`--heater-export`,
    /// `--remote-sensor`): a heater on one MCU, its sensor on another.
    pub fn with_remote_heaters(mut self, exports: &[(u8, String)], sensors: &[(u8, String)]) -> SimBoard {
        self.heater_exports = exports.to_vec();
        self.remote_sensors = sensors.to_vec();
        self
    }

    /// Publishes the sensor temperature of every exported heater as of MCU clock `now`.
    pub fn export_heaters(&mut self, now: u64) {
        let t = self.seconds(now);
        for (pin, name) in &self.heater_exports {
            if let Some(h) = self.heaters.iter_mut().find(|h| h.heater_pin == *pin) {
                // Hundredths of a degree: no publication for changes below the ADC's reach.
                let temp = (h.sensor_temperature(t) * 100.0).round() / 100.0;
                self.world.set_value(name, temp);
            }
        }
    }

    /// What analog input `pin` reads on a perfect ADC.
    fn read_adc_ideal(&mut self, pin: u8) -> u16 {
        if let Some((_, name)) = self.remote_sensors.iter().find(|(p, _)| *p == pin) {
            self.world.refresh();
            let temp = self.world.position(name).unwrap_or(super::heater::AMBIENT_C);
            return match self.ambient_curves.iter().find(|c| c.sensor_pin == pin) {
                Some(c) => c.curve.adc(temp),
                None => super::heater::adc_of(temp),
            };
        }
        let t = self.seconds(self.now);
        match self.heaters.iter_mut().find(|h| h.sensor_pin == pin) {
            Some(h) => h.adc(t),
            // Any other analog input is a sensor at room temperature (a chamber or board
            // sensor): the given one's response, else a β3950 thermistor.
            None => match self.ambient_curves.iter().find(|c| c.sensor_pin == pin) {
                Some(c) => c.curve.adc(super::heater::AMBIENT_C),
                None => super::heater::adc_of(super::heater::AMBIENT_C),
            },
        }
    }

    fn seconds(&self, clock: u64) -> f64 {
        clock as f64 / self.clock_freq.max(1) as f64
    }

    fn to_us(&self, ticks: u64) -> u32 {
        ticks_to_us(ticks, self.clock_freq as u64)
    }

    fn extend(&self, clock: WireClock) -> u64 {
        McuClock(self.now).extend(clock).0
    }

    fn record(&mut self, r: TraceRecord) {
        if let Some(w) = self.trace.as_mut() {
            if let Err(e) = w.write(&r) {
                self.trace_error.get_or_insert(e);
                self.trace = None;
            }
        }
    }

    /// `queue_step` commands received so far.
    pub fn queue_steps(&self) -> u64 {
        self.queue_steps
    }

    /// Percentiles of step lateness so far.
    pub fn lateness_summary(&self) -> LatenessSummary {
        let h = &self.lateness;
        LatenessSummary {
            steps: h.len(),
            p50: h.value_at_quantile(0.5),
            p99: h.value_at_quantile(0.99),
            p999: h.value_at_quantile(0.999),
            max: h.max(),
        }
    }

    /// Flushes and closes the trace; reports the first write error, if any.
    pub fn finish_trace(&mut self) -> io::Result<()> {
        if let Some(w) = self.trace.take() {
            w.finish()?.close()?;
        }
        match self.trace_error.take() {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }
}

impl Board for SimBoard {
    fn step(&mut self, oid: u8, dir: bool, clock: WireClock) {
        let scheduled = self.extend(clock);
        let late_us = self.to_us(self.now.saturating_sub(scheduled));
        self.lateness.saturating_record(late_us as u64);
        self.world.step(oid, dir, scheduled);
        self.record(TraceRecord::Step {
            oid,
            dir,
            clock: scheduled,
            lateness_us: late_us,
        });
    }

    fn write(&mut self, bytes: &[u8]) {
        if self.out.len() + bytes.len() > OUTPUT_LIMIT {
            self.dropped_output += bytes.len() as u64;
            return;
        }
        self.out.extend_from_slice(bytes);
    }

    fn config_stepper(&mut self, oid: u8, config: &StepperConfig) {
        self.world.config_stepper(oid, config.step_pin);
    }

    fn read_pin(&mut self, pin: u8, at: WireClock) -> bool {
        let at = self.extend(at);
        if let Some(b) = self.bltouch.iter_mut().find(|b| b.spec.sensor_pin == pin) {
            let h = self.world.surface_at_clock(pin, at);
            let z = self
                .world
                .probe_height_at_clock(pin, &b.spec.coord, at)
                .map(|z| z - h);
            return b.sense(at, z) != b.spec.active_low;
        }
        if let Some(i) = self
            .tmc
            .iter()
            .position(|t| t.spec.diag.as_ref().is_some_and(|d| d.pin == pin))
        {
            let coord = self.tmc[i].spec.diag.as_ref().map(|d| d.coord.clone());
            let pos = coord.and_then(|c| self.world.coord_at_clock(&c, at));
            return pos.is_some_and(|p| self.tmc[i].diag_level(p));
        }
        if let Some(f) = self.fans.iter_mut().find(|f| f.spec.tach_pin == pin) {
            let t = at as f64 / self.clock_freq.max(1) as f64;
            return f.tach_level(t);
        }
        self.world.read_endstop(pin, at).unwrap_or(false)
    }

    fn tmcuart_transfer(&mut self, rx_pin: u8, tx_pin: u8, _bit_time: u32, write: &[u8], read: &mut [u8]) {
        // Every driver on the line hears the request; the addressed one answers.
        let mut reply = None;
        let levels = &self.levels;
        let selected = |select: &[(u8, bool)]| select.iter().all(|&(p, l)| levels[usize::from(p)] == l);
        for t in self
            .tmc
            .iter_mut()
            .filter(|t| t.spec.bus_pin == rx_pin || t.spec.bus_pin == tx_pin)
            .filter(|t| selected(&t.spec.select))
        {
            reply = t.uart(write).or(reply);
        }
        if let Some(r) = reply.filter(|_| !read.is_empty()) {
            let n = read.len().min(r.len());
            read[..n].copy_from_slice(&r[..n]);
        }
    }

    fn spi_transfer(&mut self, cs_pin: u8, data: &mut [u8]) {
        if let Some(c) = self.spi_sensors.iter_mut().find(|c| c.spec.cs_pin == cs_pin) {
            // The temperature its heater's sensor is at (a heater whose sensor pin is the chip
            // select), else ambient.
            let t = self.now as f64 / self.clock_freq.max(1) as f64;
            let (temp, open) = match self.heaters.iter_mut().find(|h| h.sensor_pin == cs_pin) {
                Some(h) => (h.sensor_temperature(t), h.sensor_open(t)),
                None => (super::heater::AMBIENT_C, false),
            };
            c.transfer(data, temp, open);
            return;
        }
        let mut selected = self
            .tmc
            .iter_mut()
            .filter(|t| t.spec.bus_pin == cs_pin)
            .peekable();
        if selected.peek().is_none() {
            // Nothing selected: MISO floats high.
            data.fill(0xff);
            return;
        }
        // A daisy chain (drivers at positions 1..=n on one chip select): the bytes shift through
        // every driver, so position p holds the 5 bytes at (n − p)·5 of the n·5 clocked, and
        // answers in their place.
        let n = data.len() / 5;
        for t in selected {
            match usize::from(t.spec.address) {
                0 => t.spi(data),
                p if p <= n => {
                    let at = (n - p) * 5;
                    t.spi(&mut data[at..at + 5]);
                }
                _ => {}
            }
        }
    }

    fn read_adc(&mut self, pin: u8) -> u16 {
        let ideal = self.read_adc_ideal(pin);
        match self.adc_refs.first() {
            Some(r) => r.read(pin, ideal, super::heater::ADC_MAX),
            None => ideal,
        }
    }

    fn read_mcu_temperature(&mut self) -> u16 {
        let t = self.seconds(self.now);
        super::mcu_temp::adc_of(super::mcu_temp::die_temperature(t))
    }

    fn set_pin(&mut self, pin: u8, value: bool, clock: WireClock) {
        self.levels[usize::from(pin)] = value;
        let at = self.extend(clock);
        for b in self.bltouch.iter_mut().filter(|b| b.spec.control_pin == pin) {
            b.control(value, at);
        }
        for e in self
            .smart_effectors
            .iter_mut()
            .filter(|e| e.spec.control_pin == pin)
        {
            e.control(value, at);
        }
        let t = self.seconds(at);
        for h in self.heaters.iter_mut().filter(|h| h.heater_pin == pin) {
            h.set_level(value, t);
        }
        for f in self.fans.iter_mut().filter(|f| f.spec.out_pin == pin) {
            f.set(f64::from(u8::from(value)), t);
        }
    }

    fn set_pwm(&mut self, pin: u8, _cycle_ticks: u32, value: u16, clock: WireClock) {
        let t = self.seconds(self.extend(clock));
        let pwm_max = f64::from(crate::core::constants::PWM_MAX);
        for f in self.fans.iter_mut().filter(|f| f.spec.out_pin == pin) {
            f.set(f64::from(value) / pwm_max, t);
        }
    }

    fn triggered(&mut self, source: TriggerSource, oid: u8, reason: u8, clock: WireClock) {
        let t = TriggerRecord {
            oid,
            endstop: source == TriggerSource::Endstop,
            reason,
            clock: self.extend(clock),
        };
        if let Some(w) = self.trace.as_mut() {
            if let Err(e) = w.write_trigger(&t) {
                self.trace_error.get_or_insert(e);
                self.trace = None;
            }
        }
    }

    fn lateness(&self) -> Lateness {
        let l = self.lateness_summary();
        let c = |v: u64| u32::try_from(v).unwrap_or(u32::MAX);
        Lateness {
            count: c(l.steps),
            p50: c(l.p50),
            p99: c(l.p99),
            p999: c(l.p999),
            max: c(l.max),
        }
    }

    fn queue_step_received(&mut self, oid: u8, first_clock: WireClock, now: WireClock) {
        self.queue_steps += 1;
        self.record(TraceRecord::QueueStep {
            oid,
            received_clock: self.extend(now),
            first_step_clock: self.extend(first_clock),
        });
    }

    fn shutdown(&mut self, clock: WireClock, static_string_id: u16, reason: &'static str) {
        let clock = self.extend(clock);
        eprintln!("cadence-mcu: shutdown at clock {clock}: {reason}");
        self.record(TraceRecord::Shutdown {
            clock,
            static_string_id,
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn widens_clocks_and_measures_lateness_and_lead() {
        let path = std::env::temp_dir().join(format!("cadence-board-test-{}.bin", std::process::id()));
        let file = TraceFile::create(&path).unwrap();
        let w = TraceWriter::new(file, crate::trace::TraceFormat::Bin, 1_000_000, 1.0).unwrap();
        let mut b = SimBoard::new(1_000_000, Some(w)).unwrap();
        b.now = (1u64 << 32) + 500;
        b.queue_step_received(2, WireClock(100_500), WireClock(500));
        b.step(2, true, WireClock(400)); // 100 ticks = 100 µs late
        b.queue_step_received(2, WireClock(400), WireClock(500)); // already late: lead 0
        b.shutdown(WireClock(500), 7, "x");
        b.finish_trace().unwrap();
        let trace = crate::trace::read_trace(&path).unwrap();
        let _ = std::fs::remove_file(&path);
        let base = 1u64 << 32;
        let expect = [
            TraceRecord::QueueStep {
                oid: 2,
                received_clock: base + 500,
                first_step_clock: base + 100_500,
            },
            TraceRecord::Step {
                oid: 2,
                dir: true,
                clock: base + 400,
                lateness_us: 100,
            },
            // Already late: the file keeps a lead of 0.
            TraceRecord::QueueStep {
                oid: 2,
                received_clock: base + 500,
                first_step_clock: base + 500,
            },
            TraceRecord::Shutdown {
                clock: base + 500,
                static_string_id: 7,
            },
        ];
        assert_eq!(trace.records, expect);
        let l = b.lateness_summary();
        assert_eq!(l.steps, 1);
        assert!(l.max >= 100 && l.max <= 101);
        assert_eq!(b.queue_steps(), 2);
    }

    #[test]
    fn output_is_bounded() {
        let mut b = SimBoard::new(1_000_000, None).unwrap();
        let chunk = [0u8; 64];
        for _ in 0..(OUTPUT_LIMIT / 64 + 10) {
            b.write(&chunk);
        }
        assert_eq!(b.out.len(), OUTPUT_LIMIT);
        assert_eq!(b.dropped_output, 640);
    }
}
