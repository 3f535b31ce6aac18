"""``ltc gamma CONFIG --out LUT [--levels N] [--json]``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from station.commands import at_least
from station.errors import check_output


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
    p.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    p.add_argument("--levels", type=at_least(64), default=65,
                   help="grey levels to show (>= 64; default 65)")
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from station.acquisition.gamma import measure_lut, save_lut
    from station.api import load_config

    check_output(args.out, args.force)
    config = load_config(args.config)
    summary = measure_lut(config, n_levels=args.levels)
    save_lut(args.out, np.array(summary["lut"]))
    summary["out"] = str(args.out)
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"ltc gamma: {len(summary['levels'])} grey levels over {summary['pixels']} pixels; "
              f"fitted gamma {summary['gamma_fit']:.3f}; LUT written to {args.out} "
              f"(set display.lut_path = \"{args.out}\")")
    return 0
