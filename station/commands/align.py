"""``ltc align CONFIG [--shift PX] [--json]``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from station.commands import at_least


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "align",
        help="show a crosshair at the LCD centre at every depth; report offsets and axis tilt",
        description="At every configured depth, image the arms of a crosshair through the LCD "
        "centre (and shifted by --shift LCD pixels, for the image scale); report where the LCD "
        "centre appears, where the stage axis points in the image and the tilt of the optical "
        "axis it implies, so the camera can be squared to the LCD. Also says whether the check "
        "code ([frame_check]) is in the camera's view at every depth.",
    )
    p.add_argument("config", type=Path, help="station config (TOML)")
    p.add_argument("--shift", type=at_least(1), default=None, metavar="PX",
                   help="crosshair shift for the scale, LCD pixels (default: LCD height / 12)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from station.acquisition.align import format_align, run_align
    from station.api import load_config

    report = run_align(load_config(args.config), shift_px=args.shift)
    print(json.dumps(report) if args.json else format_align(report))
    return 0
