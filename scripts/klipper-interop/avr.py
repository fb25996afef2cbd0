"""Cadence's host driving Klipper's AVR build under simulavr (see interop.py).

c2k-avr-home-print: the Klipper tree is built for an ATmega644p with Klipper's "simulavr
software emulation" option (the route of Klipper's docs/Debugging.md; Klipper offers that option
for the 168/328/644p/1284p only, and simulavr has no ATmega2560 model), run in simulavr by
avr_board.py (its UART on a pty, axes that follow the step/dir pins, endstops at 0), and
Cadence's host homes it (`cadence home`) and prints a short G-code file on it (`cadence print`,
which reads every stepper's position back from the MCU with stepper_get_position); the board's
own step counts must equal what Cadence commanded. Needs `avr-gcc`/`avr-libc` and a simulavr
build with its Python module (--simulavr DIR: a simulavr tree built with `--enable-python`).
"""

import json
import os
import re
import shutil
import subprocess
import time

from interop import Blocked, Fail, last_line, log, run, selected, stop

NAME = "c2k-avr-home-print"
STEPS_PER_MM = {"x": 80.0, "y": 80.0, "z": 400.0}
AXES = [
    # axis, step, dir, enable, endstop, rotation_distance, max, homing_speed
    ("x", "PA5", "PA4", "PC0", "PB0", 40, 200, 20),
    ("y", "PA3", "PA2", "PC1", "PB1", 40, 200, 20),
    ("z", "PC7", "PC6", "PC2", "PB2", 8, 100, 5),
]
START_MM = {"x": 10.0, "y": 10.0, "z": 5.0}
GCODE = "\n".join([
    "G28", "G90", "G1 X20 Y15 Z2 F3000", "G1 X35.5 Y30.25 F3000", "G91", "G1 X-5 Y5 Z0.5 F1200",
    "G90", "M400", "",
])


def pysimulavr_dir(simulavr):
    for sub in ("src/python", "build/pysimulavr", "src/python/build"):
        d = os.path.join(simulavr, sub)
        if any(f.startswith("_pysimulavr") and f.endswith(".so")
               for f in (os.listdir(d) if os.path.isdir(d) else [])):
            return d
    return None


def build_avr(klipper, work, freq):
    d = os.path.join(work, "klipper-avr-%d" % freq)
    elf = os.path.join(d, "out", "klipper.elf")
    if os.path.exists(elf):
        return d
    if shutil.which("avr-gcc") is None:
        raise Blocked("no avr-gcc (Debian: gcc-avr avr-libc)")
    shutil.rmtree(d, ignore_errors=True)
    shutil.copytree(klipper.src, d, symlinks=True,
                    ignore=shutil.ignore_patterns("out", ".config*", "*.pyc"))
    with open(os.path.join(d, ".config"), "w") as f:
        f.write("CONFIG_LOW_LEVEL_OPTIONS=y\nCONFIG_MACH_AVR=y\nCONFIG_MACH_atmega644p=y\n"
                "CONFIG_AVR_FREQ_%d=y\nCONFIG_SIMULAVR=y\n" % freq)
    log("klipper: building the ATmega644p (simulavr) MCU at %d Hz" % freq)
    run(["make", "olddefconfig"], cwd=d)
    run(["make", "-j2"], cwd=d, timeout=1800)
    return d


def printer_cfg(path, pty):
    lines = ["[mcu]", "serial: %s" % pty, "baud: 250000", "",
             "[printer]", "kinematics: cartesian", "max_velocity: 100", "max_accel: 1000",
             "max_z_velocity: 5", "max_z_accel: 100", ""]
    for axis, step, dirp, en, endstop, rot, pmax, speed in AXES:
        lines += ["[stepper_%s]" % axis, "step_pin: %s" % step, "dir_pin: %s" % dirp,
                  "enable_pin: !%s" % en, "microsteps: 16", "rotation_distance: %s" % rot,
                  "endstop_pin: ^%s" % endstop, "position_endstop: 0",
                  "position_max: %d" % pmax, "homing_speed: %d" % speed, ""]
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def scenarios(results, args, klipper, bins):
    if not selected(args, NAME):
        return
    t0 = time.monotonic()
    try:
        results.append((NAME, "PASS", "%s (%.1f s)" % (home_print(args, klipper, bins),
                                                          time.monotonic() - t0)))
    except Blocked as e:
        results.append((NAME, "BLOCKED", str(e)))
    except (Fail, OSError, subprocess.SubprocessError, ValueError, KeyError) as e:
        results.append((NAME, "FAIL", str(e)))


def home_print(args, klipper, bins):
    if not args.simulavr:
        raise Blocked("no --simulavr DIR (a simulavr tree built with its Python module)")
    pydir = pysimulavr_dir(args.simulavr)
    if pydir is None:
        raise Blocked("no _pysimulavr*.so under %s (build simulavr with --enable-python)"
                      % args.simulavr)
    avr = build_avr(klipper, args.work, args.avr_freq)
    d = os.path.join(args.work, "c2k-avr")
    shutil.rmtree(d, ignore_errors=True)
    os.makedirs(d)
    pty = os.path.join(d, "avr.pty")
    cfg = os.path.join(d, "printer.cfg")
    printer_cfg(cfg, pty)
    gcode = os.path.join(d, "moves.gcode")
    with open(gcode, "w") as f:
        f.write(GCODE)
    positions = os.path.join(d, "board-positions.json")
    env = dict(os.environ, PYTHONPATH=pydir)
    libsim = os.path.join(args.simulavr, "src", ".libs", "libsim.so")
    if os.path.exists(libsim):
        # The autotools tree's Python module leaves rwmem.o out of its link (undefined
        # RWMemoryMember): the simulator library itself supplies it.
        env["LD_PRELOAD"] = libsim
    board_cmd = [klipper.python, os.path.join(os.path.dirname(__file__), "avr_board.py"),
                 os.path.join(avr, "out", "klipper.elf"), "--pty", pty,
                 "--speed", str(args.avr_freq),
                 "--positions", positions]
    for axis, step, dirp, _en, endstop, _rot, _pmax, _speed in AXES:
        board_cmd += ["--axis", "%s=%s,%s,%s,%s,%s" % (axis, step, dirp, endstop,
                                                        STEPS_PER_MM[axis], START_MM[axis])]
    board_log = open(os.path.join(d, "avr_board.log"), "w")
    board = subprocess.Popen(board_cmd, env=env, stdout=board_log, stderr=subprocess.STDOUT)
    try:
        for _ in range(200):
            if os.path.exists(pty) or board.poll() is not None:
                break
            time.sleep(0.1)
        if not os.path.exists(pty):
            raise Fail("avr_board.py did not start: %s" % open(board_log.name).read()[-500:])
        error = None
        home = run([os.path.join(bins, "cadence"), "home", "--config", cfg, "--cycles", "1",
                    "--no-realtime"], timeout=600, check=False)
        if home.returncode != 0:
            error = "cadence home: %s" % last_line(home)
        else:
            printed = run([os.path.join(bins, "cadence"), "print", gcode, "--config", cfg,
                           "--no-realtime"], timeout=900, check=False)
            out = (printed.stdout + printed.stderr).strip()
            m = re.search(r"final position matches the MCU's step count on all (\d+) stepper",
                          out)
            if printed.returncode != 0 or not m:
                error = "cadence print: %s" % last_line(printed)
    finally:
        stop(board, 30)
    with open(positions) as f:
        got = json.load(f)
    pace = got["sim_s"] / got["wall_s"] if got.get("wall_s") else 0.0
    if error and pace < 0.95:
        raise Blocked(
            "simulavr ran the ATmega644p at %d MHz at %.0f %% of real time here (%.1f s "
            "simulated in %.1f s; a 2-core VM shared with other builds), and a live host needs "
            "the MCU clock to keep up with its own; the live session ended: %s" % (
                args.avr_freq // 1000000, 100 * pace, got["sim_s"], got["wall_s"], error))
    if error:
        raise Fail(error)
    # After G28 (each axis at 0 = its endstop, plus the overshoot Cadence accounts for) and the
    # moves: the board's axes must be where the G-code left them.
    want = {"x": 30.5, "y": 35.25, "z": 2.5}
    rows = []
    for axis, mm in want.items():
        at = START_MM[axis] + got["axes"][axis] / STEPS_PER_MM[axis]
        rows.append("%s %.4f/%.4f mm" % (axis, at, mm))
        if abs(at - mm) > 2.0 / STEPS_PER_MM[axis] + 1e-9:  # a step of sampling either way
            raise Fail("board position differs (board/G-code): " + ", ".join(rows))
    return ("Klipper ATmega644p build in simulavr (%.0f s simulated, up to %.2f s behind real "
            "time); cadence home + print: %s; board = G-code: %s" % (
                got["sim_s"], got["max_behind_s"] or 0, m.group(0), ", ".join(rows)))
