"""Measure the display response and write the inverse LUT.

Show uniform grey levels (the display's LUT set to identity), capture them, fit the display's
response and write the inverse lookup table (256 integers) that makes the display linear. Put
its path in the config as display.lut_path. The stage does not move.
"""

from __future__ import annotations

import argparse

from station.commands import at_least

OPTIONS = {"config": None, "out": "LUT file to write: .npy, or text with one value per line",
           "force": None, "json": None}


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--levels", type=at_least(64), default=65,
                   help="grey levels to show (>= 64; default 65)")


def run(args: argparse.Namespace) -> dict:
    import numpy as np

    from station.acquisition.gamma import measure_lut, save_lut
    from station.api import load_config
    from station.outputs import LUT_FILE, staged
    from station.outputs import check_output as check_kind

    check_kind(args.out, args.force, kind=LUT_FILE, inputs=[args.config])
    summary = measure_lut(load_config(args.config), n_levels=args.levels)
    with staged(args.out, LUT_FILE, always=True) as target:
        save_lut(target, np.array(summary["lut"]))
    return {**summary, "out": str(args.out)}


def text(s: dict) -> str:
    return (f"ltc gamma: {len(s['levels'])} grey levels over {s['pixels']} pixels; fitted gamma "
            f"{s['gamma_fit']:.3f}; LUT written to {s['out']} (set display.lut_path = "
            f"\"{s['out']}\")")
