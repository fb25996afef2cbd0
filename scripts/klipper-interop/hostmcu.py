"""Cadence's host driving Klipper's Linux-process MCU (see interop.py)."""


def scenarios(results, args, klipper, bins):
    pass
