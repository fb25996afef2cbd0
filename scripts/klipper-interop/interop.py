#!/usr/bin/env python3
"""Conformance harness: Cadence against the real Klipper, built from a source tree you give.

    python3 scripts/klipper-interop/interop.py --klipper ~/klipper [--work /tmp/cadence-klipper]

Nothing of Klipper is in this repository (Klipper is GPL): the tree given with --klipper is
copied into the scratch folder (--work), its Linux-process MCU is built there, klippy's Python
environment is made there (a venv with the packages that install on Python 3.11), and klippy
runs from there. Cadence's binaries are built with cargo (or taken from --bin-dir).

Scenarios (--only NAME,NAME to pick):
  k2c-*    Klipper's unmodified host (klippy) drives `cadence-mcu` processes over ptys, through
           klippy's API socket: startup to ready, STATUS, FIRMWARE_RESTART, G28 in cycles
           (second pass and retract), moves and M400, a whole G-code print from virtual_sdcard,
           multi-MCU homing (Z endstop on a second cadence-mcu), and at the end every stepper's
           position as the MCU executed it (the step trace) against klippy's; and klippy's
           heater control on the simulated thermal models (heaters.py): M104/M109, M140/M190,
           M106/M107, verify_heater catching a dead heater, an open thermistor shutting down.
  batch-*  The same G-code and printer through both hosts' batch modes (Klipper's dictionary),
           each stream decoded by both decoders: steps per stepper and final positions equal,
           and `cadence decode --check` proving Klipper's stream.
  c2k-*    Cadence's host drives Klipper's Linux-process MCU: identify, clock sync, config, and
           the MCU's own shutdown reason shown verbatim (this VM has no GPIO: stepping is
           blocked there, and the table says so).

Prints a table: scenario, result (PASS / FAIL / BLOCKED), detail. Exit status 1 if any FAIL.
"""

import argparse
import atexit
import hashlib
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, HERE)
import mcu_wire  # noqa: E402

# klippy's pinned requirements have no wheels for Python 3.11; these install and work.
KLIPPY_PIP = [
    "greenlet==2.0.2",
    "cffi==1.17.1",
    "pyserial==3.4",
    "Jinja2==3.1.4",
    "markupsafe==2.1.5",
    "msgspec==0.19.0",
]


class Fail(Exception):
    pass


class Blocked(Exception):
    pass


def log(msg):
    print(msg, file=sys.stderr, flush=True)


def run(cmd, cwd=None, env=None, timeout=None, check=True):
    p = subprocess.run(cmd, cwd=cwd, env=env, timeout=timeout, capture_output=True, text=True)
    if check and p.returncode != 0:
        raise Fail("%s failed (%d): %s" % (" ".join(map(str, cmd)), p.returncode,
                                           (p.stderr or p.stdout)[-800:]))
    return p


def stop(proc, wait_s=10):
    """Ends a child process: SIGTERM, then SIGKILL if it is still there after `wait_s`."""
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(wait_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def last_line(p):
    """The last line a finished command printed (stderr first), for a table's detail."""
    lines = (p.stderr or p.stdout or "").strip().splitlines()
    return lines[-1] if lines else "exit status %d, no output" % p.returncode


# ----------------------------------------------------------------------------------------
# Building Klipper and Cadence


class Klipper:
    """A Klipper tree copied into the scratch folder, built for the Linux-process MCU."""

    def __init__(self, src, work):
        self.src = os.path.abspath(src)
        self.dir = os.path.join(work, "klipper")
        self.venv = os.path.join(work, "klippy-venv")
        self.python = os.path.join(self.venv, "bin", "python")
        self.elf = os.path.join(self.dir, "out", "klipper.elf")
        self.dict = os.path.join(self.dir, "out", "klipper.dict")
        self.version = "?"

    def prepare(self):
        if not os.path.exists(os.path.join(self.src, "klippy", "klippy.py")):
            raise SystemExit("--klipper %s: not a Klipper source tree (no klippy/klippy.py)"
                             % self.src)
        p = run(["git", "-C", self.src, "describe", "--tags", "--always", "--dirty"],
                check=False)
        self.version = p.stdout.strip() or "unknown (not a git tree)"
        stamp = os.path.join(self.dir, ".cadence-interop-stamp")
        want = self.version + "\n" + run(["git", "-C", self.src, "status", "--porcelain"],
                                         check=False).stdout
        if not (os.path.exists(stamp) and open(stamp).read() == want
                and os.path.exists(self.elf)):
            log("klipper: copying %s (%s) to %s" % (self.src, self.version, self.dir))
            shutil.rmtree(self.dir, ignore_errors=True)
            shutil.copytree(self.src, self.dir, symlinks=True,
                            ignore=shutil.ignore_patterns("out", ".config*", "*.pyc"))
            with open(os.path.join(self.dir, ".config"), "w") as f:
                f.write("CONFIG_MACH_LINUX=y\n")
            log("klipper: building the Linux-process MCU")
            run(["make", "olddefconfig"], cwd=self.dir)
            run(["make", "-j2"], cwd=self.dir, timeout=1800)
            with open(stamp, "w") as f:
                f.write(want)
        if not os.path.exists(self.python):
            log("klipper: making klippy's venv")
            run([sys.executable, "-m", "venv", self.venv])
            run([self.python, "-m", "pip", "install", "-q", "--only-binary=:all:"] + KLIPPY_PIP,
                timeout=900)
        # klippy's C helper builds itself on first import.
        run([self.python, "-c", "import chelper; chelper.get_ffi()"],
            cwd=os.path.join(self.dir, "klippy"), timeout=600)

    def klippy(self, *args):
        return [self.python, os.path.join(self.dir, "klippy", "klippy.py")] + list(args)


def build_cadence(args):
    if args.bin_dir:
        return os.path.abspath(args.bin_dir)
    profile = ["--release"] if args.profile == "release" else []
    log("cadence: cargo build %s" % " ".join(profile))
    run(["cargo", "build", "--bin", "cadence", "--bin", "cadence-mcu"] + profile, cwd=REPO,
        timeout=7200)
    return os.path.join(REPO, "target", "release" if args.profile == "release" else "debug")


# ----------------------------------------------------------------------------------------
# klippy's API socket


class Api:
    """klippy's API server: JSON requests each ended by 0x03."""

    def __init__(self, path):
        self.path = path
        self.next_id = 1

    def call(self, method, params=None, timeout=600.0):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(timeout)
        try:
            s.connect(self.path)
            req = {"id": self.next_id, "method": method, "params": params or {}}
            self.next_id += 1
            s.sendall(json.dumps(req).encode() + b"\x03")
            buf = b""
            while b"\x03" not in buf:
                d = s.recv(65536)
                if not d:
                    raise Fail("klippy closed the API socket during %s" % method)
                buf += d
        finally:
            s.close()
        return json.loads(buf.split(b"\x03")[0])

    def gcode(self, script, timeout=600.0):
        r = self.call("gcode/script", {"script": script}, timeout)
        if "error" in r:
            raise Fail("%s: %s" % (script.replace("\n", "; "), r["error"].get("message")))
        return r

    def state(self):
        try:
            return self.call("info", timeout=10.0).get("result", {}).get("state")
        except (OSError, Fail, ValueError):
            return None

    def query(self, objects):
        r = self.call("objects/query", {"objects": objects})
        return r.get("result", {}).get("status", {})

    def wait_ready(self, timeout=90.0):
        deadline = time.monotonic() + timeout
        state = None
        while time.monotonic() < deadline:
            state = self.state()
            if state == "ready":
                return
            if state in ("shutdown", "error"):
                break
            time.sleep(0.5)
        msg = ""
        try:
            msg = self.call("info", timeout=10.0)["result"].get("state_message", "")
        except (OSError, Fail, ValueError, KeyError):
            pass
        raise Fail("klippy state %s, not ready: %s" % (state, msg.strip()))


# ----------------------------------------------------------------------------------------
# Klipper's host -> cadence-mcu

STEPPERS = [
    # name, step, dir, enable, endstop, rotation_distance, axis, max
    ("stepper_x", "PA0", "PA1", "!PA2", "PA3", 40, "x", 220),
    ("stepper_y", "PB0", "PB1", "!PB2", "PB3", 40, "y", 220),
    ("stepper_z", "PC0", "PC1", "!PC2", "PC3", 8, "z", 200),
]
STEPS_PER_MM = {"stepper_x": 80.0, "stepper_y": 80.0, "stepper_z": 400.0}


def k2c_printer_cfg(run_dir, z_mcu=None, hotend_sensor=None):
    """A cartesian printer on cadence-mcu pins (written here for Cadence; not from Klipper).
    `hotend_sensor`: the extruder's sensor option lines instead of the Generic 3950 on PF0."""
    lines = [
        "[mcu]", "serial: %s/mcu.pty" % run_dir, "restart_method: command", "",
    ]
    if z_mcu:
        lines += ["[mcu %s]" % z_mcu, "serial: %s/%s.pty" % (run_dir, z_mcu),
                  "restart_method: command", ""]
    lines += [
        "[printer]", "kinematics: cartesian", "max_velocity: 300", "max_accel: 3000",
        "max_z_velocity: 15", "max_z_accel: 100", "",
        "[virtual_sdcard]", "path: %s/gcodes" % run_dir, "",
        "[force_move]", "enable_force_move: True", "",
    ]
    for name, step, dirp, en, endstop, rot, axis, pmax in STEPPERS:
        pin = ("^%s:%s" % (z_mcu, endstop)) if (z_mcu and axis == "z") else "^" + endstop
        lines += [
            "[%s]" % name, "step_pin: %s" % step, "dir_pin: %s" % dirp,
            "enable_pin: %s" % en, "microsteps: 16", "rotation_distance: %s" % rot,
            "endstop_pin: %s" % pin, "position_endstop: 0", "position_max: %d" % pmax,
            "homing_speed: %d" % (10 if axis == "z" else 50), "",
        ]
    lines += [
        "[extruder]", "step_pin: PD0", "dir_pin: PD1", "enable_pin: !PD2", "microsteps: 16",
        "rotation_distance: 33.5", "nozzle_diameter: 0.4", "filament_diameter: 1.75",
        "max_extrude_only_distance: 500", "max_extrude_cross_section: 50",
        "min_extrude_temp: 0",
        "heater_pin: PE0"] + (hotend_sensor or ["sensor_type: Generic 3950", "sensor_pin: PF0"]) + [
        "control: pid",
        "pid_Kp: 22.2", "pid_Ki: 1.08", "pid_Kd: 114", "min_temp: 0", "max_temp: 300", "",
        "[heater_bed]", "heater_pin: PE1", "sensor_type: Generic 3950", "sensor_pin: PF1",
        "control: watermark", "min_temp: 0", "max_temp: 130", "",
        "[fan]", "pin: PE2", "",
        "[gcode_macro PRINT_START]", "gcode:", "  G28", "",
        "[gcode_macro PRINT_END]", "gcode:", "  M400", "",
    ]
    path = os.path.join(run_dir, "printer.cfg")
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")
    return path


class Rig:
    """cadence-mcu processes in one simulated world, and klippy driving them."""

    def __init__(self, name, args, klipper, bins, z_mcu=None, mcu_extra=(), hotend_sensor=None,
                 hotend_sensor_pin="PF0", cfg_edit=None):
        self.name = name
        self.args = args
        self.klipper = klipper
        self.bins = bins
        self.z_mcu = z_mcu
        self.mcu_extra = list(mcu_extra)
        self.dir = os.path.join(args.work, "run-" + name)
        shutil.rmtree(self.dir, ignore_errors=True)
        os.makedirs(os.path.join(self.dir, "gcodes"))
        self.cfg = k2c_printer_cfg(self.dir, z_mcu, hotend_sensor)
        if cfg_edit:  # a scenario's changes to the printer.cfg text
            with open(self.cfg) as f:
                text = cfg_edit(f.read())
            with open(self.cfg, "w") as f:
                f.write(text)
        self.hotend_sensor_pin = hotend_sensor_pin
        self.world = "interop-%d-%s" % (os.getpid(), name)
        self.mcus = {}
        self.klippy = None
        self.api = Api(os.path.join(self.dir, "api.sock"))
        self.log_path = os.path.join(self.dir, "klippy.log")

    def mcu_args(self, mcu):
        a = []
        if mcu == "mcu":
            for name, step, _d, _e, endstop, rot, axis, pmax in STEPPERS:
                a += ["--axis", "%s=%s,%s,%s" % (axis, step, STEPS_PER_MM[name], pmax / 10)]
                if not (self.z_mcu and axis == "z"):
                    a += ["--endstop", "%s=%s,0,min" % (endstop, axis)]
            # The simulated thermal models: a 40 W hotend and a 150 W bed (cadence-mcu --heater).
            a += ["--heater", "PE0=%s,hotend" % self.hotend_sensor_pin,
                  "--heater", "PE1=PF1,bed"] + self.mcu_extra
        else:
            a += ["--endstop", "PC3=z,0,min"]
        return a + ["--world", self.world]

    def start(self):
        for mcu in ["mcu"] + ([self.z_mcu] if self.z_mcu else []):
            trace = os.path.join(trace_dir(self.args, self.name), "trace-%s.csv" % mcu)
            # SCHED_FIFO when the OS allows it (a board runs its timers in real time; on a
            # loaded VM an ordinary process stalls for tens of ms, longer than the 25 ms
            # multi-MCU homing budget), its memory locked (a code page the kernel dropped
            # while idle is read back from a busy disk in mid-homing otherwise); refused,
            # cadence-mcu says so once and runs anyway.
            rt = ["--fifo", str(self.args.mcu_fifo), "--lock-memory"] if self.args.mcu_fifo else []
            cmd = ([os.path.join(self.bins, "cadence-mcu"), "--keep-open"] + rt
                   + ["--pty-link", os.path.join(self.dir, mcu + ".pty"),
                      "--trace", trace, "--trace-format", "csv"] + self.mcu_args(mcu))
            err = open(os.path.join(self.dir, "cadence-mcu-%s.log" % mcu), "w")
            p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True)
            p.stdout.readline()
            self.mcus[mcu] = (p, trace)
        out = open(os.path.join(self.dir, "klippy.out"), "w")
        self.klippy = subprocess.Popen(
            chrt(self.args.klippy_fifo)
            + self.klipper.klippy(self.cfg, "-a", self.api.path, "-l", self.log_path),
            stdout=out, stderr=subprocess.STDOUT, cwd=self.dir)
        self.api.wait_ready()

    def stop(self):
        """Stops klippy and the MCUs (SIGTERM: each cadence-mcu flushes its trace)."""
        if self.klippy and self.klippy.poll() is None:
            self.klippy.send_signal(signal.SIGINT)
            try:
                self.klippy.wait(20)
            except subprocess.TimeoutExpired:
                self.klippy.kill()
                self.klippy.wait()
        for p, _ in self.mcus.values():
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(20)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()

    def klippy_log(self):
        try:
            with open(self.log_path, errors="replace") as f:
                return f.read()
        except OSError:
            return ""

    def check_no_shutdown(self):
        text = self.klippy_log()
        m = re.search(r"MCU '([^']+)' shutdown: (.*)", text)
        if m:
            raise Fail("MCU '%s' shut down: %s" % (m.group(1), m.group(2)))
        if "Transition to shutdown state" in text:
            raise Fail("klippy went to shutdown: " + text.split(
                "Transition to shutdown state")[1].splitlines()[0])

    def klippy_mcu_positions(self):
        """The last GET_POSITION's `mcu:` line from klippy's log: {stepper: steps}."""
        lines = [l for l in self.klippy_log().splitlines() if l.startswith("mcu: ")]
        if not lines:
            raise Fail("no GET_POSITION output in klippy.log")
        return {k: int(v) for k, v in (kv.split(":") for kv in lines[-1][5:].split())}


def trace_dir(args, rig_name):
    """Where a rig's cadence-mcu processes write their step traces: under --trace-dir (default
    /dev/shm, a tmpfs), removed when the harness exits. The simulator writes its trace from its
    loop thread; on a disk busy with other builds a write can block for over 100 ms (seen:
    steps 166 ms late, then a queue_step that had waited in the pty taken as too late: 'Timer
    too close'), far longer than homing's 25 ms budget."""
    base = args.trace_dir if os.access(args.trace_dir, os.W_OK) else args.work
    d = os.path.join(base, "cadence-interop-%d" % os.getpid(), rig_name)
    os.makedirs(d, exist_ok=True)
    if base != args.work:
        atexit.register(shutil.rmtree, os.path.dirname(d), True)
    return d


def chrt(priority):
    """`chrt -f PRIORITY` when SCHED_FIFO is allowed here (klippy's serial thread relays
    multi-MCU homing reports within a 25 ms budget, which other builds on a small loaded VM
    break at ordinary priority), else nothing."""
    if not priority or shutil.which("chrt") is None:
        return []
    if subprocess.run(["chrt", "-f", str(priority), "true"], capture_output=True).returncode:
        log("klippy: SCHED_FIFO refused, running at ordinary priority")
        return []
    return ["chrt", "-f", str(priority)]


def oid_map(rig, mcu):
    """{oid: stepper name} of `mcu` as klippy configures it: klippy in batch mode with the
    cadence-mcu's own dictionary (downloaded through identify) writes the configuration."""
    d = os.path.join(rig.dir, "oidmap-" + mcu)
    os.makedirs(d, exist_ok=True)
    pty = os.path.join(d, "probe.pty")
    p = subprocess.Popen([os.path.join(rig.bins, "cadence-mcu"), "--pty-link", pty],
                         stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        p.stdout.readline()
        text = mcu_wire.download_dictionary(pty)
    finally:
        p.terminate()
        p.wait()
    dict_path = os.path.join(d, "cadence-mcu.dict")
    with open(dict_path, "w") as f:
        f.write(text)
    # Pin names -> numbers: the dictionary names every board family's pins and the families
    # share numbers (P1.0 and PE0 are both 32), so compare numbers, not names.
    pin_numbers = expand_pins(json.loads(text))
    out = os.path.join(d, "config.bin")
    empty = os.path.join(d, "empty.gcode")
    open(empty, "w").close()
    batch_cfg = os.path.join(d, "printer.cfg")
    with open(rig.cfg) as src, open(batch_cfg, "w") as dst:
        dst.write(src.read())
    args = ["-i", empty, "-o", out, "-d", dict_path, "-l", os.path.join(d, "klippy.log")]
    if rig.z_mcu:
        # Every MCU needs a dictionary in batch mode (`-d NAME=FILE`); they are all the same.
        args += ["-d", "%s=%s" % (rig.z_mcu, dict_path)]
    run(rig.klipper.klippy(batch_cfg, *args), cwd=d, timeout=300)
    dump = run([rig.klipper.python, os.path.join(rig.klipper.dir, "klippy", "parsedump.py"),
                dict_path, out], timeout=120).stdout
    step_pins = {pin_numbers[s[1]]: s[0] for s in STEPPERS}
    step_pins[pin_numbers["PD0"]] = "extruder"
    oids = {}
    for m in re.finditer(r"config_stepper oid=(\d+) step_pin=([\w./]+)", dump):
        pin = m.group(2)
        number = int(pin) if pin.isdigit() else pin_numbers.get(pin)
        if number in step_pins:
            oids[int(m.group(1))] = step_pins[number]
    missing = set(step_pins.values()) - set(oids.values())
    if missing:
        raise Fail("no config_stepper for %s in klippy's configuration of '%s'" % (
            ", ".join(sorted(missing)), mcu))
    return oids


def expand_pins(dictionary):
    """{pin name: number} from the dictionary's `pin` enumeration (runs `"PA0": [0, 8]`)."""
    out = {}
    for name, v in dictionary.get("enumerations", {}).get("pin", {}).items():
        if isinstance(v, list):
            base = re.match(r"(.*?)(\d+)$", name)
            for i in range(v[1]):
                out["%s%d" % (base.group(1), int(base.group(2)) + i)] = v[0] + i
        else:
            out[name] = v
    return out


def trace_positions(trace_path):
    """{oid: net steps} executed by a cadence-mcu, from its CSV trace."""
    pos = {}
    with open(trace_path) as f:
        for line in f:
            if not line[:1].isdigit():
                continue
            kind, oid, direction, _aux, _clock = line.rstrip().split(",")
            if kind == "0":
                pos[int(oid)] = pos.get(int(oid), 0) + (1 if direction == "1" else -1)
    return pos


def compare_positions(rig):
    """klippy's MCU positions of every stepper against what the MCU executed."""
    rig.api.gcode("M400\nGET_POSITION")
    want = rig.klippy_mcu_positions()
    oids = oid_map(rig, "mcu")
    rig.stop()
    with open(os.path.join(rig.dir, "cadence-mcu-mcu.log"), errors="replace") as f:
        trouble = [l.strip() for l in f if "error:" in l]
    if trouble:
        raise Fail("the MCU's step trace is incomplete: " + "; ".join(trouble))
    got_by_oid = trace_positions(rig.mcus["mcu"][1])
    got = {name: got_by_oid.get(oid, 0) for oid, name in oids.items()}
    rows = []
    for name in sorted(want):
        rows.append("%s %d/%d" % (name, got.get(name, 0), want[name]))
        if got.get(name) != want[name] and not (want[name] == 0 and name not in got):
            raise Fail("stepper positions (MCU/klippy) differ: " + ", ".join(rows))
    return "MCU = klippy: " + ", ".join(rows)


GCODE_MOVES = "\n".join([
    "G90", "G1 X100 Y80 Z10 F6000", "G1 X12.3456 Y199.99 Z3.3 F3000",
    "G1 X150.5 Y20.25 F9000", "G91", "G1 X-10 Y10 Z0.7 F1200", "G90", "M400",
])


def scenario_k2c(results, args, klipper, bins):
    """One klippy session on one cadence-mcu: every single-MCU scenario in order."""
    rig = Rig("single", args, klipper, bins)
    names = ["k2c-startup", "k2c-status", "k2c-firmware-restart", "k2c-g28-cycles",
             "k2c-moves-m400", "k2c-print", "k2c-positions"]

    def step(name, fn):
        if not selected(args, name):
            return
        t0 = time.monotonic()
        try:
            detail = fn() or ""
            rig.check_no_shutdown()
            results.append((name, "PASS", "%s (%.1f s)" % (detail, time.monotonic() - t0)))
        except Blocked as e:
            results.append((name, "BLOCKED", str(e)))
        except (Fail, OSError, subprocess.SubprocessError, ValueError) as e:
            results.append((name, "FAIL", str(e)))
            raise

    try:
        step("k2c-startup", lambda: (rig.start(), "ready; " + klippy_mcu_line(rig))[1])
        step("k2c-status", lambda: (rig.api.gcode("STATUS"), "no error")[1])
        step("k2c-firmware-restart", lambda: firmware_restart(rig))
        step("k2c-g28-cycles", lambda: g28_cycles(rig, args.cycles))
        step("k2c-moves-m400", lambda: (rig.api.gcode(GCODE_MOVES), "G1 moves, G91, M400")[1])
        step("k2c-print", lambda: print_file(rig, args.gcode, args.print_timeout))
        step("k2c-positions", lambda: compare_positions(rig))
    except (Fail, OSError, subprocess.SubprocessError, ValueError):
        done = {r[0] for r in results}
        for n in names:
            if n not in done and selected(args, n):
                results.append((n, "FAIL", "not run: an earlier step failed"))
    finally:
        rig.stop()


def klippy_mcu_line(rig):
    m = re.findall(r"Loaded MCU 'mcu' (\d+ commands \([^)]*\))", rig.klippy_log())
    return m[-1] if m else ""


def firmware_restart(rig):
    rig.api.gcode("FIRMWARE_RESTART")
    time.sleep(1.0)
    rig.api.wait_ready()
    n = rig.klippy_log().count("config_reset command")
    return "emergency_stop + config_reset, reconnected, configured again, ready (%d)" % n


def g28_cycles(rig, cycles):
    for _ in range(cycles):
        rig.api.gcode("G28")
    homed = rig.api.query({"toolhead": ["homed_axes"]})["toolhead"]["homed_axes"]
    if homed != "xyz":
        raise Fail("homed_axes %r after G28" % homed)
    return "%d x G28 (each axis: fast pass, retract 5 mm, second pass), homed %s" % (
        cycles, homed)


def print_file(rig, gcode, timeout):
    if not gcode:
        raise Blocked("no --gcode file given")
    name = os.path.basename(gcode)
    shutil.copy(gcode, os.path.join(rig.dir, "gcodes", name))
    t0 = time.monotonic()
    rig.api.gcode("SDCARD_PRINT_FILE FILENAME=%s" % name)
    while True:
        st = rig.api.query({"print_stats": ["state", "message", "print_duration"],
                            "virtual_sdcard": ["progress"]})
        state = st["print_stats"]["state"]
        if state == "complete":
            break
        if state in ("error", "cancelled", "paused") or rig.api.state() != "ready":
            rig.check_no_shutdown()
            raise Fail("print %s at %.1f %%: %s" % (
                state, 100 * st["virtual_sdcard"]["progress"], st["print_stats"].get("message")))
        if time.monotonic() - t0 > timeout:
            raise Fail("print not done after %d s (progress %.1f %%)" % (
                timeout, 100 * st["virtual_sdcard"]["progress"]))
        time.sleep(2.0)
    rig.api.gcode("M400")
    lines = sum(1 for _ in open(gcode, errors="replace"))
    return "%s (%d lines) printed to the end, print_duration %.0f s" % (
        name, lines, st["print_stats"]["print_duration"])


def scenario_k2c_multi(results, args, klipper, bins):
    name = "k2c-multi-mcu-homing"
    if not selected(args, name):
        return
    rig = Rig("multi", args, klipper, bins, z_mcu="zmcu")
    t0 = time.monotonic()
    try:
        rig.start()
        # Each cycle on its own: a failed cycle (klippy stays ready) is counted, not fatal.
        failures = []
        for i in range(args.cycles):
            try:
                rig.api.gcode("G28")
            except Fail as e:
                failures.append("cycle %d: %s" % (i + 1, e))
        try:
            rig.api.gcode("G28")  # homed for the moves whatever happened above
        except Fail as e:
            failures.append("extra G28 before the moves: %s" % e)
            rig.api.gcode("G28")
        rig.api.gcode(GCODE_MOVES)
        rig.check_no_shutdown()
        pos = compare_positions(rig)
        cycle_failures = sum(1 for f in failures if f.startswith("cycle"))
        detail = "Z endstop on cadence-mcu 'zmcu': %d of %d G28 cycles ok%s; %s (%.1f s)" % (
            args.cycles - cycle_failures, args.cycles,
            (" (" + "; ".join(failures) + ")") if failures else "", pos,
            time.monotonic() - t0)
        results.append((name, "FAIL" if failures else "PASS", detail))
    except (Fail, OSError, subprocess.SubprocessError, ValueError) as e:
        results.append((name, "FAIL", str(e)))
    finally:
        rig.stop()


# ----------------------------------------------------------------------------------------


def selected(args, name):
    if not args.only:
        return True
    return any(name == o or name.startswith(o.rstrip("*")) for o in args.only.split(","))


def run_scenarios(results, args, klipper, bins, table):
    """Runs each selected `(name, fn)` of `table`: fn's detail is a PASS row, its Fail (or an
    OS, subprocess or data error) a FAIL row."""
    for name, fn in table:
        if not selected(args, name):
            continue
        t0 = time.monotonic()
        try:
            detail = fn(args, klipper, bins)
            results.append((name, "PASS", "%s (%.1f s)" % (detail, time.monotonic() - t0)))
        except (Fail, OSError, subprocess.SubprocessError, ValueError, KeyError,
                IndexError) as e:
            results.append((name, "FAIL", str(e)))


def print_table(results, klipper):
    out = ["Klipper %s (Linux-process MCU build), Cadence %s" % (
        klipper.version, run(["git", "-C", REPO, "describe", "--always", "--dirty"],
                             check=False).stdout.strip()), ""]
    w = max([len(r[0]) for r in results] + [8])
    out.append("| %-*s | result  | detail |" % (w, "scenario"))
    out.append("|-%s-|---------|--------|" % ("-" * w))
    for name, res, detail in results:
        out.append("| %-*s | %-7s | %s |" % (w, name, res, detail.replace("|", "/")))
    print("\n".join(out))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--klipper", default=os.environ.get("CADENCE_KLIPPER_SRC"),
                    help="a Klipper source tree (default: $CADENCE_KLIPPER_SRC)")
    ap.add_argument("--work", default="/tmp/cadence-klipper-interop",
                    help="scratch folder (Klipper's copy, build, venv, runs)")
    ap.add_argument("--bin-dir", help="take cadence and cadence-mcu from here (no cargo build)")
    ap.add_argument("--profile", choices=["release", "dev"], default="release")
    ap.add_argument("--only", help="comma-separated scenario names or prefixes (k2c-, batch-)")
    ap.add_argument("--cycles", type=int, default=3, help="G28 cycles")
    ap.add_argument("--gcode", default=os.path.join(REPO, "examples", "square.gcode"),
                    help="the G-code file printed whole by k2c-print and batch-*")
    ap.add_argument("--print-timeout", type=float, default=3600.0)
    ap.add_argument("--klippy-fifo", type=int, default=60,
                    help="SCHED_FIFO priority of klippy (0: ordinary); below the simulated "
                         "MCUs' (--mcu-fifo), above everything else")
    ap.add_argument("--simulavr", default=os.environ.get("CADENCE_SIMULAVR"),
                    help="a simulavr tree built with its Python module (--enable-python): "
                         "c2k-avr-home-print runs Klipper's ATmega644p build in it")
    ap.add_argument("--avr-freq", type=int, default=16000000,
                    choices=[8000000, 16000000, 20000000],
                    help="clock of the simulated ATmega644p (simulavr must keep up with it)")
    ap.add_argument("--trace-dir", default="/dev/shm",
                    help="where the simulated MCUs write their step traces (default: /dev/shm, "
                         "a tmpfs, so that no trace write waits for the disk)")
    ap.add_argument("--mcu-fifo", type=int, default=70,
                    help="SCHED_FIFO priority of the cadence-mcu processes (0: ordinary); above "
                         "klippy's, as a board's MCU never waits for the host's CPUs (at 50, "
                         "below klippy, their steps ran late by p99.9 22 ms on this VM under "
                         "load; at 70, 2 ms)")
    args = ap.parse_args()
    if not args.klipper:
        ap.error("--klipper DIR (or CADENCE_KLIPPER_SRC) is required")
    args.work = os.path.abspath(args.work)
    os.makedirs(args.work, exist_ok=True)
    klipper = Klipper(args.klipper, args.work)
    klipper.prepare()
    bins = build_cadence(args)
    results = []
    scenario_k2c(results, args, klipper, bins)
    scenario_k2c_multi(results, args, klipper, bins)
    import heaters  # noqa: E402  (klippy driving the simulated heaters and fan)
    heaters.scenarios(results, args, klipper, bins)
    import tmc  # noqa: E402  (klippy driving simulated TMC drivers, sensorless homing)
    tmc.scenarios(results, args, klipper, bins)
    import probe  # noqa: E402  (klippy's BLTouch and bed mesh on a simulated warped bed)
    probe.scenarios(results, args, klipper, bins)
    import batch  # noqa: E402  (the batch and Cadence-host scenarios)
    batch.scenarios(results, args, klipper, bins)
    import avr  # noqa: E402  (Cadence's host on Klipper's AVR build under simulavr)
    avr.scenarios(results, args, klipper, bins)
    print_table(results, klipper)
    return 1 if any(r[1] == "FAIL" for r in results) else 0


if __name__ == "__main__":
    sys.exit(main())
