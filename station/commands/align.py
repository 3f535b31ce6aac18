"""Show a crosshair at the LCD centre at every depth; report offsets and axis tilt.

At every configured depth, image the arms of a crosshair through the LCD centre (and shifted
by --shift LCD pixels, for the image scale); report where the LCD centre appears, where the
stage axis points in the image and the tilt of the optical axis it implies, so the camera can
be squared to the LCD. Also says whether the check code ([frame_check]) is in the camera's
view at every depth.
"""

from __future__ import annotations

import argparse

from station.commands import at_least

OPTIONS = {"config": None, "json": None}


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--shift", type=at_least(1), default=None, metavar="PX",
                   help="crosshair shift for the scale, LCD pixels (default: LCD height / 12)")


def run(args: argparse.Namespace) -> dict:
    from station.acquisition.align import run_align
    from station.api import load_config

    return run_align(load_config(args.config), shift_px=args.shift)


def text(report: dict) -> str:
    from station.acquisition.align import format_align

    return format_align(report)
