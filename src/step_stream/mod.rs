//! The step stream encoder: the planner's per-stepper step commands → encoded MCU messages
//! ([`sink`]: encoding, send clocks and where messages go), in streams of a print: one per MCU
//! that drives steppers (the main `[mcu]` always first), each with its own step streamer (move-pool accounting, encoders from that MCU's
//! data dictionary) and, in a live print, its own shared-memory channel and IO stage.
//!
//! Clock domains: print time is the main MCU's clock divided by its `CLOCK_FREQ`. A stepper
//! on another MCU is planned in that MCU's clock: the map `clock = a + b · print_time` follows
//! from the two clock-sync fits (both against the host's system time `T`):
//!
//! ```text
//! main:   c_m(T) = ĉ_m + (T − T̂_m) · f_m        print_time = c_m / F_m
//! other:  c_s(T) = ĉ_s + (T − T̂_s) · f_s
//! ⇒       c_s = a + b · print_time,  b = F_m · f_s / f_m,  a = c_s(T) − b · c_m(T) / F_m (any T)
//! ```
//!
//! The planner gets the maps at start and again between batches ([`StepStreams::refresh_clocks`]),
//! so each MCU's crystal drift is followed (the fits are `links::clocksync`'s).

mod error;
pub mod sink;

pub use error::StreamError;

use links::clocksync::ClockEstimate;
use links::dict::Dictionary;
use links::mcu::McuLink;
use planner::pipeline::{ClockMap, Pipeline};
use planner::stepgen::StepCmd;

use crate::hardware::Machine;
use sink::{EnableOut, Sink, StepStreamer};

/// How long after the last step M84 turns the drivers off (s; Klipper's stall time).
pub const MOTORS_OFF_STALL_S: f64 = 0.1;

/// What a stream needs to know of its MCU.
#[derive(Debug, Clone, Copy)]
pub struct McuParams<'a> {
    pub name: &'a str,
    /// Index of the MCU in the printer's `[mcu]` order (0 = the main one).
    pub mcu_index: usize,
    pub dict: &'a Dictionary,
    /// Nominal CLOCK_FREQ.
    pub clock_freq: f64,
    /// Entries of its move queue.
    pub move_count: usize,
}

/// One MCU's step stream.
#[derive(Debug)]
pub struct McuStream {
    pub name: String,
    /// Index of the MCU in the printer's `[mcu]` order.
    pub mcu_index: usize,
    /// Nominal CLOCK_FREQ (its step commands count these ticks).
    pub clock_freq: f64,
    pub streamer: StepStreamer,
    /// The machine's stepper indices on this MCU, in machine order.
    pub steppers: Vec<usize>,
}

/// The streams of every MCU with steppers, and the route from the planner's stepper index to
/// its stream.
#[derive(Debug)]
pub struct StepStreams {
    pub mcus: Vec<McuStream>,
    /// Per machine stepper: (stream, index within the stream's streamer).
    route: Vec<(usize, usize)>,
}

/// The MCUs (indices into `names`, the printer's `[mcu]` order) that get a step stream: the
/// main one, then every other that drives a stepper.
pub fn stream_mcus(machine: &Machine, names: &[&str]) -> Vec<usize> {
    (0..names.len())
        .filter(|&i| i == 0 || machine.steppers.iter().any(|s| s.mcu == names[i]))
        .collect()
}

impl StepStreams {
    /// Streams for `mcus` (from [`stream_mcus`], the main MCU first); every stepper's MCU must
    /// be among them.
    pub fn new(machine: &Machine, mcus: &[McuParams<'_>]) -> Result<StepStreams, StreamError> {
        let mut route = vec![(usize::MAX, 0); machine.steppers.len()];
        let mut out = Vec::with_capacity(mcus.len());
        for (k, m) in mcus.iter().enumerate() {
            let steppers: Vec<usize> = (0..machine.steppers.len())
                .filter(|&i| machine.steppers[i].mcu == m.name)
                .collect();
            let outs: Vec<_> = steppers.iter().map(|&i| machine.steppers[i].clone()).collect();
            for (local, &i) in steppers.iter().enumerate() {
                route[i] = (k, local);
            }
            let (oid0, pins) = crate::mcus::enable_pins(m.dict, machine, m.name).map_err(|_| {
                StreamError::TooManyObjects {
                    mcu: m.name.to_string(),
                }
            })?;
            let mut enables = Vec::with_capacity(pins.len());
            for (i, p) in pins.iter().enumerate() {
                enables.push(EnableOut {
                    oid: u8::try_from(oid0 + i).map_err(|_| StreamError::TooManyObjects {
                        mcu: m.name.to_string(),
                    })?,
                    pin: p.pin.clone(),
                    invert: p.invert,
                });
            }
            let streamer = StepStreamer::new(m.dict, &outs, &enables, m.move_count).map_err(|source| {
                StreamError::McuDictionary {
                    mcu: m.name.to_string(),
                    source,
                }
            })?;
            out.push(McuStream {
                name: m.name.to_string(),
                mcu_index: m.mcu_index,
                clock_freq: m.clock_freq,
                streamer,
                steppers,
            });
        }
        if let Some(i) = route.iter().position(|r| r.0 == usize::MAX) {
            let s = &machine.steppers[i];
            return Err(StreamError::NotConnected {
                stepper: s.name.clone(),
                mcu: s.mcu.clone(),
            });
        }
        Ok(StepStreams { mcus: out, route })
    }

    /// Klipper's M84/M18 on every MCU: each driver that is on goes off
    /// [`MOTORS_OFF_STALL_S`] after its MCU's last step sent, and not before `floors[k]`
    /// (stream k's earliest clock a message sent now may carry; `sinks[k]`: its sink).
    pub fn motors_off<S: Sink>(&mut self, floors: &[u64], sinks: &mut [S]) -> Result<(), StreamError> {
        for (k, (m, sink)) in self.mcus.iter_mut().zip(sinks.iter_mut()).enumerate() {
            let stall = (MOTORS_OFF_STALL_S * m.clock_freq) as u64;
            let floor = floors.get(k).copied().unwrap_or(0);
            m.streamer.motors_off(stall, floor, sink)?;
        }
        Ok(())
    }

    /// The stream of stepper `idx`.
    pub fn stream_of(&self, idx: usize) -> Option<usize> {
        self.route.get(idx).map(|r| r.0)
    }

    /// Encodes one planner command for stepper `idx` into its MCU's sink (`sinks[k]` is
    /// stream k's).
    pub fn push<S: Sink>(&mut self, idx: usize, cmd: StepCmd, sinks: &mut [S]) -> Result<(), StreamError> {
        let Some(&(k, local)) = self.route.get(idx) else {
            return Err(StreamError::UnknownStepper(idx));
        };
        let (Some(stream), Some(sink)) = (self.mcus.get_mut(k), sinks.get_mut(k)) else {
            return Err(StreamError::NoSink(k));
        };
        stream.streamer.push(local, cmd, sink)
    }

    /// The MCU stopped stepper `idx` (homing) and is idle by `now_clock` of its own clock.
    pub fn note_stopped(&mut self, idx: usize, now_clock: u64) {
        if let Some(&(k, local)) = self.route.get(idx) {
            self.mcus[k].streamer.note_stopped(local, now_clock);
        }
    }

    /// `queue_step` messages handed to the sinks, all MCUs.
    pub fn queue_steps(&self) -> u64 {
        self.mcus.iter().map(|m| m.streamer.queue_steps()).sum()
    }

    /// Steps handed to the sinks per stepper, in machine order.
    pub fn steps_sent(&self) -> Vec<u64> {
        let per: Vec<Vec<u64>> = self.mcus.iter().map(|m| m.streamer.steps_sent()).collect();
        self.route
            .iter()
            .map(|&(k, local)| per[k].get(local).copied().unwrap_or(0))
            .collect()
    }

    /// (MCU index, largest step clock sent) of every stream.
    pub fn end_clocks(&self) -> Vec<(usize, u64)> {
        self.mcus
            .iter()
            .map(|m| (m.mcu_index, m.streamer.last_step_clock))
            .collect()
    }

    /// Every stepper's clock map now, in machine order; `clock(mcu_index)` is that MCU's
    /// clock-sync fit. Fails when another MCU has no valid fit.
    pub fn clock_maps(&self, clock: impl Fn(usize) -> ClockEstimate) -> Result<Vec<ClockMap>, StreamError> {
        let main = &self.mcus[0];
        let main_est = clock(main.mcu_index);
        let now = McuLink::system_now();
        let mut maps = vec![ClockMap::identity(main.clock_freq); self.route.len()];
        for m in &self.mcus[1..] {
            let map = clock_map(&main_est, main.clock_freq, &clock(m.mcu_index), now)
                .ok_or_else(|| StreamError::NoClock { mcu: m.name.clone() })?;
            for &i in &m.steppers {
                maps[i] = map;
            }
        }
        Ok(maps)
    }

    /// Hands the planner the current clock maps of the MCUs other than the main one (between
    /// batches: the fits move with each clock sample). An MCU without a valid fit keeps its
    /// map. Allocation-free.
    pub fn refresh_clocks(
        &self,
        pipeline: &mut Pipeline,
        clock: impl Fn(usize) -> ClockEstimate,
    ) -> Result<(), StreamError> {
        let Some((main, others)) = self.mcus.split_first() else {
            return Ok(());
        };
        if others.is_empty() {
            return Ok(());
        }
        let main_est = clock(main.mcu_index);
        let now = McuLink::system_now();
        for m in others {
            let Some(map) = clock_map(&main_est, main.clock_freq, &clock(m.mcu_index), now) else {
                continue;
            };
            for &i in &m.steppers {
                pipeline.set_clock_map(i, map)?;
            }
        }
        Ok(())
    }
}

/// The map print time → clock of an MCU whose fit is `est`, print time being the main MCU's
/// clock (fit `main`) / `main_freq` (see the module doc; `now` is any system time, best a
/// recent one). `None` while either fit is invalid.
pub fn clock_map(main: &ClockEstimate, main_freq: f64, est: &ClockEstimate, now: f64) -> Option<ClockMap> {
    if !(main.is_valid() && est.is_valid() && main_freq > 0.0) {
        return None;
    }
    let freq = main_freq * est.freq() / main.freq();
    let offset = est.clock_at(now) - freq * (main.clock_at(now) / main_freq);
    (freq.is_finite() && offset.is_finite()).then_some(ClockMap { offset, freq })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clock_map_agrees_with_both_fits() {
        // Main: 50 MHz nominal, running 20 ppm fast, clock 1e9 at T = 100 s. Other: 16 MHz
        // nominal, 35 ppm slow, 3e8 at T = 99.5 s.
        let main = ClockEstimate::new(100.0, 1e9, 50e6 * (1.0 + 20e-6));
        let other = ClockEstimate::new(99.5, 3e8, 16e6 * (1.0 - 35e-6));
        let map = clock_map(&main, 50e6, &other, 101.0).unwrap();
        for t in [90.0, 100.0, 250.0, 1e4] {
            let print_time = main.clock_at(t) / 50e6;
            let want = other.clock_at(t);
            let got = map.clock(print_time);
            assert!((got - want).abs() < 1e-2, "T {t}: {got} vs {want} ticks");
            assert!((map.print_time(want) - print_time).abs() < 1e-9);
        }
        assert!(clock_map(&ClockEstimate::INVALID, 50e6, &other, 0.0).is_none());
    }

    #[test]
    fn the_main_mcu_always_streams_and_others_only_with_steppers() {
        let text = include_str!("../../examples/simulated-toolboard.cfg");
        let cfg = sysconfig::parse_str(text, std::path::Path::new("printer.cfg")).unwrap();
        let m = Machine::from_config(&cfg).unwrap();
        assert_eq!(stream_mcus(&m, &["mcu", "toolboard"]), [0, 1]);
        assert_eq!(stream_mcus(&m, &["mcu", "toolboard", "spare"]), [0, 1]);
        let dict = crate::wire_check::load_dictionary(None).unwrap();
        let p = |name, mcu_index| McuParams {
            name,
            mcu_index,
            dict: &dict,
            clock_freq: 50e6,
            move_count: 1024,
        };
        let s = StepStreams::new(&m, &[p("mcu", 0), p("toolboard", 1)]).unwrap();
        let z = m.steppers.iter().position(|s| s.name == "stepper_z").unwrap();
        let x = m.steppers.iter().position(|s| s.name == "stepper_x").unwrap();
        assert_eq!((s.stream_of(x), s.stream_of(z)), (Some(0), Some(1)));
        let err = StepStreams::new(&m, &[p("mcu", 0)]).unwrap_err();
        assert!(
            matches!(&err, StreamError::NotConnected { mcu, .. } if mcu == "toolboard"),
            "{err:?}"
        );
        assert!(err.to_string().contains("'toolboard'"), "{err}");
    }

    /// Every message a stream sends, decoded: (name, fields, req_clock).
    struct Recorder(Vec<(String, Vec<i64>, u64)>, Dictionary);

    impl Sink for Recorder {
        fn send(&mut self, cmd: links::dict::Cmd) -> Result<(), StreamError> {
            self.send_clocked(cmd, 0, 0)
        }
        fn send_clocked(&mut self, cmd: links::dict::Cmd, _: u64, req: u64) -> Result<(), StreamError> {
            for m in self.1.decode_command(cmd.as_bytes())? {
                let fields = m.fields.iter().filter_map(|(n, _)| m.get(n)).collect();
                self.0.push((m.name, fields, req));
            }
            Ok(())
        }
    }

    #[test]
    fn drivers_go_on_before_the_first_step_and_off_after_m84() {
        let text = include_str!("../../examples/simulated-cartesian.cfg");
        let cfg = sysconfig::parse_str(text, std::path::Path::new("printer.cfg")).unwrap();
        let m = Machine::from_config(&cfg).unwrap();
        let dict = crate::wire_check::load_dictionary(None).unwrap();
        let params = McuParams {
            name: "mcu",
            mcu_index: 0,
            dict: &dict,
            clock_freq: 50e6,
            move_count: 1024,
        };
        let mut s = StepStreams::new(&m, &[params]).unwrap();
        let mut sink = [Recorder(Vec::new(), dict.clone())];
        let (oid0, pins) = crate::mcus::enable_pins(&dict, &m, "mcu").unwrap();
        assert_eq!(pins.len(), 4, "one enable pin per stepper in this config");
        let x = m.steppers.iter().position(|s| s.name == "stepper_x").unwrap();
        let step = |first_clock| StepCmd::QueueStep {
            interval: 1000,
            count: 10,
            add: 0,
            first_clock,
            last_clock: first_clock + 9000,
        };
        s.push(x, StepCmd::ResetClock { clock: 1_000_000 }, &mut sink)
            .unwrap();
        s.push(x, step(1_001_000), &mut sink).unwrap();
        s.push(x, step(1_011_000), &mut sink).unwrap();
        s.motors_off(&[], &mut sink).unwrap();
        s.push(x, StepCmd::ResetClock { clock: 9_000_000 }, &mut sink)
            .unwrap();
        s.push(x, step(9_001_000), &mut sink).unwrap();
        // A stop right after a move: off no earlier than a message sent now may be scheduled.
        s.motors_off(&[20_000_000], &mut sink).unwrap();
        let outs: Vec<_> = sink[0]
            .0
            .iter()
            .filter(|(n, _, _)| n == "queue_digital_out")
            .map(|(_, f, req)| (f.clone(), *req))
            .collect();
        // `enable_pin: !PA2` is active low: on is 0. On at the reset clock (before the first
        // step), off 0.1 s (5e6 ticks) after the last step, on again for the next move, off again.
        let oid = i64::try_from(oid0 + pins.iter().position(|p| p.pin == "PA2").unwrap()).unwrap();
        assert_eq!(
            outs,
            [
                (vec![oid, 1_000_000, 0], 1_000_000),
                (vec![oid, 6_020_000, 1], 6_020_000),
                (vec![oid, 9_000_000, 0], 9_000_000),
                (vec![oid, 20_000_000, 1], 20_000_000),
            ]
        );
        // The enable precedes its stepper's first queue_step.
        let first_step = sink[0].0.iter().position(|(n, _, _)| n == "queue_step").unwrap();
        let first_enable = sink[0]
            .0
            .iter()
            .position(|(n, _, _)| n == "queue_digital_out")
            .unwrap();
        assert!(first_enable < first_step);
        // Configured off: value and default_value inactive (1 on an active-low pin).
        let (cmds, _, _) = crate::mcus::config_commands(&dict, &m, "mcu").unwrap();
        let mut config = Recorder(Vec::new(), dict.clone());
        for c in cmds {
            config.send(c).unwrap();
        }
        let enable = config
            .0
            .iter()
            .find(|(n, f, _)| n == "config_digital_out" && f[0] == oid)
            .unwrap();
        assert_eq!(enable.1[2..], [1, 1, 0]);
    }
}
