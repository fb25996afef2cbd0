//! The host's heater logic, pure and clock-free (time is an argument): temperature sensors
//! ([`thermistor`]: ADC ↔ °C for thermistors and platinum RTDs), control ([`control`]: PID in
//! Klipper's units, watermark, smoothing), the MCU's own sensor ([`mcu_sensor`]), SPI
//! temperature chips ([`spi_sensor`]), thermal runaway protection ([`verify`]:
//! `[verify_heater]`) and PID calibration ([`calibrate`]: the relay method of PID_CALIBRATE).
//!
//! Driving them: [`objects`] (printer.cfg → heaters, sensors and fans with their MCU objects
//! and configuration commands) and [`runtime`] (the heater thread of a live print: ADC reports
//! → temperature → control → PWM on the MCU clock, verify_heater, fans).

pub mod adc_scaled;
pub mod calibrate;
pub mod control;
pub mod feed;
pub mod gcode;
pub mod mcu_sensor;
pub mod objects;
pub mod runtime;
pub mod spi_sensor;
pub mod tachometer;
pub mod thermistor;
pub mod verify;
