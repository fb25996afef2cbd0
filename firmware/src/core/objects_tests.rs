//! Protocol tests of endstops, trsyncs, digital outs and analog ins (virtual clock, fake board).

use super::*;

/// oids: 0 stepper, 1 trsync, 2 endstop on pin 10 (reads 1 once stepper 0 is at ≥ `trip`).
fn homing_host(trip: i32) -> Host {
    let mut host = Host::new(64, 0);
    host.mcu.board_mut().endstop = Some((10, 0, trip));
    host.exchange(&[("allocate_oids", &[3])]);
    host.exchange(&[("config_stepper", &[0, 0, 1, 0, 2])]);
    host.exchange(&[("config_trsync", &[1]), ("config_endstop", &[2, 10, 0])]);
    host.exchange(&[("finalize_config", &[1])]);
    host
}

fn named<'a>(msgs: &'a [Resp], name: &str) -> Vec<&'a [i64]> {
    msgs.iter()
        .filter(|r| r.name == name)
        .map(|r| r.ints.as_slice())
        .collect()
}

#[test]
fn config_endstop_sets_up_its_input_pin_with_the_pull_up_asked() {
    let mut host = Host::new(64, 0);
    host.exchange(&[("allocate_oids", &[2])]);
    host.exchange(&[("config_endstop", &[0, 10, 0]), ("config_endstop", &[1, 27, 1])]);
    assert_eq!(host.mcu.board().inputs, [(10, false), (27, true)]);
}

#[test]
fn endstop_trigger_stops_the_attached_stepper_at_the_right_step() {
    let mut host = homing_host(20);
    host.exchange(&[
        ("trsync_start", &[1, 0, 0, 4]),
        ("stepper_stop_on_trigger", &[0, 1]),
        ("trsync_set_timeout", &[1, 1_000_000]),
    ]);
    host.exchange(&[("endstop_home", &[2, 1000, 15, 4, 110, 1, 1, 1])]);
    host.exchange(&[
        ("reset_step_clock", &[0, 1000]),
        ("set_next_step_dir", &[0, 1]),
        ("queue_step", &[0, 50, 1000, 0]),
        ("queue_step", &[0, 50, 1000, 0]),
    ]);
    // Steps at 1050, 1100, …: position 20 at 2000. Reads at 1000 + 110k: 2100 is the first match
    // (position 22), confirmed at 2115, 2130, 2145 (no step in between): trigger at 2145.
    let msgs = all_msgs(&host.advance(100_000));
    assert_eq!(named(&msgs, "trsync_state"), [&[1, 0, 1, 2145][..]]);
    assert_eq!(host.mcu.stepper_position(0), Some(22));
    assert_eq!(host.mcu.board().steps.len(), 22);
    assert_eq!(host.mcu.board().steps.last(), Some(&(0, true, 2100)));
    assert_eq!(
        host.mcu.pool.used(),
        0,
        "the discarded move went back to the pool"
    );
    assert_eq!(
        host.mcu.board().triggers,
        [
            (TriggerSource::Endstop, 2, 1, 2145),
            (TriggerSource::Trsync, 1, 1, 2145)
        ]
    );
    // next_clock = first matching read (2100) + rest_ticks (110): Klipper's host subtracts them.
    let msgs = all_msgs(&host.exchange(&[("endstop_query_state", &[2]), ("stepper_get_position", &[0])]));
    assert_eq!(named(&msgs, "endstop_state"), [&[2, 0, 2210, 1][..]]);
    assert_eq!(named(&msgs, "stepper_position"), [&[0, 22][..]]);
    // The host's own trsync_trigger afterwards only reports the original reason.
    let msgs = all_msgs(&host.exchange(&[("trsync_trigger", &[1, 2])]));
    assert_eq!(named(&msgs, "trsync_state"), [&[1, 0, 1, 2145][..]]);
    // A step command the trigger overtook is dropped (the stepper needs a reset): no shutdown,
    // no step, no pool slot.
    let msgs = all_msgs(&host.exchange(&[("queue_step", &[0, 50, 10, 0])]));
    assert!(named(&msgs, "shutdown").is_empty());
    assert_eq!(host.mcu.pool.used(), 0);
    host.advance(150_000);
    assert_eq!(host.mcu.stepper_position(0), Some(22));
    assert_eq!(host.mcu.board().steps.len(), 22);
    // reset_step_clock re-enables it: a new move runs from the new base.
    host.exchange(&[
        ("reset_step_clock", &[0, 200_000]),
        ("queue_step", &[0, 10, 2, 0]),
    ]);
    host.advance(300_000);
    assert_eq!(host.mcu.stepper_position(0), Some(24));
    assert_eq!(host.mcu.board().steps.last(), Some(&(0, true, 200_020)));
    assert!(host.mcu.shutdown_reason().is_none());
}

#[test]
fn while_homing_next_clock_is_the_next_read() {
    let mut host = homing_host(1000);
    host.exchange(&[("trsync_start", &[1, 0, 0, 4])]);
    host.exchange(&[("endstop_home", &[2, 1000, 15, 4, 110, 1, 1, 1])]);
    host.advance(1500);
    let msgs = all_msgs(&host.exchange(&[("endstop_query_state", &[2])]));
    assert_eq!(named(&msgs, "endstop_state"), [&[2, 1, 1550, 0][..]]);
    // Cancel (sample_count 0): no more reads, homing off.
    host.exchange(&[("endstop_home", &[2, 0, 0, 0, 0, 0, 0, 0])]);
    let msgs = all_msgs(&host.exchange(&[("endstop_query_state", &[2])]));
    assert_eq!(named(&msgs, "endstop_state")[0][1], 0);
    assert_eq!(host.mcu.sched.armed_count(), 0);
}

#[test]
fn trsync_reports_at_the_right_clocks_and_expires_with_reason_4() {
    let mut host = homing_host(1_000_000);
    host.exchange(&[
        ("trsync_start", &[1, 5000, 3000, 4]),
        ("stepper_stop_on_trigger", &[0, 1]),
        ("trsync_set_timeout", &[1, 10_500]),
        ("reset_step_clock", &[0, 1000]),
        ("set_next_step_dir", &[0, 1]),
        ("queue_step", &[0, 1000, 60, 0]),
    ]);
    let msgs = all_msgs(&host.advance(9_999));
    assert_eq!(
        named(&msgs, "trsync_state"),
        [&[1, 1, 0, 5000][..], &[1, 1, 0, 8000][..]]
    );
    // Expiry at 10 500: triggers itself with the expire reason, the stepper (steps at 2000,
    // 3000, …, 10 000) stops at once.
    let msgs = all_msgs(&host.advance(10_999));
    assert_eq!(named(&msgs, "trsync_state"), [&[1, 0, 4, 10_500][..]]);
    assert_eq!(host.mcu.stepper_position(0), Some(9));
    let msgs = all_msgs(&host.advance(11_000));
    assert_eq!(
        named(&msgs, "trsync_state"),
        [&[1, 0, 4, 10_500][..]],
        "periodic reports carry the trigger clock"
    );
    host.advance(100_000);
    assert_eq!(host.mcu.stepper_position(0), Some(9));
}

#[test]
fn renewed_timeout_does_not_expire_and_host_trigger_reports() {
    let mut host = homing_host(1_000_000);
    host.exchange(&[
        ("trsync_start", &[1, 0, 0, 4]),
        ("trsync_set_timeout", &[1, 10_000]),
    ]);
    host.advance(9_000);
    host.exchange(&[("trsync_set_timeout", &[1, 20_000])]);
    let msgs = all_msgs(&host.advance(15_000));
    assert!(
        named(&msgs, "trsync_state").is_empty(),
        "10 000 passed after the renewal"
    );
    let msgs = all_msgs(&host.exchange(&[("trsync_trigger", &[1, 2])]));
    assert_eq!(named(&msgs, "trsync_state"), [&[1, 0, 2, 15_000][..]]);
    let msgs = all_msgs(&host.advance(30_000));
    assert!(named(&msgs, "trsync_state").is_empty(), "expiry was cancelled");
    // A restart re-arms it.
    host.exchange(&[
        ("trsync_start", &[1, 0, 0, 4]),
        ("trsync_set_timeout", &[1, 40_000]),
    ]);
    let msgs = all_msgs(&host.advance(40_000));
    assert_eq!(named(&msgs, "trsync_state"), [&[1, 0, 4, 40_000][..]]);
}

/// A platform loop that comes back late (a stalled simulator process) hands the bytes that
/// waited to the MCU before its overdue timers: a renewal the host sent before the expiry
/// renews it although the loop only reads it after the expiry clock. Before, `receive` ran
/// the due timers first and the trsync expired with reason 4 ("Communication timeout during
/// homing" under Klipper's host, whose renewals sat in the pty of a stalled cadence-mcu).
#[test]
fn renewal_read_after_a_stall_is_applied_before_the_overdue_expiry() {
    let mut host = homing_host(1_000_000);
    host.exchange(&[
        ("trsync_start", &[1, 0, 0, 4]),
        ("trsync_set_timeout", &[1, 10_000]),
    ]);
    host.advance(9_000);
    // The loop stalls from 9 000 to 12 000; the renewal waited in its input meanwhile.
    host.now = 12_000;
    let msgs = all_msgs(&host.exchange(&[("trsync_set_timeout", &[1, 30_000])]));
    assert!(named(&msgs, "trsync_state").is_empty(), "{msgs:?}");
    let msgs = all_msgs(&host.advance(29_000));
    assert!(
        named(&msgs, "trsync_state").is_empty(),
        "the renewal came first: no expiry at 10 000"
    );
    let msgs = all_msgs(&host.advance(30_000));
    assert_eq!(named(&msgs, "trsync_state"), [&[1, 0, 4, 30_000][..]]);
}

/// Klipper's host takes any `trsync_state can_trigger=0` as the trigger of the pass it waits
/// for: after its `trsync_trigger` (end of a homing pass) the MCU must stay silent until the
/// next `trsync_start`, or a stale report ends the next pass early ("No trigger on stepper_z
/// after full movement" when Z's retract was cut short). Before that command, reports go on
/// after an endstop trigger, as on Klipper's MCU.
#[test]
fn host_trsync_trigger_silences_periodic_reports_until_the_next_start() {
    let mut host = homing_host(20);
    host.exchange(&[
        ("trsync_start", &[1, 1000, 500, 4]),
        ("stepper_stop_on_trigger", &[0, 1]),
        ("trsync_set_timeout", &[1, 1_000_000]),
    ]);
    host.exchange(&[("endstop_home", &[2, 1000, 15, 4, 110, 1, 1, 1])]);
    host.exchange(&[
        ("reset_step_clock", &[0, 1000]),
        ("set_next_step_dir", &[0, 1]),
        ("queue_step", &[0, 50, 1000, 0]),
    ]);
    // Reports at 1000, 1500 and 2000 (armed), trigger at 2145, then 2500 and 3000 (triggered).
    let msgs = all_msgs(&host.advance(3_000));
    assert_eq!(
        named(&msgs, "trsync_state"),
        [
            &[1, 1, 0, 1000][..],
            &[1, 1, 0, 1500][..],
            &[1, 1, 0, 2000][..],
            &[1, 0, 1, 2145][..],
            &[1, 0, 1, 2145][..],
            &[1, 0, 1, 2145][..]
        ]
    );
    let msgs = all_msgs(&host.exchange(&[("trsync_trigger", &[1, 2])]));
    assert_eq!(named(&msgs, "trsync_state"), [&[1, 0, 1, 2145][..]]);
    let msgs = all_msgs(&host.advance(50_000));
    assert!(
        named(&msgs, "trsync_state").is_empty(),
        "no report after the host's trsync_trigger: {msgs:?}"
    );
    // Also when the host ends a pass that never triggered (the retract move): one report of
    // the host's reason, then silence.
    host.exchange(&[("trsync_start", &[1, 60_000, 500, 4])]);
    let msgs = all_msgs(&host.advance(60_600));
    assert_eq!(
        named(&msgs, "trsync_state"),
        [&[1, 1, 0, 60_000][..], &[1, 1, 0, 60_500][..]]
    );
    let msgs = all_msgs(&host.exchange(&[("trsync_trigger", &[1, 2])]));
    assert_eq!(named(&msgs, "trsync_state"), [&[1, 0, 2, 60_600][..]]);
    let msgs = all_msgs(&host.advance(100_000));
    assert!(named(&msgs, "trsync_state").is_empty());
    // The next trsync_start reports again.
    host.exchange(&[("trsync_start", &[1, 110_000, 500, 4])]);
    let msgs = all_msgs(&host.advance(110_000));
    assert_eq!(named(&msgs, "trsync_state"), [&[1, 1, 0, 110_000][..]]);
}

/// A periodic report made late carries the clock it was made at, as Klipper's MCU's
/// (`timer_read_time()` in its task): Klipper's host extends the other MCUs' trsync timeouts
/// from that clock, so reporting the due time instead shortened them by the lateness (multi-MCU
/// homing under klippy ended in "Communication timeout during homing" on a loaded machine).
#[test]
fn late_periodic_report_carries_the_clock_it_was_made_at() {
    let mut host = homing_host(1_000_000);
    host.exchange(&[("trsync_start", &[1, 5000, 3000, 4])]);
    host.now = 5_400; // the timer due at 5000 runs 400 ticks late
    host.mcu.run_timers(WireClock(5_400));
    let msgs = all_msgs(&host.take());
    assert_eq!(named(&msgs, "trsync_state"), [&[1, 1, 0, 5_400][..]]);
    // The schedule stays on its period: the next is due at 8000.
    let msgs = all_msgs(&host.advance(8_000));
    assert_eq!(named(&msgs, "trsync_state"), [&[1, 1, 0, 8_000][..]]);
}

#[test]
fn bad_homing_oids_shut_down() {
    let mut host = homing_host(0);
    let msgs = all_msgs(&host.exchange(&[("stepper_stop_on_trigger", &[0, 2])]));
    assert_eq!(
        find(&msgs, "shutdown").unwrap().ints[1],
        host.reason_id("Invalid oid")
    );
    let mut host = homing_host(0);
    let msgs = all_msgs(&host.exchange(&[("endstop_home", &[2, 1000, 15, 4, 110, 1, 0, 1])]));
    assert_eq!(
        find(&msgs, "shutdown").unwrap().ints[1],
        host.reason_id("Invalid oid")
    );
}

#[test]
fn digital_out_schedules_pwm_and_faults() {
    let mut host = Host::new(64, 0);
    host.exchange(&[("allocate_oids", &[1])]);
    host.exchange(&[("config_digital_out", &[0, 12, 0, 0, 0])]);
    host.exchange(&[("finalize_config", &[1])]);
    host.exchange(&[
        ("set_digital_out_pwm_cycle", &[0, 1000]),
        ("queue_digital_out", &[0, 5000, 250]),
        ("queue_digital_out", &[0, 7000, 0]),
    ]);
    host.advance(10_000);
    assert_eq!(
        host.mcu.board().pin_sets,
        [
            (12, false, 0),
            (12, true, 5000),
            (12, false, 5250),
            (12, true, 6000),
            (12, false, 6250),
        ]
    );
    host.exchange(&[("update_digital_out", &[0, 1])]);
    assert_eq!(host.mcu.board().pin_sets.last(), Some(&(12, true, 10_000)));
    let msgs = all_msgs(&host.exchange(&[("queue_digital_out", &[0, 9_000, 1000])]));
    assert_eq!(
        find(&msgs, "shutdown").unwrap().ints[1],
        host.reason_id("Missed scheduling of next digital out event")
    );
    assert_eq!(
        host.mcu.board().pin_sets.last(),
        Some(&(12, false, 10_000)),
        "shutdown sets the default value"
    );
}

#[test]
fn digital_out_max_duration_shuts_down() {
    let mut host = Host::new(64, 0);
    host.exchange(&[("allocate_oids", &[1])]);
    host.exchange(&[("config_digital_out", &[0, 3, 0, 0, 2000])]);
    host.exchange(&[("finalize_config", &[1])]);
    host.exchange(&[("queue_digital_out", &[0, 1000, 1])]);
    let msgs = all_msgs(&host.advance(2_999));
    assert!(find(&msgs, "shutdown").is_none());
    let msgs = all_msgs(&host.advance(3_000));
    assert_eq!(
        find(&msgs, "shutdown").unwrap().ints,
        [
            3_000,
            host.reason_id("Missed scheduling of next digital out event")
        ]
    );
}

#[test]
fn analog_in_reports_sums_and_checks_range() {
    let mut host = Host::new(64, 0);
    host.mcu.board_mut().adc.insert(20, 1000);
    host.exchange(&[("allocate_oids", &[1])]);
    host.exchange(&[("config_analog_in", &[0, 20])]);
    host.exchange(&[("finalize_config", &[1])]);
    host.exchange(&[("query_analog_in", &[0, 1000, 10, 4, 5000, 100, 60_000, 2])]);
    let msgs = all_msgs(&host.advance(10_999));
    assert_eq!(
        named(&msgs, "analog_in_state"),
        [&[0, 6000, 4000][..], &[0, 11_000, 4000][..]]
    );
    host.mcu.board_mut().adc.insert(20, 10); // sum 40 < 100: first bad round reported
    let msgs = all_msgs(&host.advance(16_029));
    assert_eq!(named(&msgs, "analog_in_state"), [&[0, 16_000, 40][..]]);
    let msgs = all_msgs(&host.advance(16_030));
    assert_eq!(
        find(&msgs, "shutdown").unwrap().ints,
        [16_030, host.reason_id("ADC out of range")]
    );
}

#[test]
fn zero_interval_steps_are_simultaneous() {
    let mut host = Host::new(64, 0);
    host.configure(1);
    host.exchange(&[
        ("reset_step_clock", &[0, 1000]),
        ("set_next_step_dir", &[0, 1]),
        ("queue_step", &[0, 100, 1, 0]),
        ("queue_step", &[0, 0, 2, 0]),
        ("queue_step", &[0, 50, 1, 0]),
    ]);
    host.advance(10_000);
    let clocks: Vec<u32> = host.mcu.board().steps.iter().map(|s| s.2).collect();
    assert_eq!(clocks, [1100, 1100, 1100, 1150]);
    assert!(host.mcu.shutdown_reason().is_none());
}

#[test]
fn late_steps_and_timers_shut_down_when_limited() {
    let mut host = Host::with_late_limit(64, 0, 100);
    host.configure(1);
    host.exchange(&[("reset_step_clock", &[0, 1000]), ("queue_step", &[0, 100, 5, 0])]);
    host.now = 1201;
    host.mcu.run_timers(host.wire_now());
    let msgs = all_msgs(&host.take());
    assert_eq!(
        find(&msgs, "shutdown").unwrap().ints,
        [1201, host.reason_id("Stepper too far in past")]
    );
    // A periodic analog timer that cannot keep up.
    let mut host = Host::with_late_limit(64, 0, 100);
    host.exchange(&[("allocate_oids", &[1]), ("config_analog_in", &[0, 20])]);
    host.exchange(&[("query_analog_in", &[0, 1000, 10, 1, 10, 0, 60_000, 0])]);
    host.now = 5000;
    host.mcu.run_timers(host.wire_now());
    let msgs = all_msgs(&host.take());
    assert_eq!(
        find(&msgs, "shutdown").unwrap().ints,
        [5000, host.reason_id("Rescheduled timer in the past")]
    );
}

#[test]
fn lateness_extension_reports_the_board_figures() {
    let mut host = Host::new(64, 0);
    assert!(host.dict["commands"]["cadence_get_lateness"].is_u64());
    let msgs = all_msgs(&host.exchange(&[("cadence_get_lateness", &[])]));
    assert_eq!(named(&msgs, "cadence_lateness"), [&[7, 1, 2, 3, 4][..]]);
}

/// A heater on pin 12 (oid 0, `max_duration` 3 s, PWM cycle 0.1 s) warming the thermistor on
/// ADC pin 20 (oid 1, Klipper's oversampling: 8 readings 1 ms apart every 0.3 s, range of
/// 0..250 °C checked over 4 rounds), both on the simulator's hotend model.
fn heater_host(heater: crate::sim::heater::Heater) -> Host {
    use crate::sim::heater::adc_of;
    let mut host = Host::new(64, 0);
    host.mcu.board_mut().thermal = Some(heater);
    host.exchange(&[("allocate_oids", &[2])]);
    host.exchange(&[
        ("config_digital_out", &[0, 12, 0, 0, 3 * FREQ as i64]),
        ("config_analog_in", &[1, 20]),
    ]);
    host.exchange(&[("finalize_config", &[1])]);
    let (min, max) = (8 * adc_of(250.0) as i64, 8 * adc_of(0.0) as i64);
    host.exchange(&[
        ("set_digital_out_pwm_cycle", &[0, 100_000]),
        ("query_analog_in", &[1, 1000, 1000, 8, 300_000, min, max, 4]),
    ]);
    host
}

/// Plays a host that keeps the heater at `on_ticks` of every 0.1 s cycle, sending an update
/// 0.1 s ahead every 0.3 s until `quiet_at` (µs), then goes silent until `until`. Returns the
/// ADC sums reported and the messages after `quiet_at`.
fn drive_heater(host: &mut Host, on_ticks: i64, quiet_at: u64, until: u64) -> (Vec<i64>, Vec<Resp>) {
    let mut sums = Vec::new();
    let mut t = 0;
    while t < quiet_at {
        let clock = (t + 100_000) as i64;
        let msgs = all_msgs(&host.exchange(&[("queue_digital_out", &[0, clock, on_ticks])]));
        assert!(find(&msgs, "shutdown").is_none(), "{msgs:?}");
        t += 300_000;
        let msgs = all_msgs(&host.advance(t));
        assert!(find(&msgs, "shutdown").is_none(), "at {t}: {msgs:?}");
        sums.extend(named(&msgs, "analog_in_state").iter().map(|a| a[2]));
    }
    (sums, all_msgs(&host.advance(until)))
}

#[test]
fn heater_turns_itself_off_when_the_host_goes_quiet() {
    use crate::sim::heater::{Heater, ThermalModel};
    let mut host = heater_host(Heater::new(12, 20, ThermalModel::HOTEND));
    // 75 % power for 40 s: the thermistor warms (its ADC sum falls) round after round.
    let (sums, after) = drive_heater(&mut host, 75_000, 40_000_000, 50_000_000);
    assert!(sums.len() >= 130, "{}", sums.len());
    assert!(sums.windows(10).all(|w| w[9] < w[0]), "{sums:?}");
    let last_update = 39_900_000 + 100_000; // the update queued at 39.9 s for 40.0 s
    let shutdown = find(&after, "shutdown").expect("the MCU shuts the heater down");
    assert_eq!(
        shutdown.ints,
        [
            last_update + 3_000_000,
            host.reason_id("Missed scheduling of next digital out event")
        ]
    );
    let heater_sets: Vec<_> = host
        .mcu
        .board()
        .pin_sets
        .iter()
        .filter(|s| s.0 == 12)
        .copied()
        .collect();
    assert_eq!(
        heater_sets.last(),
        Some(&(12, false, (last_update + 3_000_000) as u32))
    );
    let board = host.mcu.board_mut();
    let h = board.thermal.as_mut().unwrap();
    let at_off = h.temperature(43.0);
    assert!(at_off > 100.0, "heated to {at_off} °C");
    assert!(h.temperature(100.0) < at_off - 20.0, "cooling once off");
}

#[test]
fn open_thermistor_shuts_the_mcu_down_with_klippers_reason() {
    use crate::sim::heater::{Heater, HeaterFault, ThermalModel};
    let heater = Heater::new(12, 20, ThermalModel::HOTEND).with_fault(HeaterFault::OpenThermistor, 5.0);
    let mut host = heater_host(heater);
    let msgs = all_msgs(&host.exchange(&[("queue_digital_out", &[0, 100_000, 100_000])]));
    assert!(find(&msgs, "shutdown").is_none());
    // Updates keep coming (the host has not noticed): the MCU's own range check stops it.
    let mut t = 0;
    let mut seen = Vec::new();
    while t < 8_000_000 {
        let clock = (t + 100_000) as i64;
        let msgs = all_msgs(&host.exchange(&[("queue_digital_out", &[0, clock, 100_000])]));
        seen.extend(msgs);
        t += 300_000;
        seen.extend(all_msgs(&host.advance(t)));
        if find(&seen, "shutdown").is_some() {
            break;
        }
    }
    // Rounds start at 1000 + k·0.3 s; rounds 17..=20 read the open sensor; the 4th ends at its
    // 8th reading, 7 ms after its start.
    let at = 1000 + 20 * 300_000 + 7000;
    assert_eq!(
        find(&seen, "shutdown").unwrap().ints,
        [at, host.reason_id("ADC out of range")]
    );
    let reports = named(&seen, "analog_in_state");
    assert_eq!(
        reports.last().unwrap()[2],
        8 * 4095,
        "the open sensor's rounds are reported"
    );
    assert_eq!(host.mcu.board().pin_sets.last(), Some(&(12, false, at as u32)));
}

#[test]
fn set_digital_out_sets_a_pin_once() {
    let mut host = Host::new(64, 0);
    host.exchange(&[("set_digital_out", &[7, 1])]);
    assert_eq!(host.mcu.board().pin_sets, [(7, true, 0)]);
}

#[test]
fn queue_past_max_duration_is_refused() {
    let mut host = Host::new(64, 0);
    host.exchange(&[("allocate_oids", &[1])]);
    host.exchange(&[("config_digital_out", &[0, 3, 0, 0, 2000])]);
    host.exchange(&[("finalize_config", &[1])]);
    host.exchange(&[("queue_digital_out", &[0, 1000, 1])]);
    let msgs = all_msgs(&host.exchange(&[("queue_digital_out", &[0, 3001, 0])]));
    assert_eq!(
        find(&msgs, "shutdown").unwrap().ints[1],
        host.reason_id("Scheduled digital out event will exceed max_duration")
    );
}
