"""Cadence's host driving Klipper's Linux-process MCU (see interop.py).

c2k-config: `cadence home` connects to a fresh `klipper.elf` (identify, clock sync, get_config,
the configuration with endstops first, as Klipper's host sends it). Where the machine has no
GPIO (no /dev/gpiochip*), Klipper's MCU shuts down on the first pin it cannot open: Cadence
must say the MCU's reason verbatim and the MCU must stay up (it crashed on a stepper-first
configuration). c2k-shutdown-verbatim: the same against the MCU already shut down.
c2k-home-print: homing and printing on it. Where the machine has no GPIO chip, Klipper's MCU
runs with gpio_sim.c preloaded (built here with the system's C compiler): a simulated GPIO chip
behind which axes follow their step/dir lines and endstops read high at 0 mm. `cadence home`
(two cycles), then `cadence print` of a short G-code — which finds the MCU configured by the
home run and restarts it the way Klipper's FIRMWARE_RESTART does (emergency_stop,
config_reset: Klipper's Linux MCU re-executes itself, and Cadence connects to the new
instance) — and the board's step counts against the G-code.
"""

import glob
import shutil
import struct
import os
import re
import subprocess
import time

from interop import last_line, run, selected, stop

def scenarios(results, args, klipper, bins):
    names = ("c2k-config", "c2k-shutdown-verbatim", "c2k-home-print")
    if not any(selected(args, n) for n in names):
        return
    import batch
    d = os.path.join(args.work, "c2k")
    os.makedirs(d, exist_ok=True)
    link = os.path.join(d, "klipper_host_mcu")
    cfg = os.path.join(d, "printer.cfg")
    with open(cfg, "w") as f:
        f.write("[mcu]\nserial: %s\n" % link + batch.PRINTER_BODY)
    log_path = os.path.join(d, "klipper-mcu.log")
    mcu = subprocess.Popen([klipper.elf, "-I", link], stdout=open(log_path, "w"),
                           stderr=subprocess.STDOUT)
    try:
        for _ in range(100):
            if os.path.exists(link):
                break
            time.sleep(0.05)
        home = [os.path.join(bins, "cadence"), "home", "--config", cfg, "--cycles", "1",
                "--no-realtime"]
        gpio = glob.glob("/dev/gpiochip*")
        first = run(home, timeout=120, check=False)
        alive = mcu.poll() is None
        err = (first.stderr or "").strip().splitlines()
        msg = err[-1] if err else ""
        m = re.search(r"shut down: (.*?) \(the configuration", msg)
        if selected(args, "c2k-config"):
            if first.returncode == 0:
                results.append(("c2k-config", "PASS", "configured and homed: " +
                                first.stdout.strip().splitlines()[-1]))
            elif m and alive:
                results.append(("c2k-config", "PASS",
                                "identify, clock sync, get_config, config (endstops first) "
                                "sent; Klipper's MCU shut down cleanly and stays up; Cadence "
                                "says: %s" % msg))
            else:
                results.append(("c2k-config", "FAIL", "%s; klipper.elf %s" % (
                    msg or "no error text", "running" if alive else
                    "exited with %s" % mcu.returncode)))
        if selected(args, "c2k-shutdown-verbatim") and alive:
            second = run(home, timeout=120, check=False)
            msg2 = (second.stderr or "").strip().splitlines()[-1:] or [""]
            m2 = re.search(r"shut down: (.*?) \(the configuration", msg2[0])
            ok = m is not None and m2 is not None and m2.group(1) == m.group(1)
            results.append(("c2k-shutdown-verbatim", "PASS" if ok else "FAIL",
                            "MCU already shut down: %s" % msg2[0]))
        if selected(args, "c2k-home-print"):
            if first.returncode == 0 or not gpio:
                results.append(home_print(args, klipper, bins, d))
            else:
                results.append(("c2k-home-print", "FAIL", msg))
    finally:
        stop(mcu)


# The c2k-home-print machine: axis, step, dir, enable, endstop line, rotation_distance,
# position_max, homing_speed, steps per mm, where the carriage starts (mm).
AXES = [
    ("x", 0, 1, 2, 3, 40, 200, 20, 80.0, 10.0),
    ("y", 4, 5, 6, 7, 40, 200, 20, 80.0, 10.0),
    ("z", 8, 9, 10, 11, 8, 100, 5, 400.0, 5.0),
]
MOVES = "\n".join([
    "G28", "G90", "G1 X20 Y15 Z2 F3000", "G1 X35.5 Y30.25 F3000", "G91", "G1 X-5 Y5 Z0.5 F1200",
    "G90", "M400", "",
])
# Where MOVES leaves the carriages (G28 puts each at its endstop, 0 mm).
WANT_MM = {"x": 30.5, "y": 35.25, "z": 2.5}


def home_print(args, klipper, bins, d):
    """c2k-home-print on Klipper's Linux MCU with the simulated GPIO chip."""
    name = "c2k-home-print"
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        return (name, "BLOCKED", "this machine has no GPIO chip and no C compiler to build "
                "gpio_sim.c (the simulated chip Klipper's Linux MCU would run on)")
    shim = os.path.join(d, "gpio_sim.so")
    run([cc, "-O2", "-Wall", "-shared", "-fPIC", "-o", shim,
         os.path.join(os.path.dirname(os.path.abspath(__file__)), "gpio_sim.c"), "-ldl"])
    link = os.path.join(d, "klipper_gpio_sim_mcu")
    cfg = os.path.join(d, "gpio-sim-printer.cfg")
    lines = ["[mcu]", "serial: %s" % link, "", "[printer]", "kinematics: cartesian",
             "max_velocity: 100", "max_accel: 1000", "max_z_velocity: 5", "max_z_accel: 100", ""]
    for axis, step, dirp, en, endstop, rot, pmax, speed, _spm, _start in AXES:
        lines += ["[stepper_%s]" % axis, "step_pin: gpio%d" % step, "dir_pin: gpio%d" % dirp,
                  "enable_pin: !gpio%d" % en, "microsteps: 16", "rotation_distance: %s" % rot,
                  "endstop_pin: ^gpio%d" % endstop, "position_endstop: 0",
                  "position_max: %d" % pmax, "homing_speed: %d" % speed, ""]
    with open(cfg, "w") as f:
        f.write("\n".join(lines) + "\n")
    gcode = os.path.join(d, "gpio-sim-moves.gcode")
    with open(gcode, "w") as f:
        f.write(MOVES)
    # On a tmpfs: the MCU writes it at every step, and a page of a file on a disk filesystem
    # can block that write while the kernel flushes it (here: "Stepper too far in past").
    shm = "/dev/shm" if os.path.isdir("/dev/shm") else d
    counts = os.path.join(shm, "cadence-gpio-sim-%d.bin" % os.getpid())
    if os.path.exists(counts):
        os.remove(counts)
    env = dict(os.environ, LD_PRELOAD=shim, CADENCE_GPIO_SIM_OUT=counts,
               CADENCE_GPIO_SIM_AXES=";".join(
                   "%s=%d,%d,%d,%s,%s" % (a, st, di, es, spm, start)
                   for a, st, di, _en, es, _r, _p, _s, spm, start in AXES))
    def fail(msg):
        if os.path.exists(counts):
            os.remove(counts)
        return (name, "FAIL", msg)
    log_path = os.path.join(d, "klipper-mcu-gpio-sim.log")
    # -r: SCHED_FIFO and mlockall, as Klipper's install runs its Linux MCU.
    mcu = subprocess.Popen([klipper.elf, "-r", "-I", link], env=env,
                           stdout=open(log_path, "w"), stderr=subprocess.STDOUT)
    t0 = time.monotonic()
    try:
        for _ in range(100):
            if os.path.exists(link):
                break
            time.sleep(0.05)
        cadence = os.path.join(bins, "cadence")
        home = run([cadence, "home", "--config", cfg, "--cycles", str(max(1, args.cycles))],
                   timeout=600, check=False)
        if home.returncode != 0:
            # Klipper's Linux MCU shuts down when it runs a step over 1 ms late: the machine's
            # own wake-up latency (measured by `cadence home` meanwhile) says whether this
            # machine could give it that.
            jitter = [l.strip() for l in home.stdout.splitlines() if "wake-up latency" in l]
            return fail("cadence home: %s%s" % (
                last_line(home), "; " + jitter[0] if jitter else ""))
        cycles = [l for l in home.stdout.splitlines() if l.startswith("homing: ")]
        printed = run([cadence, "print", gcode, "--config", cfg], timeout=900, check=False)
        out = (printed.stdout + printed.stderr)
        m = re.search(r"final position matches the MCU's step count on all (\d+) stepper", out)
        if printed.returncode != 0 or not m:
            return fail("cadence print: %s" % last_line(printed))
        restarted = [l for l in printed.stderr.splitlines() if "restarting it" in l]
    finally:
        stop(mcu)
    with open(counts, "rb") as f:
        got = struct.unpack("<9q", f.read(72))
    os.remove(counts)
    rows = []
    for i, (axis, *_rest, spm, start) in enumerate(AXES):
        at = start + got[i] / spm
        rows.append("%s %.4f/%.4f mm" % (axis, at, WANT_MM[axis]))
        if abs(at - WANT_MM[axis]) > 2.0 / spm + 1e-9:  # a step of sampling either way
            return (name, "FAIL", "board position differs (board/G-code): " + ", ".join(rows))
    return (name, "PASS",
            "Klipper's Linux MCU on gpio_sim.c (a simulated GPIO chip: %d line writes); "
            "cadence home: %s; cadence print (%s): %s; board = G-code: %s (%.1f s)" % (
                got[len(AXES)], cycles[-1] if cycles else "ok",
                "MCU restarted with emergency_stop + config_reset, reconnected"
                if restarted else "no restart", m.group(0), ", ".join(rows),
                time.monotonic() - t0))

