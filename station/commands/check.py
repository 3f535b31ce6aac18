"""Open stage, display and camera; home; capture test patterns at three depths.

Check the bench: home the stage, visit three depths, show a crosshair and a checkerboard at
each, capture them, write a contact sheet, print a summary with the white level (a fraction of
full scale: tune the exposure to 0.80-0.90). Exit code 1 when any step failed. Run it as often
as needed: each run writes a new contact sheet, check-YYYYMMDD-HHMMSS.png, into --out and
never replaces an earlier one.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from station.errors import UsageError

OPTIONS = {"json": None}


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", type=Path, help="station config (TOML)")
    p.add_argument("--fake", action="store_true", help="use the built-in fake bench config")
    p.add_argument("--out", type=Path, default=Path("out/check"),
                   help="folder for the contact sheet (default: out/check)")
    p.add_argument("--force", action="store_true",
                   help="accepted for old scripts; no effect (nothing is ever replaced)")


def run(args: argparse.Namespace) -> dict:
    from station.acquisition.check import run_check
    from station.acquisition.config import example_config, load_config

    if args.fake == (args.config is not None):
        raise UsageError("give either a CONFIG.toml or --fake")
    config = example_config("fake") if args.fake else load_config(args.config)
    return run_check(config, args.out, sheet_name=_new_sheet_name(args.out))


def _new_sheet_name(folder: Path) -> str:
    """``check-<UTC time>.png``, with ``-2``, ``-3``... when that name is taken."""
    import time

    stem = time.strftime("check-%Y%m%d-%H%M%S", time.gmtime())
    name, n = f"{stem}.png", 1
    while (folder / name).exists() or (folder / name).is_symlink():
        n += 1
        name = f"{stem}-{n}.png"
    return name


def text(report: dict) -> str:
    from station.acquisition.check import format_report

    return format_report(report)
