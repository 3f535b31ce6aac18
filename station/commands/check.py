"""Open stage, display and camera; home; capture test patterns at three depths.

Check the bench: home the stage, visit three depths, show a crosshair and a checkerboard at
each, capture them, write a contact sheet, print a summary. Exit code 1 when any step failed.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from station.errors import UsageError, check_output

OPTIONS = {"json": None}


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", type=Path, help="station config (TOML)")
    p.add_argument("--fake", action="store_true", help="use the built-in fake bench config")
    p.add_argument("--out", type=Path, default=Path("out/check"),
                   help="folder for the contact sheet (default: out/check)")
    p.add_argument("--force", action="store_true", help="overwrite the contact sheet in --out")


def run(args: argparse.Namespace) -> dict:
    from station.acquisition.check import run_check
    from station.acquisition.config import example_config, load_config

    if args.fake == (args.config is not None):
        raise UsageError("give either a CONFIG.toml or --fake")
    check_output(args.out / "check.png", args.force)
    config = example_config("fake") if args.fake else load_config(args.config)
    return run_check(config, args.out)


def text(report: dict) -> str:
    from station.acquisition.check import format_report

    return format_report(report)
