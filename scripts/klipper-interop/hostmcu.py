"""Cadence's host driving Klipper's Linux-process MCU (see interop.py).

c2k-config: `cadence home` connects to a fresh `klipper.elf` (identify, clock sync, get_config,
the configuration with endstops first, as Klipper's host sends it). Where the machine has no
GPIO (no /dev/gpiochip*), Klipper's MCU shuts down on the first pin it cannot open: Cadence
must say the MCU's reason verbatim and the MCU must stay up (it crashed on a stepper-first
configuration). c2k-shutdown-verbatim: the same against the MCU already shut down.
c2k-home-print: homing and printing on it, which needs GPIO.
"""

import glob
import os
import re
import signal
import subprocess
import time

from interop import run, selected

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
            if first.returncode == 0:
                p = run([os.path.join(bins, "cadence"), "print", os.path.abspath(args.gcode),
                         "--config", cfg, "--no-realtime"], timeout=7200, check=False)
                results.append(("c2k-home-print", "PASS" if p.returncode == 0 else "FAIL",
                                (p.stdout or p.stderr).strip().splitlines()[-1:][0]))
            elif not gpio:
                results.append(("c2k-home-print", "BLOCKED",
                                "this machine has no GPIO (no /dev/gpiochip*, no gpio-sim "
                                "module): Klipper's Linux MCU shuts down on the first pin "
                                "(%s); homing and printing on it need a GPIO chip (a board, a "
                                "Pi, or gpio-sim), or its AVR build under simulavr (not tried "
                                "here)" % (m.group(1) if m else msg)))
            else:
                results.append(("c2k-home-print", "FAIL", msg))
    finally:
        if mcu.poll() is None:
            mcu.send_signal(signal.SIGTERM)
            try:
                mcu.wait(10)
            except subprocess.TimeoutExpired:
                mcu.kill()
                mcu.wait()
