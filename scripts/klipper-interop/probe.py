"""Klipper's host probing a simulated warped bed with a BLTouch on cadence-mcu (see interop.py).

The printer.cfg is the harness's cartesian printer with a `[bltouch]` (sensor PB6, servo PB7)
as Z's endstop (`probe:z_virtual_endstop`), `[safe_z_home]` at the bed's centre and a 4 x 4
`[bed_mesh]`. cadence-mcu simulates the BLTouch (deployed and stowed by klippy's servo pulses,
its pin touching the bed, `--bltouch PB6=PB7,z,0`) over a tilted, warped bed (`--bed-surface`:
h(x, y) = tilt_x·x + tilt_y·y + warp·sin(2πx/period)·sin(2πy/period)).

k2c-bltouch-mesh   G28 (X, Y, then Z on the BLTouch at the centre), BED_MESH_CALIBRATE, and
                   klippy's probed matrix against the surface's truth relative to the homing
                   point (within 0.02 mm at every probed point); no shutdown.
"""

import math
import re

from interop import Fail, Rig, run_scenarios

HOME_XY = (110.0, 110.0)
MESH_MIN, MESH_MAX, COUNT = 30.0, 190.0, 4
TILT = (0.001, -0.0006)
WARP, PERIOD = 0.06, 200.0


def height(x, y):
    k = 2 * math.pi / PERIOD
    return TILT[0] * x + TILT[1] * y + WARP * math.sin(k * x) * math.sin(k * y)


def scenarios(results, args, klipper, bins):
    run_scenarios(results, args, klipper, bins, [("k2c-bltouch-mesh", bltouch_mesh)])


def edit_cfg(text):
    """Z homes on the BLTouch; the probe, safe_z_home and bed_mesh sections."""
    z = text.index("[stepper_z]")
    end = text.index("\n\n", z)
    section = re.sub(r"endstop_pin: .*", "endstop_pin: probe:z_virtual_endstop", text[z:end])
    section = re.sub(r"position_endstop: .*\n", "", section) + "\nposition_min: -5"
    text = text[:z] + section + text[end:]
    return text + "\n".join([
        "[bltouch]", "sensor_pin: ^PB6", "control_pin: PB7", "z_offset: 2.0", "speed: 5",
        "",
        "[safe_z_home]", "home_xy_position: %g, %g" % HOME_XY, "z_hop: 5", "z_hop_speed: 10",
        "",
        "[bed_mesh]", "speed: 100", "horizontal_move_z: 5",
        "mesh_min: %g, %g" % (MESH_MIN, MESH_MIN), "mesh_max: %g, %g" % (MESH_MAX, MESH_MAX),
        "probe_count: %d, %d" % (COUNT, COUNT), "",
    ]) + "\n"


def bltouch_mesh(args, klipper, bins):
    surface = "PB6=x,y,0,0,%g,%g,%g,%g" % (TILT[0], TILT[1], WARP, PERIOD)
    rig = Rig("bltouch-mesh", args, klipper, bins, cfg_edit=edit_cfg,
              mcu_extra=["--bltouch", "PB6=PB7,z,0", "--bed-surface", surface])
    try:
        rig.start()
        rig.api.gcode("G28", timeout=300.0)
        rig.api.gcode("BED_MESH_CALIBRATE", timeout=600.0)
        mesh = rig.api.query({"bed_mesh": ["probed_matrix", "mesh_min", "mesh_max"]})["bed_mesh"]
        matrix = mesh["probed_matrix"]
        if len(matrix) != COUNT or any(len(row) != COUNT for row in matrix):
            raise Fail("probed matrix is not %d x %d: %r" % (COUNT, COUNT, matrix))
        step = (MESH_MAX - MESH_MIN) / (COUNT - 1)
        worst = 0.0
        for j, row in enumerate(matrix):  # rows along Y, columns along X
            for i, z in enumerate(row):
                x, y = MESH_MIN + i * step, MESH_MIN + j * step
                truth = height(x, y) - height(*HOME_XY)
                worst = max(worst, abs(z - truth))
        if worst > 0.02:
            raise Fail("probed matrix off the true surface by %.4f mm: %r" % (worst, matrix))
        rig.check_no_shutdown()
        spread = max(map(max, matrix)) - min(map(min, matrix))
        return ("G28 on the BLTouch, BED_MESH_CALIBRATE %dx%d: probed points within %.4f mm "
                "of the true surface (its range over the points %.3f mm); no shutdown" % (
                    COUNT, COUNT, worst, spread))
    finally:
        rig.stop()
