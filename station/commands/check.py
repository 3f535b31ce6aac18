"""``ltc check [CONFIG.toml | --fake] [--out DIR] [--json]``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from station.acquisition.check import format_report, run_check
from station.acquisition.config import ConfigError, example_config, load_config


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "check",
        help="open stage, display and camera; home; capture test patterns at three depths",
        description="Check the bench: home the stage, visit three depths, show a crosshair and "
        "a checkerboard at each, capture them, write a contact sheet, print a summary.",
    )
    p.add_argument("config", nargs="?", type=Path, help="station config (TOML)")
    p.add_argument("--fake", action="store_true", help="use the built-in fake bench config")
    p.add_argument("--out", type=Path, default=Path("out/check"),
                   help="folder for the contact sheet (default: out/check)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.fake == (args.config is not None):
        print("ltc check: give either a CONFIG.toml or --fake", file=sys.stderr)
        return 2
    try:
        config = example_config("fake") if args.fake else load_config(args.config)
    except ConfigError as exc:
        print(f"ltc check: {exc}", file=sys.stderr)
        return 2
    report = run_check(config, args.out)
    print(json.dumps(report) if args.json else format_report(report))
    return 0 if report["ok"] else 1
