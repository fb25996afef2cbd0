"""Klipper's host driving simulated TMC drivers on cadence-mcu (see interop.py).

The printer.cfg is the harness's cartesian printer with a TMC2209 on stepper_x (UART on PA9,
bit-banged by the MCU with Klipper's tmcuart commands; DIAG on PB5) homing sensorlessly
(`endstop_pin: tmc2209_stepper_x:virtual_endstop`) and a TMC5160 on stepper_y (hardware SPI,
`spi_bus: spi1`, chip select PA4). cadence-mcu simulates both chips (`--tmc
tmc2209@PA9:0=PB5,x,0,min --tmc tmc5160@PA4:0`): their register files, the TMC2209's IFCNT,
and the DIAG output when the X carriage reaches its end with stallGuard routed to it.

k2c-tmc   klippy initialises both drivers (it checks every UART write by IFCNT and reads GSTAT
          and DRV_STATUS periodically), DUMP_TMC of each, SET_TMC_CURRENT read back from the
          driver's status, G28 X homing on the TMC2209's stallGuard (3 times), G28 Y on the
          endstop; no shutdown, no TMC error in klippy's log.
"""

import re

from interop import Fail, Rig, run_scenarios


def scenarios(results, args, klipper, bins):
    run_scenarios(results, args, klipper, bins, [("k2c-tmc", drivers)])


def edit_cfg(text):
    """stepper_x homes on the TMC2209's virtual endstop; the two driver sections."""
    x = text.index("[stepper_x]")
    end = text.index("\n\n", x)
    section = re.sub(r"endstop_pin: .*", "endstop_pin: tmc2209_stepper_x:virtual_endstop",
                     text[x:end]) + "\nhoming_retract_dist: 0"
    text = text[:x] + section + text[end:]
    return text + "\n".join([
        "[tmc2209 stepper_x]", "uart_pin: PA9", "diag_pin: ^PB5", "run_current: 0.8",
        "driver_SGTHRS: 100", "",
        "[tmc5160 stepper_y]", "cs_pin: PA4", "spi_bus: spi1", "run_current: 0.9",
        "sense_resistor: 0.075", "stealthchop_threshold: 0", "",
    ]) + "\n"


def dump(rig, stepper):
    """DUMP_TMC's lines for `stepper`, from klippy's log (klippy logs every response)."""
    before = len(rig.klippy_log())
    rig.api.gcode("DUMP_TMC STEPPER=%s" % stepper)
    return rig.klippy_log()[before:]


def drivers(args, klipper, bins):
    rig = Rig("tmc", args, klipper, bins, cfg_edit=edit_cfg,
              mcu_extra=["--tmc", "tmc2209@PA9:0=PB5,x,0,min", "--tmc", "tmc5160@PA4:0"])
    try:
        rig.start()
        x_dump = dump(rig, "stepper_x")
        y_dump = dump(rig, "stepper_y")
        for name, text, want in (("stepper_x", x_dump, ["IFCNT", "GCONF", "SGTHRS"]),
                                 ("stepper_y", y_dump, ["GCONF", "CHOPCONF", "IHOLD_IRUN"])):
            missing = [w for w in want if w not in text]
            if missing:
                raise Fail("DUMP_TMC STEPPER=%s lacks %s: %r" % (name, missing, text[-600:]))
        sgthrs = re.search(r"sgthrs=(\d+)", x_dump)
        ifcnt = re.search(r"ifcnt=(\d+)", x_dump)
        rig.api.gcode("SET_TMC_CURRENT STEPPER=stepper_y CURRENT=0.5")
        status = rig.api.query({"tmc5160 stepper_y": ["run_current"],
                                "tmc2209 stepper_x": ["run_current", "drv_status"]})
        y_current = status["tmc5160 stepper_y"]["run_current"]
        if abs(y_current - 0.5) > 0.05:
            raise Fail("SET_TMC_CURRENT CURRENT=0.5: stepper_y run_current %s" % y_current)
        for _ in range(3):
            rig.api.gcode("G28 X")
        rig.api.gcode("G28 Y")
        homed = rig.api.query({"toolhead": ["homed_axes"]})["toolhead"]["homed_axes"]
        if "x" not in homed or "y" not in homed:
            raise Fail("after G28 X (sensorless) and G28 Y: homed axes %r" % homed)
        rig.check_no_shutdown()
        log = rig.klippy_log()
        errors = [l for l in log.splitlines() if re.search(r"(?i)tmc.*(error|unable)", l)]
        if errors:
            raise Fail("klippy logged TMC errors: %s" % errors[:3])
        return ("TMC2209 (UART) and TMC5160 (spi1) initialised by klippy; DUMP_TMC of both "
                "(stepper_x sgthrs=%s ifcnt=%s); SET_TMC_CURRENT 0.5 A read back %.3f A; "
                "3 x G28 X on stallGuard, G28 Y; homed %s; no shutdown, no TMC error" % (
                    sgthrs.group(1) if sgthrs else "?", ifcnt.group(1) if ifcnt else "?",
                    y_current, homed))
    finally:
        rig.stop()
