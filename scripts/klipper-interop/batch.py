"""Batch-mode and Cadence-host scenarios of the harness (see interop.py).

batch-*: one printer (written here, on the Linux MCU's gpioN/analogN pins so that both hosts
encode with Klipper's own out/klipper.dict) and one G-code file, through klippy's batch mode
(`-o`, with a [homing_override] that only sets the position, as Cadence's batch G28 moves
nothing) and `cadence print --batch --dictionary out/klipper.dict`; each stream decoded by
Klipper's parsedump.py and by `cadence decode`.
"""

import os
import re
import subprocess
import time

from interop import Blocked, Fail, run, selected, log  # noqa: F401

PRINTER_BODY = """
[printer]
kinematics: cartesian
max_velocity: 300
max_accel: 3000
max_z_velocity: 15
max_z_accel: 100
square_corner_velocity: 5

[stepper_x]
step_pin: gpio0
dir_pin: gpio1
enable_pin: !gpio2
microsteps: 16
rotation_distance: 40
endstop_pin: ^gpio3
position_endstop: 0
position_max: 220

[stepper_y]
step_pin: gpio4
dir_pin: gpio5
enable_pin: !gpio6
microsteps: 16
rotation_distance: 40
endstop_pin: ^gpio7
position_endstop: 0
position_max: 220

[stepper_z]
step_pin: gpio8
dir_pin: gpio9
enable_pin: !gpio10
microsteps: 16
rotation_distance: 8
endstop_pin: ^gpio11
position_endstop: 0
position_max: 200

[extruder]
step_pin: gpio12
dir_pin: gpio13
enable_pin: !gpio14
microsteps: 16
rotation_distance: 33.5
nozzle_diameter: 0.4
filament_diameter: 1.75
max_extrude_only_distance: 500
max_extrude_cross_section: 50
heater_pin: gpio15
sensor_type: Generic 3950
sensor_pin: analog0
control: pid
pid_Kp: 22.2
pid_Ki: 1.08
pid_Kd: 114
min_temp: 0
max_temp: 300
min_extrude_temp: 0

[heater_bed]
heater_pin: gpio16
sensor_type: Generic 3950
sensor_pin: analog1
control: watermark
min_temp: 0
max_temp: 130
"""

STEP_PINS = {"gpio0": "stepper_x", "gpio4": "stepper_y", "gpio8": "stepper_z",
             "gpio12": "extruder"}

KLIPPER_EXTRA = """
[homing_override]
gcode: SET_KINEMATIC_POSITION X=0 Y=0 Z=0

[force_move]
enable_force_move: True

[gcode_macro PRINT_START]
gcode:
  G28

[gcode_macro PRINT_END]
gcode:
  M400
"""


def parse_decoded(text):
    """[(name, {field: int})] from decoder output (one message per line)."""
    msgs = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        fields = {}
        for p in parts[1:]:
            if "=" in p:
                k, v = p.split("=", 1)
                try:
                    fields[k] = int(v)
                except ValueError:
                    fields[k] = v
        msgs.append((parts[0], fields))
    return msgs


def batch_compare(results, args, klipper, bins, gcode, ccfg, kbin, ks):
    """batch-compare: `cadence bench plan FILE --compare KLIPPER_STREAM` plans the file and
    prints Klipper's step commands beside its own; its count of Klipper's steps per stepper must
    be the one replayed from parsedump's decoding (`ks`)."""
    import json
    p = run([os.path.join(bins, "cadence"), "bench", "plan", gcode, "--config", ccfg,
             "--dictionary", klipper.dict, "--compare", kbin, "--json"], timeout=3600,
            check=False)
    if p.returncode != 0:
        results.append(("batch-compare", "FAIL", (p.stderr or p.stdout).strip()[-400:]))
        return
    f = json.loads(p.stdout)["figures"]
    wrong = [n for n, st in ks.items() if f.get("compare_steps." + n) != st[0]]
    detail = "queue_step %d/%d (Cadence/Klipper), step command bytes %d/%d, steps %d/%d" % (
        f["queue_steps"], f["compare_queue_steps"], f["step_cmd_bytes"],
        f["compare_step_cmd_bytes"], f["steps"], f["compare_steps"])
    if wrong:
        results.append(("batch-compare", "FAIL", "Klipper's steps counted wrong for %s; %s" % (
            ", ".join(wrong), detail)))
    else:
        results.append(("batch-compare", "PASS", detail))


def stepper_stats(msgs, pins):
    """{stepper: (steps, final position in steps, queue_steps)} replayed from messages."""
    by_oid = {}
    stats = {}
    dirs = {}
    for name, f in msgs:
        if name == "config_stepper":
            pin = f["step_pin"]
            pin = str(pins.get(pin, pin)).split("/")[-1]  # gpiochip0/gpio0 -> gpio0
            if pin in STEP_PINS:
                by_oid[f["oid"]] = STEP_PINS[pin]
                stats[STEP_PINS[pin]] = [0, 0, 0]
        elif name == "set_next_step_dir" and f["oid"] in by_oid:
            dirs[f["oid"]] = f["dir"]
        elif name == "queue_step" and f["oid"] in by_oid:
            s = stats[by_oid[f["oid"]]]
            s[0] += f["count"]
            s[1] += f["count"] if dirs.get(f["oid"]) else -f["count"]
            s[2] += 1
    return {k: tuple(v) for k, v in stats.items()}


def normalise(msgs, pins):
    """Messages with pin numbers given by name, for comparing the two decoders' output."""
    out = []
    for name, f in msgs:
        g = {k: pins.get(v, v) if k.endswith("pin") else v for k, v in f.items()}
        out.append((name, tuple(sorted(g.items()))))
    return out


def scenarios(results, args, klipper, bins):
    if any(selected(args, n) for n in ("batch-decoders", "batch-steps", "batch-compare",
                                       "batch-check")):
        batch(results, args, klipper, bins)
    import hostmcu
    hostmcu.scenarios(results, args, klipper, bins)


def batch(results, args, klipper, bins):
    import json
    d = os.path.join(args.work, "batch")
    os.makedirs(d, exist_ok=True)
    kcfg, ccfg = os.path.join(d, "klipper.cfg"), os.path.join(d, "cadence.cfg")
    with open(kcfg, "w") as f:
        f.write("[mcu]\nserial: /dev/null\n" + PRINTER_BODY + KLIPPER_EXTRA)
    with open(ccfg, "w") as f:
        f.write("[mcu]\nserial: /dev/null\n" + PRINTER_BODY)
    gcode = os.path.abspath(args.gcode)
    kbin, cbin = os.path.join(d, "klipper.bin"), os.path.join(d, "cadence.bin")
    pins = {}
    with open(klipper.dict) as f:
        kdict = json.load(f)
    from interop import expand_pins
    pins = {v: k for k, v in expand_pins(kdict).items()}
    try:
        t0 = time.monotonic()
        run(klipper.klippy(kcfg, "-i", gcode, "-o", kbin, "-d", klipper.dict,
                           "-l", os.path.join(d, "klippy.log")), cwd=d, timeout=3600)
        tk = time.monotonic() - t0
        t0 = time.monotonic()
        run([os.path.join(bins, "cadence"), "print", gcode, "--config", ccfg, "--batch", cbin,
             "--dictionary", klipper.dict], cwd=d, timeout=3600)
        tc = time.monotonic() - t0
        decoded = {}
        for label, path in (("klipper", kbin), ("cadence", cbin)):
            k = run([klipper.python, os.path.join(klipper.dir, "klippy", "parsedump.py"),
                     klipper.dict, path], timeout=1200).stdout
            c = run([os.path.join(bins, "cadence"), "decode", path, "--dictionary",
                     klipper.dict], timeout=1200).stdout
            decoded[label] = (parse_decoded(k), parse_decoded(c))
    except Fail as e:
        results.append(("batch-decoders", "FAIL", str(e)))
        return
    # 1. Both decoders read both streams the same way.
    rows = []
    ok = True
    for label in ("klipper", "cadence"):
        k, c = decoded[label]
        same = normalise(k, pins) == normalise(c, pins)
        ok &= same
        rows.append("%s stream: %d messages, parsedump %s cadence decode" % (
            label, len(k), "=" if same else "!=", ))
    if selected(args, "batch-decoders"):
        results.append(("batch-decoders", "PASS" if ok else "FAIL", "; ".join(rows)))
    # 2. Steps and final positions per stepper.
    ks = stepper_stats(decoded["klipper"][0], pins)
    cs = stepper_stats(decoded["cadence"][0], pins)
    detail = []
    ok = True
    for name in sorted(set(ks) | set(cs)):
        a, b = ks.get(name, (0, 0, 0)), cs.get(name, (0, 0, 0))
        ok &= a[1] == b[1]
        detail.append("%s steps %d/%d pos %d/%d qs %d/%d" % (name, a[0], b[0], a[1], b[1],
                                                            a[2], b[2]))
    kbytes, cbytes = os.path.getsize(kbin), os.path.getsize(cbin)
    steps_equal = all(ks.get(n, (0,))[0] == cs.get(n, (0,))[0] for n in set(ks) | set(cs))
    if selected(args, "batch-steps"):
        results.append(("batch-steps", "PASS" if ok else "FAIL",
                        "%s (Klipper/Cadence): %s; steps %s; wire bytes %d/%d; "
                        "wall %.1f/%.1f s" % (os.path.basename(gcode), ", ".join(detail),
                                             "equal" if steps_equal else "differ",
                                             kbytes, cbytes, tk, tc)))
    # 3. `cadence bench plan --compare` counts Klipper's stream as parsedump's messages say.
    if selected(args, "batch-compare"):
        batch_compare(results, args, klipper, bins, gcode, ccfg, kbin, ks)
    # 4. Cadence's checker proves both streams against the G-code.
    if selected(args, "batch-check"):
        for label, path in (("klipper", kbin), ("cadence", cbin)):
            p = run([os.path.join(bins, "cadence"), "decode", path, "--check", gcode,
                     "--config", ccfg, "--dictionary", klipper.dict], timeout=3600,
                    check=False)
            lines = [l.strip() for l in p.stdout.splitlines() if l.strip().endswith(": ok")]
            if p.returncode == 0:
                results.append(("batch-check-" + label, "PASS",
                                "cadence decode --check: " + "; ".join(lines)))
            else:
                results.append(("batch-check-" + label, "FAIL",
                                (p.stderr or p.stdout).strip()[-400:]))
