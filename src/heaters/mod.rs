//! The host's heater logic, pure and clock-free (time is an argument): temperature sensors
//! ([`thermistor`]: ADC ↔ °C for thermistors and platinum RTDs), control ([`control`]: PID in
//! Klipper's units, watermark, smoothing), thermal runaway protection ([`verify`]:
//! `[verify_heater]`) and PID calibration ([`calibrate`]: the relay method of PID_CALIBRATE).
//!
//! The print loop, M104/M109/M140/M190, the heater objects on the MCUs and the status are
//! wired to these in the host integration that follows the library restructuring (issue #17);
//! until then only the tests and embedders use them.

pub mod calibrate;
pub mod control;
pub mod thermistor;
pub mod verify;
