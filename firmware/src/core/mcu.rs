//! The MCU state machine: link, scheduler, oid objects, shutdown and stats, tied together.
//!
//! Time is an argument: the platform calls [`Mcu::receive`] with incoming bytes and
//! [`Mcu::run_timers`] when [`Mcu::next_wake`] has come, each with the current 32-bit clock.
//! `receive` runs due timers first, so a stepper whose last step is due counts as idle when the
//! next command arrives. The 64-bit uptime is rebuilt from the 32-bit `now` values: the high
//! word grows each time `now` wraps, which is seen because the stats timer guarantees a call at
//! least every 2^30 ticks (less than a quarter of the wrap period).
//!
//! Every fault goes through [`Mcu::shutdown`]: it stops all steppers (timers disarmed, queued
//! moves dropped), reports `shutdown clock static_string_id` once, and from then on commands
//! not marked `in_shutdown` in the table are answered with `is_shutdown` until
//! `clear_shutdown`. `config_reset` (only while shut down, as on Klipper's MCU) forgets the
//! whole configuration and clears the shutdown: the next host configures it from scratch, which
//! is how Klipper's host does `FIRMWARE_RESTART` on an MCU without a `reset` command.

use super::board::Board;
use super::commands::{FMT_SHUTDOWN, FMT_STATS, ID_SHUTDOWN, ID_STATS};
use super::constants::{static_string_id, STATS_SUMSQ_BASE};
use super::link::Link;
use super::moves::MovePool;
use super::sched::Scheduler;
use super::stepper::Stepper;
use super::{analog_in::AnalogIn, digital_out::DigitalOut, endstop::Endstop, trsync::Trsync};
use links::proto::block::MESSAGE_PAYLOAD_MAX;
use links::proto::format::{encode_message, Value};
use rt_core::WireClock;

/// Start-up parameters of the core.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct McuConfig {
    /// Ticks per second of the MCU clock (the dictionary's `CLOCK_FREQ`).
    pub clock_freq: u32,
    /// Moves the pool may hold at once (clamped to the pool's capacity); reported in `config`.
    pub move_count: u16,
    /// How late (ticks) a step or a periodic timer may run before the MCU shuts down
    /// ("Stepper too far in past", "Rescheduled timer in the past"); 0 = never.
    pub late_limit: u32,
}

/// What an oid refers to.
#[derive(Debug, Clone)]
pub(super) enum Object {
    /// Allocated, not configured yet.
    Free,
    /// A stepper.
    Stepper(Stepper),
    /// An endstop.
    Endstop(Endstop),
    /// A trsync.
    Trsync(Trsync),
    /// A digital out.
    DigitalOut(DigitalOut),
    /// An analog in.
    AnalogIn(AnalogIn),
    /// A hardware PWM output.
    PwmOut(super::pwm_out::PwmOut),
    /// A pulse counter.
    Counter(super::counter::Counter),
    /// A TMC driver's bit-banged UART line.
    TmcUart(super::buses::TmcUart),
    /// An SPI device (its chip select).
    Spi(super::buses::SpiDevice),
    /// An SPI temperature chip.
    Thermocouple(super::thermocouple::Thermocouple),
}

/// The periodic `stats` accumulator.
#[derive(Debug, Clone, Copy)]
struct Stats {
    count: u32,
    sum: u32,
    sumsq: u32,
    next_report: WireClock,
    period: u32,
}

/// The firmware core for board `B`, with `OIDS` oid slots and a pool of `MOVES` moves.
pub struct Mcu<B: Board, const OIDS: usize, const MOVES: usize> {
    pub(super) board: B,
    pub(super) dictionary: &'static [u8],
    pub(super) link: Link,
    pub(super) sched: Scheduler<OIDS>,
    pub(super) pool: MovePool<MOVES>,
    /// The digital outs' scheduled updates.
    pub(super) updates: super::digital_out::UpdatePool,
    pub(super) objects: [Object; OIDS],
    /// `allocate_oids` count, once allocated.
    pub(super) oid_count: Option<u8>,
    pub(super) is_config: bool,
    pub(super) config_crc: u32,
    /// The reason of the current shutdown.
    pub(super) shutdown_reason: Option<&'static str>,
    /// See [`McuConfig::late_limit`].
    pub(super) late_limit: u32,
    uptime_high: u32,
    last_now: WireClock,
    stats: Stats,
}

impl<B: Board, const OIDS: usize, const MOVES: usize> ::core::fmt::Debug for Mcu<B, OIDS, MOVES> {
    fn fmt(&self, f: &mut ::core::fmt::Formatter<'_>) -> ::core::fmt::Result {
        f.debug_struct("Mcu")
            .field("dictionary_len", &self.dictionary.len())
            .field("rx_seq", &self.link.rx_seq())
            .field("oid_count", &self.oid_count)
            .field("is_config", &self.is_config)
            .field("config_crc", &self.config_crc)
            .field("shutdown_reason", &self.shutdown_reason)
            .field("moves_used", &self.pool.used())
            .field("move_count", &self.pool.limit())
            .field("armed_timers", &self.sched.armed_count())
            .finish_non_exhaustive()
    }
}

impl<B: Board, const OIDS: usize, const MOVES: usize> Mcu<B, OIDS, MOVES> {
    /// A powered-up MCU at clock `now`, serving `dictionary` (the zlib-compressed JSON) through
    /// `identify`.
    pub fn new(board: B, dictionary: &'static [u8], config: McuConfig, now: WireClock) -> Self {
        // Report at least every 2^30 ticks so the uptime high word never misses a wrap.
        let period = (config.clock_freq as u64 * 5).clamp(1, 1 << 30) as u32;
        Mcu {
            board,
            dictionary,
            link: Link::new(),
            sched: Scheduler::new(),
            pool: MovePool::new(config.move_count as usize),
            updates: super::digital_out::UpdatePool::new(),
            objects: [const { Object::Free }; OIDS],
            oid_count: None,
            is_config: false,
            config_crc: 0,
            shutdown_reason: None,
            late_limit: config.late_limit,
            uptime_high: 0,
            last_now: now,
            stats: Stats {
                count: 0,
                sum: 0,
                sumsq: 0,
                next_report: now.add(period),
                period,
            },
        }
    }

    /// The board.
    pub fn board(&self) -> &B {
        &self.board
    }

    /// The board, mutably (e.g. to tell a simulated board the current time).
    pub fn board_mut(&mut self) -> &mut B {
        &mut self.board
    }

    /// The reason of the current shutdown, if shut down.
    pub fn shutdown_reason(&self) -> Option<&'static str> {
        self.shutdown_reason
    }

    /// True after `finalize_config`.
    pub fn is_config(&self) -> bool {
        self.is_config
    }

    /// The `move_count` reported in `config`.
    pub fn move_count(&self) -> u16 {
        self.pool.limit() as u16
    }

    /// Net executed steps of stepper `oid`.
    pub fn stepper_position(&self, oid: u8) -> Option<i32> {
        match self.objects.get(oid as usize) {
            Some(Object::Stepper(s)) => Some(s.position()),
            _ => None,
        }
    }

    /// The 64-bit clock of `now` (uptime): high word counted from observed wraps.
    pub fn uptime(&self) -> u64 {
        ((self.uptime_high as u64) << 32) | self.last_now.0 as u64
    }

    /// When [`Mcu::run_timers`] must run next (a step timer or the stats report).
    pub fn next_wake(&self) -> WireClock {
        match self.sched.next_wake() {
            Some(t) if t.is_before(self.stats.next_report) => t,
            _ => self.stats.next_report,
        }
    }

    /// Feeds bytes from the host received at `now`: dispatches every complete block, answering
    /// and acking. Timers already due are left to the next [`Mcu::run_timers`], after the
    /// commands: a platform loop that ran late (a stalled process, a long interrupt) cannot
    /// tell when during its delay the bytes came, and a board's UART takes them in while its
    /// timers wait, so a `trsync_set_timeout` sent in time must renew the trsync before the
    /// expiry it was sent to prevent (a simulated MCU stalled under Klipper's host expired
    /// trsyncs whose renewal was waiting: "Communication timeout during homing").
    pub fn receive(&mut self, now: WireClock, mut data: &[u8]) {
        self.observe(now);
        let mut payload = [0u8; MESSAGE_PAYLOAD_MAX];
        while !data.is_empty() {
            let n = self.link.push_rx(data);
            data = &data[n..];
            while let Some(len) = self.link.next_block(&mut payload, &mut self.board) {
                self.dispatch(&payload[..len], now);
                self.link.ack(&mut self.board);
            }
        }
        self.link.flush(&mut self.board);
    }

    /// Runs every timer due at `now` (steps, stats) and sends what they produced.
    pub fn run_timers(&mut self, now: WireClock) {
        self.run_due(now);
        self.link.flush(&mut self.board);
    }

    /// Accounts one iteration of the platform's main loop that was busy for `busy_ticks`
    /// (reported in `stats`: count, sum of ticks, sum of squares in units of
    /// `STATS_SUMSQ_BASE`, all saturating).
    pub fn record_loop(&mut self, busy_ticks: u32) {
        let s = &mut self.stats;
        s.count = s.count.saturating_add(1);
        s.sum = s.sum.saturating_add(busy_ticks);
        let sq = (busy_ticks as u64 * busy_ticks as u64).div_ceil(STATS_SUMSQ_BASE as u64);
        s.sumsq = s.sumsq.saturating_add(u32::try_from(sq).unwrap_or(u32::MAX));
    }

    fn observe(&mut self, now: WireClock) {
        if now.0 < self.last_now.0 {
            self.uptime_high = self.uptime_high.wrapping_add(1);
        }
        self.last_now = now;
    }

    fn run_due(&mut self, now: WireClock) {
        self.observe(now);
        while let Some((oid, at)) = self.sched.pop_due(now) {
            self.timer_event(oid, at, now);
        }
        if !now.is_before(self.stats.next_report) {
            self.report_stats(now);
        }
    }

    /// The timer of `oid` fired at `now` for the event scheduled at `at`.
    fn timer_event(&mut self, oid: u8, at: WireClock, now: WireClock) {
        match self.objects.get_mut(oid as usize) {
            Some(Object::Stepper(s)) => {
                if self.late_limit > 0 && at.add(self.late_limit).is_before(now) {
                    return self.shutdown(super::constants::reason::STEPPER_TOO_FAR_IN_PAST, now);
                }
                if let Some(taken) = s.step_event(&mut self.pool, at) {
                    self.board.step(oid, taken.dir, at);
                    if let Some(next) = taken.next {
                        self.sched.arm(oid, next);
                    }
                }
            }
            Some(Object::Free) | None => {}
            Some(_) => self.object_timer(oid, at, now),
        }
    }

    fn report_stats(&mut self, now: WireClock) {
        let s = self.stats;
        let args = [
            Value::Int(s.count as i64),
            Value::Int(s.sum as i64),
            Value::Int(s.sumsq as i64),
        ];
        self.respond(ID_STATS, FMT_STATS, &args);
        let mut next = s.next_report.add(s.period);
        if !now.is_before(next) {
            next = now.add(s.period); // we slept through whole periods: restart from now
        }
        self.stats = Stats {
            count: 0,
            sum: 0,
            sumsq: 0,
            next_report: next,
            period: s.period,
        };
    }

    /// Encodes one response and queues it for the host.
    pub(super) fn respond(&mut self, id: u32, format: &str, args: &[Value<'_>]) {
        let mut msg = [0u8; MESSAGE_PAYLOAD_MAX];
        match encode_message(id, format, args, &mut msg) {
            Ok(n) => self.link.send(&msg[..n], &mut self.board),
            Err(_) => debug_assert!(false, "response {format} does not encode"),
        }
    }

    /// `config_reset`: while shut down, back to the unconfigured state (no oids, no objects,
    /// no moves, `is_config` 0, crc 0, not shut down); the link and clock go on. Not shut
    /// down: shutdown "config_reset only available when shutdown".
    pub(super) fn config_reset(&mut self, now: WireClock) {
        if self.shutdown_reason.is_none() {
            return self.shutdown(super::constants::reason::CONFIG_RESET_NOT_SHUTDOWN, now);
        }
        self.sched.clear();
        self.pool.clear();
        self.updates.clear();
        self.objects = [const { Object::Free }; OIDS];
        self.oid_count = None;
        self.is_config = false;
        self.config_crc = 0;
        self.shutdown_reason = None;
    }

    /// The one shutdown path: stops every stepper and reports `reason` (the first reason wins;
    /// later calls while shut down do nothing). `reason` should be one of
    /// [`super::constants::SHUTDOWN_REASONS`].
    pub fn shutdown(&mut self, reason: &'static str, now: WireClock) {
        if self.shutdown_reason.is_some() {
            return;
        }
        self.shutdown_reason = Some(reason);
        for obj in self.objects.iter_mut() {
            match obj {
                Object::Stepper(s) => s.stop(),
                Object::Endstop(e) => e.halt(),
                Object::Trsync(t) => t.halt(),
                Object::AnalogIn(a) => a.halt(),
                Object::Thermocouple(t) => t.halt(),
                Object::Counter(c) => c.halt(),
                Object::PwmOut(p) => {
                    let (pin, cycle) = (p.config().pin, p.config().cycle_ticks);
                    let value = p.halt();
                    self.board.set_pwm(pin, cycle, value, now);
                }
                Object::DigitalOut(d) => {
                    let pin = d.config().pin;
                    let level = d.halt();
                    self.board.set_pin(pin, level, now);
                }
                // The UART line idles high, as after `config_tmcuart`.
                Object::TmcUart(u) => self.board.set_pin(u.tx_pin, true, now),
                Object::Spi(_) | Object::Free => {}
            }
        }
        self.sched.clear();
        self.pool.clear();
        self.updates.clear();
        let id = static_string_id(reason);
        self.board.shutdown(now, id, reason);
        self.respond(
            ID_SHUTDOWN,
            FMT_SHUTDOWN,
            &[Value::Int(now.0 as i64), Value::Int(id as i64)],
        );
    }
}

#[cfg(test)]
#[path = "mcu_tests.rs"]
mod tests;
