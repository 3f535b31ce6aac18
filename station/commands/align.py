"""``ltc align CONFIG [--shift PX] [--json]``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from drivers.interfaces import DeviceError
from station.acquisition.align import AlignError, format_align, run_align
from station.acquisition.config import ConfigError, load_config


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
    p.add_argument("--shift", type=int, default=None, metavar="PX",
                   help="crosshair shift for the scale, LCD pixels (default: LCD height / 12)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        config = load_config(args.config)
    except ConfigError as exc:
        print(f"ltc align: {exc}", file=sys.stderr)
        return 2
    if args.shift is not None and args.shift < 1:
        print(f"ltc align: --shift must be >= 1 LCD pixel, got {args.shift}", file=sys.stderr)
        return 2
    try:
        report = run_align(config, shift_px=args.shift)
    except (AlignError, DeviceError) as exc:
        print(f"ltc align: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(report) if args.json else format_align(report))
    return 0
