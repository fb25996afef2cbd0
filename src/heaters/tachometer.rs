//! A fan's tachometer (`tachometer_pin`) on a live printer: the MCU's pulse counter
//! (`config_counter`, `query_counter`) polls the tach line every `tachometer_poll_interval`
//! and reports every second; the speed is Klipper's: the level changes counted between the
//! clocks of the last changes of two reports, `rpm = changes / seconds · 30 / ppr` (a pulse is
//! two changes, a revolution `ppr` pulses); no change in a report's second reads 0.

use links::mcu::McuLink;

use super::runtime::HeaterLoopError;

/// Seconds between reports (Klipper's `sample_time` of a fan tachometer).
pub const SAMPLE_TIME: f64 = 1.0;

/// One tachometer's loop state.
#[derive(Debug)]
pub struct Tachometer {
    /// The fan (index in `Thermal::fans`).
    pub fan: usize,
    /// Its counter's MCU (index in the printer's MCU list).
    pub link_index: usize,
    oid: u8,
    ppr: u32,
    last_serial: u64,
    /// Time (s) and count of the last measure's end.
    last: Option<(f64, u32)>,
}

impl Tachometer {
    /// The tachometer of fan `fan`, counter object `oid` on MCU `link_index`.
    pub fn new(fan: usize, link_index: usize, oid: u8, ppr: u32) -> Tachometer {
        Tachometer {
            fan,
            link_index,
            oid,
            ppr: ppr.max(1),
            last_serial: 0,
            last: None,
        }
    }

    /// Starts the counter at MCU clock `clock`, polling every `poll_interval` seconds.
    pub fn start(
        &self,
        link: &McuLink,
        clock: u64,
        freq: f64,
        poll_interval: f64,
    ) -> Result<(), HeaterLoopError> {
        let cmd = link.dictionary().encode(
            "query_counter",
            &[
                i64::from(self.oid),
                (clock & 0xFFFF_FFFF) as i64,
                (poll_interval * freq).round().max(1.0) as i64,
                (SAMPLE_TIME * freq).round() as i64,
            ],
        )?;
        Ok(link.send(cmd)?)
    }

    /// Takes the counter's new report, if any: the speed then (rev/min).
    pub fn update(&mut self, link: &McuLink, freq: f64, now_sys: f64) -> Option<f64> {
        let r = link.counter_report(self.oid)?;
        if r.serial == self.last_serial {
            return None;
        }
        self.last_serial = r.serial;
        let est = link.clock();
        // Klipper takes the report's time as its next poll less one poll; a second-long
        // sample makes the poll's length immaterial here.
        let time = est.extend(r.next_clock, now_sys) as f64 / freq;
        let count_time = est.extend(r.count_clock, now_sys) as f64 / freq;
        let (rpm, last) = measure(self.last, time, r.count, count_time, self.ppr);
        self.last = Some(last);
        rpm
    }
}

/// Klipper's frequency counter: from the last measure's end `(time, count)` and a report at
/// `time` with `count` changes, the last at `count_time`: the speed (rev/min; `None` for the
/// first report) and the new measure's end.
pub fn measure(
    last: Option<(f64, u32)>,
    time: f64,
    count: u32,
    count_time: f64,
    ppr: u32,
) -> (Option<f64>, (f64, u32)) {
    let Some((last_time, last_count)) = last else {
        return (None, (time, count));
    };
    let dt = count_time - last_time;
    if dt > 0.0 {
        let freq = f64::from(count.wrapping_sub(last_count)) / dt;
        (Some(freq * 30.0 / f64::from(ppr.max(1))), (count_time, count))
    } else {
        (Some(0.0), (time, count))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn speed_from_counted_changes() {
        // 2 pulses per revolution: 4 changes a revolution; 2500 rpm is 166.7 changes/s.
        let (rpm, last) = measure(None, 1.0, 10, 0.99, 2);
        assert_eq!((rpm, last), (None, (1.0, 10)));
        let (rpm, last) = measure(Some(last), 2.0, 177, 1.999, 2);
        assert!((rpm.unwrap() - 167.0 / 0.999 * 15.0).abs() < 1e-9);
        assert_eq!(last, (1.999, 177));
        // No change since: stopped.
        let (rpm, _) = measure(Some(last), 3.0, 177, 1.999, 2);
        assert_eq!(rpm, Some(0.0));
    }
}
