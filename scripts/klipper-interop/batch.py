"""Batch-mode and Cadence-host scenarios of the harness (see interop.py)."""


def scenarios(results, args, klipper, bins):
    pass
