"""``ltc check [CONFIG.toml | --fake] [--out DIR] [--json]``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from station.errors import UsageError, check_output


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "check",
        help="open stage, display and camera; home; capture test patterns at three depths",
        description="Check the bench: home the stage, visit three depths, show a crosshair and "
        "a checkerboard at each, capture them, write a contact sheet, print a summary. "
        "Exit code 1 when any step failed.",
    )
    p.add_argument("config", nargs="?", type=Path, help="station config (TOML)")
    p.add_argument("--fake", action="store_true", help="use the built-in fake bench config")
    p.add_argument("--out", type=Path, default=Path("out/check"),
                   help="folder for the contact sheet (default: out/check)")
    p.add_argument("--force", action="store_true", help="overwrite the contact sheet in --out")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from station.acquisition.check import format_report, run_check
    from station.acquisition.config import example_config, load_config

    if args.fake == (args.config is not None):
        raise UsageError("give either a CONFIG.toml or --fake")
    check_output(args.out / "check.png", args.force)
    config = example_config("fake") if args.fake else load_config(args.config)
    report = run_check(config, args.out)
    print(json.dumps(report) if args.json else format_report(report))
    return 0 if report["ok"] else 1
