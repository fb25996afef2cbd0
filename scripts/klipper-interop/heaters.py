"""Klipper's host driving the heaters and the fan of a simulated board (see interop.py).

The printer.cfg the harness writes has an [extruder] heater (PE0) with a "Generic 3950"
thermistor (PF0, PID), a [heater_bed] (PE1 / PF1, watermark) and a [fan] (PE2); cadence-mcu
simulates a 40 W hotend and a 150 W bed behind those pins (`--heater PE0=PF0,hotend --heater
PE1=PF1,bed`), so klippy's thermistor readings follow its own heater commands.

k2c-heaters            M104/M140, then M109/M190 wait until klippy reads the targets; M106 sets
                       the fan (klippy's fan status), M107 stops it; TURN_OFF_HEATERS; no
                       shutdown. verify_heater runs all the while (klippy loads it for every
                       heater) and must stay quiet.
k2c-verify-heater      the hotend's heater stops heating in the simulator (`--heater-fault
                       PE0=no-heat@0`): M104 S200, and klippy's verify_heater must shut the
                       printer down with its own message ("not heating at expected rate").
k2c-thermistor-fault   the hotend's thermistor goes open in the simulator (`--heater-fault
                       PE0=open@T`): the MCU's ADC range check fires and klippy shuts down with
                       its message for it ("ADC out of range" and its min_temp/max_temp help).
k2c-thermocouple       the hotend's sensor is a MAX31855 on hardware SPI (`spi_bus: spi1`, chip
                       select PA4; cadence-mcu `--spi-sensor PA4=MAX31855` answers with the
                       simulated hotend's temperature): klippy configures it with its SPI and
                       thermocouple commands, M109 S150 waits until klippy reads the target, no
                       shutdown.
k2c-thermocouple-fault the MAX31855's thermocouple goes open (`--heater-fault PE0=open@T`): the
                       MCU sees the chip's fault bit and klippy shuts down with "Thermocouple
                       reader fault".
"""

import time

from interop import Fail, Rig, run_scenarios

HOTEND_TARGET = 150
BED_TARGET = 45


def scenarios(results, args, klipper, bins):
    run_scenarios(results, args, klipper, bins, [
        ("k2c-heaters", heaters_reach_targets),
        ("k2c-verify-heater", verify_heater_fault),
        ("k2c-thermistor-fault", thermistor_fault),
        ("k2c-thermocouple", thermocouple_heats),
        ("k2c-thermocouple-fault", thermocouple_fault),
    ])


def temperatures(rig):
    st = rig.api.query({"extruder": ["temperature", "target", "power"],
                        "heater_bed": ["temperature", "target", "power"],
                        "fan": ["speed"]})
    return st


def heaters_reach_targets(args, klipper, bins):
    rig = Rig("heat", args, klipper, bins)
    try:
        rig.start()
        start = temperatures(rig)
        for _ in range(20):  # the first readings come a moment after ready
            if start["extruder"]["temperature"] > 0 and start["heater_bed"]["temperature"] > 0:
                break
            time.sleep(0.5)
            start = temperatures(rig)
        rig.api.gcode("M140 S%d\nM104 S%d" % (BED_TARGET, HOTEND_TARGET))
        t0 = time.monotonic()
        rig.api.gcode("M109 S%d" % HOTEND_TARGET, timeout=900.0)
        t_hotend = time.monotonic() - t0
        rig.api.gcode("M190 S%d" % BED_TARGET, timeout=900.0)
        t_bed = time.monotonic() - t0
        hot = temperatures(rig)
        e, b = hot["extruder"], hot["heater_bed"]
        if abs(e["temperature"] - HOTEND_TARGET) > 5 or b["temperature"] < BED_TARGET - 1:
            raise Fail("after M109/M190: extruder %.1f (target %d), bed %.1f (target %d)" % (
                e["temperature"], HOTEND_TARGET, b["temperature"], BED_TARGET))
        # Held at the target for a while (PID on the hotend, bang-bang on the bed).
        time.sleep(10.0)
        held = temperatures(rig)
        if abs(held["extruder"]["temperature"] - HOTEND_TARGET) > 5:
            raise Fail("extruder drifted to %.1f after reaching %d" % (
                held["extruder"]["temperature"], HOTEND_TARGET))
        rig.api.gcode("M106 S128")
        fan_half = temperatures(rig)["fan"]["speed"]
        rig.api.gcode("M106 S255")
        fan_full = temperatures(rig)["fan"]["speed"]
        rig.api.gcode("M107")
        fan_off = temperatures(rig)["fan"]["speed"]
        if abs(fan_half - 128 / 255) > 0.01 or fan_full != 1.0 or fan_off != 0.0:
            raise Fail("fan speeds after M106 S128 / S255 / M107: %s / %s / %s" % (
                fan_half, fan_full, fan_off))
        rig.api.gcode("TURN_OFF_HEATERS")
        rig.check_no_shutdown()
        return ("extruder %.1f -> %.1f C (M109 S%d done after %.0f s, %.1f C 10 s later), "
                "bed %.1f -> %.1f C (M190 S%d done after %.0f s); fan 0.50/1.00/0 after "
                "M106 S128/S255/M107; verify_heater quiet; no shutdown" % (
                    start["extruder"]["temperature"], e["temperature"], HOTEND_TARGET,
                    t_hotend, held["extruder"]["temperature"],
                    start["heater_bed"]["temperature"], b["temperature"], BED_TARGET, t_bed))
    finally:
        rig.stop()


def wait_shutdown(rig, timeout):
    """klippy's state message once it is in shutdown (Fail if it is not within timeout)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        info = rig.api.call("info", timeout=10.0).get("result", {})
        if info.get("state") == "shutdown":
            return info.get("state_message", "")
        time.sleep(1.0)
    raise Fail("klippy still %s after %d s" % (rig.api.state(), timeout))


def verify_heater_fault(args, klipper, bins):
    rig = Rig("verify-heater", args, klipper, bins,
              mcu_extra=["--heater-fault", "PE0=no-heat@0"])
    try:
        rig.start()
        t0 = time.monotonic()
        rig.api.gcode("M104 S200")
        msg = wait_shutdown(rig, 180.0)
        first = msg.strip().splitlines()[0] if msg.strip() else ""
        if "Heater extruder not heating at expected rate" not in msg:
            raise Fail("klippy shut down, but not by verify_heater: %r" % msg)
        temp = rig.api.query({"extruder": ["temperature"]})["extruder"]["temperature"]
        return ("heater dead in the simulator; M104 S200; klippy shut down after %.0f s "
                "at %.1f C: \"%s\"" % (time.monotonic() - t0, temp, first))
    finally:
        rig.stop()


def open_sensor_shutdown(rig, fault_at, want, what):
    """Heats with M104 S100 until the sensor opened at `fault_at` s of MCU time shuts klippy
    down: its message's lines, which must contain every string of `want`."""
    try:
        rig.start()
        rig.api.gcode("M104 S100")
        msg = wait_shutdown(rig, 120.0)
        if not all(w in msg for w in want):
            raise Fail("klippy shut down, but not for the open %s: %r" % (what, msg))
        return [l.strip() for l in msg.strip().splitlines() if l.strip()]
    finally:
        rig.stop()


def thermistor_fault(args, klipper, bins):
    fault_at = 20
    rig = Rig("thermistor", args, klipper, bins,
              mcu_extra=["--heater-fault", "PE0=open@%d" % fault_at])
    lines = open_sensor_shutdown(rig, fault_at, ["MCU 'mcu' shutdown: ADC out of range",
                                                 "min_temp"], "thermistor")
    return ("thermistor open at %d s of MCU time (M104 S100 heating): klippy: \"%s\" "
            "(\"%s\")" % (fault_at, lines[0], " ".join(lines[1:3])))


# The hotend's sensor as a MAX31855 on hardware SPI (written here for Cadence).
THERMOCOUPLE = ["sensor_type: MAX31855", "sensor_pin: PA4", "spi_bus: spi1"]


def thermocouple_rig(name, args, klipper, bins, extra=()):
    return Rig(name, args, klipper, bins, hotend_sensor=THERMOCOUPLE, hotend_sensor_pin="PA4",
               mcu_extra=["--spi-sensor", "PA4=MAX31855"] + list(extra))


def thermocouple_heats(args, klipper, bins):
    rig = thermocouple_rig("thermocouple", args, klipper, bins)
    try:
        rig.start()
        start = temperatures(rig)["extruder"]["temperature"]
        for _ in range(20):  # the first reading comes a moment after ready
            if start > 0:
                break
            time.sleep(0.5)
            start = temperatures(rig)["extruder"]["temperature"]
        t0 = time.monotonic()
        rig.api.gcode("M109 S%d" % HOTEND_TARGET, timeout=900.0)
        t_hot = time.monotonic() - t0
        hot = temperatures(rig)["extruder"]["temperature"]
        if abs(hot - HOTEND_TARGET) > 5:
            raise Fail("after M109 S%d the MAX31855 reads %.1f" % (HOTEND_TARGET, hot))
        rig.api.gcode("TURN_OFF_HEATERS")
        rig.check_no_shutdown()
        return ("MAX31855 on spi1: extruder %.2f -> %.2f C (M109 S%d done after %.0f s); "
                "no shutdown" % (start, hot, HOTEND_TARGET, t_hot))
    finally:
        rig.stop()


def thermocouple_fault(args, klipper, bins):
    fault_at = 20
    rig = thermocouple_rig("thermocouple-fault", args, klipper, bins,
                           extra=["--heater-fault", "PE0=open@%d" % fault_at])
    lines = open_sensor_shutdown(rig, fault_at, ["Thermocouple reader fault"], "thermocouple")
    return ("MAX31855 open at %d s of MCU time (M104 S100 heating): klippy: \"%s\"" % (
        fault_at, lines[0]))
