"""``ltc gamma CONFIG --out LUT [--levels N] [--json]``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from drivers.interfaces import DeviceError
from station.acquisition.config import ConfigError, load_config
from station.acquisition.gamma import GammaError, measure_lut, save_lut


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "gamma",
        help="measure the display response and write the inverse LUT",
        description="Show uniform grey levels (the display's LUT set to identity), capture them, "
        "fit the display's response and write the inverse lookup table (256 integers) that makes "
        "the display linear. Put its path in the config as display.lut_path. The stage does not move.",
    )
    p.add_argument("config", type=Path, help="station config (TOML)")
    p.add_argument("--out", type=Path, required=True,
                   help="LUT file to write: .npy, or text with one value per line")
    p.add_argument("--levels", type=int, default=65, help="grey levels to show (>= 64; default 65)")
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        config = load_config(args.config)
    except ConfigError as exc:
        print(f"ltc gamma: {exc}", file=sys.stderr)
        return 2
    if args.levels < 64:
        print(f"ltc gamma: --levels must be >= 64, got {args.levels}", file=sys.stderr)
        return 2
    try:
        summary = measure_lut(config, n_levels=args.levels)
    except (GammaError, DeviceError) as exc:
        print(f"ltc gamma: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    save_lut(args.out, np.array(summary["lut"]))
    summary["out"] = str(args.out)
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"ltc gamma: {len(summary['levels'])} grey levels over {summary['pixels']} pixels; "
              f"fitted gamma {summary['gamma_fit']:.3f}; LUT written to {args.out} "
              f"(set display.lut_path = \"{args.out}\")")
    return 0
