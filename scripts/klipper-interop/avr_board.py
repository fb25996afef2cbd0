#!/usr/bin/env python3
"""A simulated AVR printer board: Klipper's AVR build running in simulavr, its UART on a pty,
with axes that follow the step/dir pins and endstops that trigger at 0.

    PYTHONPATH=SIMULAVR/src/python python3 avr_board.py klipper.elf --pty PATH \\
        --axis x=PA5,PA4,PB0,80,10 [--axis ...] [--machine atmega644] [--speed 16000000] \\
        [--positions FILE]

Written for Cadence against simulavr's Python API (pysimulavr: SystemClock, AvrFactory, Pin,
Net, PySimulationMember; see simulavr's documentation). The UART is bit-level: simulavr models
the AVR's USART pins, so bytes from the pty are clocked onto RXD0 (PD0) and TXD0 (PD1) is
sampled back into bytes, 8N1 at --baud. An axis is STEP_PIN,DIR_PIN,ENDSTOP_PIN,STEPS_PER_MM,
START_MM: every rising edge on the step pin moves it one step (dir pin high = positive), and
the endstop pin reads high while the axis is at or below 0 mm. --positions FILE gets the net
steps of each axis (JSON) at exit (SIGTERM/SIGINT). Runs paced to real time (--pace, default 1;
it cannot run faster than simulavr does: the line 'pace' in FILE.stats says how far behind).
"""

import argparse
import errno
import json
import os
import pty
import signal
import sys
import termios
import time
import tty

import pysimulavr

NS = 10 ** 9


class StepInput(pysimulavr.Pin):
    """Watches one output pin of the AVR; calls on_change(level) on every change."""

    def __init__(self, on_change):
        pysimulavr.Pin.__init__(self)
        self.on_change = on_change
        self.level = 0

    def SetInState(self, pin):
        pysimulavr.Pin.SetInState(self, pin)
        level = 1 if pin.outState == pin.HIGH else 0
        if level != self.level:
            self.level = level
            self.on_change(level)


class Axis:
    def __init__(self, spec, dev):
        name, rest = spec.split("=", 1)
        step, dirp, endstop, spm, start = rest.split(",")
        self.name = name
        self.steps = 0
        self.steps_per_mm = float(spm)
        self.start_mm = float(start)
        self.dir_in = StepInput(lambda level: None)
        self.step_in = StepInput(self.on_step)
        self.endstop_out = pysimulavr.Pin()
        self.nets = []
        for pin_name, member in ((step, self.step_in), (dirp, self.dir_in),
                                 (endstop, self.endstop_out)):
            net = pysimulavr.Net()
            net.Add(member)
            net.Add(dev.GetPin(avr_pin(pin_name)))
            self.nets.append(net)
        self.update_endstop()

    def position_mm(self):
        return self.start_mm + self.steps / self.steps_per_mm

    def on_step(self, level):
        if level:
            self.steps += 1 if self.dir_in.level else -1
            self.update_endstop()

    def update_endstop(self):
        self.endstop_out.SetPin("H" if self.position_mm() <= 0.0 else "L")


def avr_pin(name):
    """simulavr names port pins without the P: PA5 -> A5."""
    return name[1:] if name.upper().startswith("P") else name


class UartToAvr(pysimulavr.PySimulationMember, pysimulavr.Pin):
    """Clocks bytes read from the pty onto the AVR's RXD pin (8N1)."""

    def __init__(self, fd, baud):
        pysimulavr.Pin.__init__(self)
        pysimulavr.PySimulationMember.__init__(self)
        self.fd = fd
        self.bit_ns = NS // baud
        self.pending = bytearray()
        self.frame = 0
        self.bit = 0
        self.SetPin("H")

    def DoStep(self, true_hw_step):
        if self.bit == 0:
            if not self.pending:
                try:
                    self.pending.extend(os.read(self.fd, 64))
                except OSError as e:
                    if e.errno not in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EIO):
                        raise
                if not self.pending:
                    return self.bit_ns * 50
            # start bit (0), 8 data bits LSB first, stop bit (1)
            self.frame = (self.pending.pop(0) << 1) | (1 << 9)
        self.SetPin("H" if (self.frame >> self.bit) & 1 else "L")
        self.bit = (self.bit + 1) % 10
        return self.bit_ns


class UartFromAvr(pysimulavr.PySimulationMember, pysimulavr.Pin):
    """Samples the AVR's TXD pin into bytes written to the pty."""

    def __init__(self, fd, baud):
        pysimulavr.Pin.__init__(self)
        pysimulavr.PySimulationMember.__init__(self)
        self.fd = fd
        self.bit_ns = NS // baud
        self.clock = pysimulavr.SystemClock.Instance()
        self.level = 1
        self.bit = -1
        self.value = 0

    def SetInState(self, pin):
        pysimulavr.Pin.SetInState(self, pin)
        self.level = 0 if pin.outState == pin.LOW else 1
        if self.bit < 0 and self.level == 0:
            self.bit = 0
            self.value = 0
            self.clock.Add(self)

    def DoStep(self, true_hw_step):
        if self.bit == 0:
            self.bit = 1
            return self.bit_ns * 3 // 2  # to the middle of data bit 0
        self.value |= self.level << (self.bit - 1)
        self.bit += 1
        if self.bit > 8:
            try:
                os.write(self.fd, bytes([self.value & 0xFF]))
            except OSError:
                pass
            self.bit = -1
            return -1
        return self.bit_ns


class Pace(pysimulavr.PySimulationMember):
    """Keeps simulated time from running ahead of wall time."""

    def __init__(self, rate):
        pysimulavr.PySimulationMember.__init__(self)
        self.clock = pysimulavr.SystemClock.Instance()
        self.rate = rate
        self.t0 = time.monotonic()
        self.behind_s = 0.0

    def DoStep(self, true_hw_step):
        sim_s = self.clock.GetCurrentTime() / NS / self.rate
        ahead = sim_s - (time.monotonic() - self.t0)
        if ahead > 0.0002:
            time.sleep(ahead - 0.0001)
        else:
            self.behind_s = max(self.behind_s, -ahead)
        return NS // 10000


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("elf")
    ap.add_argument("--pty", required=True, help="symlink to the UART's pty")
    ap.add_argument("--machine", default="atmega644")
    ap.add_argument("--speed", type=int, default=16000000)
    ap.add_argument("--baud", type=int, default=250000)
    ap.add_argument("--pace", type=float, default=1.0)
    ap.add_argument("--axis", action="append", default=[])
    ap.add_argument("--positions", help="write the axes' net steps (JSON) here at exit")
    args = ap.parse_args()

    clock = pysimulavr.SystemClock.Instance()
    dev = pysimulavr.AvrFactory.instance().makeDevice(args.machine)
    dev.Load(args.elf)
    dev.SetClockFreq(NS // args.speed)
    clock.Add(dev)
    pysimulavr.cvar.sysConHandler.SetUseExit(False)

    master, slave = pty.openpty()
    tty.setraw(master)
    attrs = termios.tcgetattr(master)
    attrs[3] &= ~termios.ECHO
    termios.tcsetattr(master, termios.TCSANOW, attrs)
    os.set_blocking(master, False)
    if os.path.lexists(args.pty):
        os.unlink(args.pty)
    os.symlink(os.ttyname(slave), args.pty)

    to_avr = UartToAvr(master, args.baud)
    rx_net = pysimulavr.Net()
    rx_net.Add(to_avr)
    rx_net.Add(dev.GetPin("D0"))
    clock.Add(to_avr)
    from_avr = UartFromAvr(master, args.baud)
    tx_net = pysimulavr.Net()
    tx_net.Add(from_avr)
    tx_net.Add(dev.GetPin("D1"))
    axes = [Axis(spec, dev) for spec in args.axis]
    pace = Pace(args.pace) if args.pace else None
    if pace:
        clock.Add(pace)

    def finish(*_):
        clock.stop()

    signal.signal(signal.SIGTERM, finish)
    signal.signal(signal.SIGINT, finish)
    wall0 = time.monotonic()
    print("avr_board: %s %s at %d Hz, UART %d baud on %s" % (
        args.machine, args.elf, args.speed, args.baud, args.pty), flush=True)
    try:
        clock.RunTimeRange(0x7FFF0000FFFF0000)
    finally:
        os.unlink(args.pty)
        sim_s = clock.GetCurrentTime() / NS
        if args.positions:
            with open(args.positions, "w") as f:
                json.dump({"axes": {a.name: a.steps for a in axes}, "sim_s": sim_s,
                       "wall_s": time.monotonic() - wall0,
                           "max_behind_s": pace.behind_s if pace else None}, f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
