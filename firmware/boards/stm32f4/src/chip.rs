//! The chip the image runs on, as the data dictionary names it. Shared by the build script
//! (which writes the dictionary) and the firmware (which turns pin numbers into port and bit),
//! so both read the one declaration.

use firmware::core::constants::Chip;

/// STM32F405/F407: ports A..I of 16 pins (`PA0` = 0, `PB0` = 16, …), as Klipper names them.
pub const CHIP: Chip = Chip {
    mcu: "stm32f405",
    ports: b"ABCDEFGHI",
    pins_per_port: 16,
};

/// Ticks per second of the MCU clock (TIM2, 32-bit free running): the dictionary's
/// `CLOCK_FREQ`. 8 MHz divides both the chip's 16 MHz HSI timer clock and QEMU's timer rate.
pub const CLOCK_FREQ: u32 = 8_000_000;
