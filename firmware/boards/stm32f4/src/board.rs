//! [`Stm32Board`]: the core's [`Board`] on an STM32F4 — steps and outputs on GPIO, endstops
//! from GPIO inputs, analog inputs from ADC1, bytes to USART1, lateness measured against TIM2.
//!
//! Pins are numbered as the dictionary's `pin` enumeration says ([`crate::chip::CHIP`]: 16 per
//! port, `PA0` = 0). A pin number outside the chip is ignored (the host only sends numbers
//! from the enumeration). Under QEMU the GPIO writes go nowhere and inputs read low; the core
//! still counts every step, so `stepper_get_position` stays exact.

use crate::chip::CHIP;
use crate::lateness::LatenessHistogram;
use crate::{hw, uart};
use firmware::core::stepper::StepperConfig;
use firmware::core::{Board, Lateness};
use rt_core::WireClock;

/// Oid slots of the image.
pub const OIDS: usize = 64;

/// Status polls an ADC conversion may take before it reads as 0 (a conversion takes ~20 µs).
const ADC_MAX_POLLS: u32 = 10_000;

/// The pins of one configured stepper.
#[derive(Debug, Clone, Copy)]
struct StepPins {
    step: (usize, u8),
    dir: (usize, u8),
    invert_step: bool,
    pulse_ticks: u32,
    dir_level: bool,
}

/// The STM32F4 board.
#[derive(Debug)]
pub struct Stm32Board {
    steppers: [Option<StepPins>; OIDS],
    lateness: LatenessHistogram,
    ticks_per_us: u32,
}

impl Stm32Board {
    /// A board whose MCU clock runs at `clock_freq` Hz.
    pub const fn new(clock_freq: u32) -> Self {
        let per_us = clock_freq / 1_000_000;
        Stm32Board {
            steppers: [None; OIDS],
            lateness: LatenessHistogram::new(),
            ticks_per_us: if per_us == 0 { 1 } else { per_us },
        }
    }
}

/// ADC1 channel of a pin (RM0090 table 7: ADC123_IN0..15).
fn adc_channel(port: usize, bit: u8) -> Option<u8> {
    match (port, bit) {
        (0, 0..=7) => Some(bit),
        (1, 0..=1) => Some(8 + bit),
        (2, 0..=5) => Some(10 + bit),
        _ => None,
    }
}

impl Board for Stm32Board {
    fn step(&mut self, oid: u8, dir: bool, clock: WireClock) {
        let start = hw::clock();
        let late = start.wrapping_sub(clock.0);
        // A step timer never runs early; a huge value is a step that ran before its time.
        let late_us = if late > u32::MAX / 2 {
            0
        } else {
            late / self.ticks_per_us
        };
        self.lateness.record(late_us);
        let Some(Some(p)) = self.steppers.get_mut(oid as usize) else {
            return;
        };
        if p.dir_level != dir {
            hw::gpio_set(p.dir.0, p.dir.1, dir);
            p.dir_level = dir;
        }
        hw::gpio_set(p.step.0, p.step.1, !p.invert_step);
        while hw::clock().wrapping_sub(start) < p.pulse_ticks {}
        hw::gpio_set(p.step.0, p.step.1, p.invert_step);
    }

    fn write(&mut self, bytes: &[u8]) {
        uart::send(bytes);
    }

    fn config_stepper(&mut self, oid: u8, config: &StepperConfig) {
        let (Some(step), Some(dir)) = (CHIP.port_bit(config.step_pin), CHIP.port_bit(config.dir_pin)) else {
            return;
        };
        let Some(slot) = self.steppers.get_mut(oid as usize) else {
            return;
        };
        hw::gpio_set(step.0, step.1, config.invert_step);
        hw::gpio_output(step.0, step.1);
        hw::gpio_set(dir.0, dir.1, false);
        hw::gpio_output(dir.0, dir.1);
        *slot = Some(StepPins {
            step,
            dir,
            invert_step: config.invert_step,
            // At most 10 µs: the pulse is a busy wait inside the step timer.
            pulse_ticks: config.step_pulse_ticks.min(10 * self.ticks_per_us),
            dir_level: false,
        });
    }

    fn config_input(&mut self, pin: u8, pull_up: bool) {
        if let Some((port, bit)) = CHIP.port_bit(pin) {
            hw::gpio_input(port, bit, pull_up);
        }
    }

    fn read_pin(&mut self, pin: u8, _at: WireClock) -> bool {
        CHIP.port_bit(pin)
            .is_some_and(|(port, bit)| hw::gpio_read(port, bit))
    }

    fn read_adc(&mut self, pin: u8) -> u16 {
        let Some((port, bit)) = CHIP.port_bit(pin) else {
            return 0;
        };
        let Some(channel) = adc_channel(port, bit) else {
            return 0;
        };
        hw::gpio_analog(port, bit);
        hw::adc_convert(channel, ADC_MAX_POLLS).unwrap_or(0)
    }

    fn set_pin(&mut self, pin: u8, value: bool, _clock: WireClock) {
        if let Some((port, bit)) = CHIP.port_bit(pin) {
            hw::gpio_set(port, bit, value);
            hw::gpio_output(port, bit);
        }
    }

    fn lateness(&self) -> Lateness {
        self.lateness.summary()
    }
}
