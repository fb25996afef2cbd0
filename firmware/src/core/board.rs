//! The board: everything the core asks of the hardware (or of the simulator).
//!
//! The core calls these from `receive` and `run_timers`; none may block. On a real MCU
//! `step` toggles the step pin (and the direction pin when it changed) and `write` queues bytes
//! for the UART; the Linux-process target records steps in its trace and writes to its pty.

use super::stepper::StepperConfig;
use rt_core::WireClock;

/// What triggered, in [`Board::triggered`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TriggerSource {
    /// A trsync triggered (and stopped its steppers).
    Trsync,
    /// An endstop confirmed its trigger.
    Endstop,
}

/// Step lateness percentiles in µs of MCU time (`cadence_lateness`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Lateness {
    /// Steps measured.
    pub count: u32,
    /// Median.
    pub p50: u32,
    /// 99th percentile.
    pub p99: u32,
    /// 99.9th percentile.
    pub p999: u32,
    /// Maximum.
    pub max: u32,
}

/// Hardware hooks of the firmware core.
pub trait Board {
    /// Take one step on stepper `oid` in direction `dir` (true = position +1). `clock` is the
    /// step's scheduled time; the board may be running a little after it.
    fn step(&mut self, oid: u8, dir: bool, clock: WireClock);

    /// Send bytes (whole message blocks) to the host.
    fn write(&mut self, bytes: &[u8]);

    /// `config_stepper` configured `oid` (set the pins up).
    fn config_stepper(&mut self, _oid: u8, _config: &StepperConfig) {}

    /// A `queue_step` arrived at `now`; its first step is due at `first_clock`.
    fn queue_step_received(&mut self, _oid: u8, _first_clock: WireClock, _now: WireClock) {}

    /// `config_endstop` made `pin` an input, its pull-up resistor on when `pull_up`.
    fn config_input(&mut self, _pin: u8, _pull_up: bool) {}

    /// Level of input `pin` (endstops), sampled for clock `at`: the due time of the timer
    /// reading it, or now for a query. Hardware reads the pin when called, within its timer's
    /// latency of `at`; a simulation reads its world as it was at `at`.
    fn read_pin(&mut self, _pin: u8, _at: WireClock) -> bool {
        false
    }

    /// ADC reading of `pin` now, `0..=ADC_MAX` (analog in).
    fn read_adc(&mut self, _pin: u8) -> u16 {
        0
    }

    /// ADC reading of the MCU's own temperature sensor (the `ADC_TEMPERATURE` channel),
    /// `0..=ADC_MAX`; 0 on a board that does not offer it.
    fn read_mcu_temperature(&mut self) -> u16 {
        0
    }

    /// Set hardware PWM output `pin` to a duty of `value / PWM_MAX` at `cycle_ticks` per cycle
    /// (`config_pwm_out`, `queue_pwm_out`, `set_pwm_out`); `clock` is the change's time.
    fn set_pwm(&mut self, _pin: u8, _cycle_ticks: u32, _value: u16, _clock: WireClock) {}

    /// Drive output `pin` to `value`; `clock` is the event's scheduled time.
    fn set_pin(&mut self, _pin: u8, _value: bool, _clock: WireClock) {}

    /// `tmcuart_send` on the single-wire (or `rx_pin` ≠ `tx_pin`) UART of TMC drivers: send
    /// the line bits of `write` (least significant bit first, start and stop bits included as
    /// the host encoded them) at `bit_time` ticks per bit, then, if `read` is not empty, sample
    /// `read.len() × 8` bits of the answer from its first start bit on into `read`. A line that
    /// stays idle leaves `read` as it was (zeros): the host's check of the answer fails.
    fn tmcuart_transfer(
        &mut self,
        _rx_pin: u8,
        _tx_pin: u8,
        _bit_time: u32,
        _write: &[u8],
        _read: &mut [u8],
    ) {
    }

    /// One SPI transaction with chip select `cs_pin` asserted: `data` goes out and is replaced
    /// by the bytes clocked in.
    fn spi_transfer(&mut self, _cs_pin: u8, _data: &mut [u8]) {}

    /// Trsync or endstop `oid` triggered at `clock` with `reason`.
    fn triggered(&mut self, _source: TriggerSource, _oid: u8, _reason: u8, _clock: WireClock) {}

    /// Step lateness so far (`cadence_get_lateness`); a board that does not measure it
    /// reports zeros.
    fn lateness(&self) -> Lateness {
        Lateness::default()
    }

    /// The MCU shut down at `clock` for `reason` (`static_string_id` is its dictionary id).
    fn shutdown(&mut self, _clock: WireClock, _static_string_id: u16, _reason: &'static str) {}
}
