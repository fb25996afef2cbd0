//! Registers of the STM32F405/F407 peripherals the board uses (RM0090), the only `unsafe` of
//! the image besides the start-up vector table: RCC clock enables, GPIO, USART1, TIM2 (the MCU
//! clock), ADC1. Each access is a volatile read or write of a fixed, aligned, always-mapped
//! peripheral register.
//!
//! Under QEMU 7.2's `netduinoplus2` (STM32F405 model) USART1..6, TIM2..5, ADC1..3, SPI,
//! SYSCFG and EXTI are modelled; RCC, GPIO, flash interface, DMA and the other timers are
//! "unimplemented" regions (writes ignored, reads 0). So nothing here waits on an RCC ready
//! flag, GPIO writes have no effect in emulation and GPIO inputs read low. The ADC model
//! never sets its end-of-conversion flag (see [`adc_convert`]).

use core::ptr::{read_volatile, write_volatile};

const RCC: usize = 0x4002_3800;
const RCC_AHB1ENR: usize = RCC + 0x30;
const RCC_APB1ENR: usize = RCC + 0x40;
const RCC_APB2ENR: usize = RCC + 0x44;

const GPIO_BASE: usize = 0x4002_0000;
const GPIO_STRIDE: usize = 0x400;
const GPIO_MODER: usize = 0x00;
const GPIO_PUPDR: usize = 0x0C;
const GPIO_IDR: usize = 0x10;
const GPIO_BSRR: usize = 0x18;

const USART1: usize = 0x4001_1000;
const USART_SR: usize = USART1;
const USART_DR: usize = USART1 + 0x04;
const USART_BRR: usize = USART1 + 0x08;
const USART_CR1: usize = USART1 + 0x0C;
/// `SR.RXNE`: a received byte waits in `DR`.
pub const SR_RXNE: u32 = 1 << 5;
/// `SR.TXE`: `DR` may take the next byte.
pub const SR_TXE: u32 = 1 << 7;
/// `SR.ORE`: a byte was lost (overrun).
pub const SR_ORE: u32 = 1 << 3;
const CR1_UE: u32 = 1 << 13;
const CR1_TXEIE: u32 = 1 << 7;
const CR1_RXNEIE: u32 = 1 << 5;
const CR1_TE: u32 = 1 << 3;
const CR1_RE: u32 = 1 << 2;
/// USART1's interrupt number.
pub const USART1_IRQ: u16 = 37;

const TIM2: usize = 0x4000_0000;
const TIM_CR1: usize = 0x00;
const TIM_EGR: usize = 0x14;
const TIM_CNT: usize = 0x24;
const TIM_PSC: usize = 0x28;
const TIM_ARR: usize = 0x2C;

const ADC1: usize = 0x4001_2000;
const ADC_SR: usize = ADC1;
const ADC_CR2: usize = ADC1 + 0x08;
const ADC_SMPR1: usize = ADC1 + 0x0C;
const ADC_SMPR2: usize = ADC1 + 0x10;
/// 144-cycle sampling (0b110) for every channel field: ~20 µs per conversion at 8 MHz.
const SMPR2_144: u32 = 0o6666666666;
const SMPR1_144: u32 = 0o666666666;
const ADC_SQR1: usize = ADC1 + 0x2C;
const ADC_SQR3: usize = ADC1 + 0x34;
const ADC_DR: usize = ADC1 + 0x4C;

fn read(addr: usize) -> u32 {
    // SAFETY: every `addr` passed here is one of the constant register addresses above: mapped,
    // 4-byte aligned, and readable at any time without side effects beyond the peripheral's own.
    unsafe { read_volatile(addr as *const u32) }
}

fn write(addr: usize, value: u32) {
    // SAFETY: as in `read`; the registers written are owned by this module (the board has the
    // only copy of the peripherals) and a write touches no memory the program uses.
    unsafe { write_volatile(addr as *mut u32, value) }
}

fn modify(addr: usize, f: impl FnOnce(u32) -> u32) {
    write(addr, f(read(addr)));
}

/// Clocks on for GPIO ports A..I, TIM2, USART1 and ADC1.
pub fn enable_clocks() {
    modify(RCC_AHB1ENR, |v| v | 0x1FF);
    modify(RCC_APB1ENR, |v| v | 1);
    modify(RCC_APB2ENR, |v| v | (1 << 4) | (1 << 8));
}

/// TIM2 counting up, free running over all 32 bits, at `timer_input_hz / (prescaler + 1)`.
pub fn start_clock(prescaler: u16) {
    write(TIM2 + TIM_CR1, 0);
    write(TIM2 + TIM_PSC, prescaler as u32);
    write(TIM2 + TIM_ARR, u32::MAX);
    write(TIM2 + TIM_EGR, 1); // load the prescaler now
    write(TIM2 + TIM_CNT, 0);
    write(TIM2 + TIM_CR1, 1);
}

/// TIM2's counter: the MCU clock.
pub fn clock() -> u32 {
    read(TIM2 + TIM_CNT)
}

/// USART1 at `pclk_hz / brr` baud (8N1), receive interrupt on, transmitter idle.
pub fn start_uart(brr: u32) {
    // PA9 (TX) and PA10 (RX) to alternate function 7.
    modify(GPIO_BASE + GPIO_MODER, |v| (v & !(0xF << 18)) | (0xA << 18));
    modify(GPIO_BASE + 0x24, |v| (v & !(0xFF << 4)) | (0x77 << 4)); // AFRH
    write(USART_BRR, brr);
    write(USART_CR1, CR1_UE | CR1_TE | CR1_RE | CR1_RXNEIE);
}

/// USART1's status register.
pub fn uart_status() -> u32 {
    read(USART_SR)
}

/// Reads USART1's data register (takes the received byte, clearing `RXNE`/`ORE`).
pub fn uart_read() -> u8 {
    read(USART_DR) as u8
}

/// Writes one byte to USART1's data register (only when `TXE` is set).
pub fn uart_write(byte: u8) {
    write(USART_DR, byte as u32);
}

/// Turns the transmit-empty interrupt on or off.
pub fn uart_tx_interrupt(on: bool) {
    modify(USART_CR1, |v| if on { v | CR1_TXEIE } else { v & !CR1_TXEIE });
}

/// True when the transmit-empty interrupt is on.
pub fn uart_tx_interrupt_on() -> bool {
    read(USART_CR1) & CR1_TXEIE != 0
}

fn gpio(port: usize, reg: usize) -> usize {
    GPIO_BASE + port * GPIO_STRIDE + reg
}

/// Makes `bit` of `port` a push-pull output.
pub fn gpio_output(port: usize, bit: u8) {
    let shift = 2 * bit as u32;
    modify(gpio(port, GPIO_MODER), |v| (v & !(3 << shift)) | (1 << shift));
}

/// Makes `bit` of `port` an input, pulled up or floating.
pub fn gpio_input(port: usize, bit: u8, pull_up: bool) {
    let shift = 2 * bit as u32;
    modify(gpio(port, GPIO_MODER), |v| v & !(3 << shift));
    modify(gpio(port, GPIO_PUPDR), |v| {
        (v & !(3 << shift)) | ((pull_up as u32) << shift)
    });
}

/// Drives `bit` of `port` high or low (atomic through BSRR).
pub fn gpio_set(port: usize, bit: u8, high: bool) {
    let b = if high { 1u32 << bit } else { 1u32 << (bit + 16) };
    write(gpio(port, GPIO_BSRR), b);
}

/// Level of `bit` of `port`.
pub fn gpio_read(port: usize, bit: u8) -> bool {
    read(gpio(port, GPIO_IDR)) & (1 << bit) != 0
}

/// Makes `bit` of `port` an analog input.
pub fn gpio_analog(port: usize, bit: u8) {
    let shift = 2 * bit as u32;
    modify(gpio(port, GPIO_MODER), |v| v | (3 << shift));
}

/// ADC1 on, 12 bits, one conversion per start, 144-cycle sampling on every channel.
pub fn start_adc() {
    write(ADC_SMPR1, SMPR1_144);
    write(ADC_SMPR2, SMPR2_144);
    write(ADC_SQR1, 0);
    write(ADC_CR2, 1);
}

/// One ADC1 conversion of `channel`, or `None` if it did not finish within `max_polls`
/// status reads.
pub fn adc_convert(channel: u8, max_polls: u32) -> Option<u16> {
    write(ADC_SQR3, channel as u32 & 0x1F);
    write(ADC_SR, 0);
    write(ADC_CR2, 1 | (1 << 30)); // ADON | SWSTART
    if cfg!(feature = "qemu") {
        // QEMU 7.2's ADC model never sets EOC: it "converts" when DR is read after SWSTART
        // (a synthetic value stepping by 7).
        return Some((read(ADC_DR) & 0xFFF) as u16);
    }
    for _ in 0..max_polls {
        if read(ADC_SR) & 0x2 != 0 {
            return Some((read(ADC_DR) & 0xFFF) as u16);
        }
    }
    None
}
