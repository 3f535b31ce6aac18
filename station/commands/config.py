"""``ltc config --example fake|real`` and ``ltc config --check FILE``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "config",
        help="print a commented example config, or check one",
        description="Print a commented starting config (--example fake: the built-in fake bench, "
        "runs anywhere; --example real: a Zaber stage, an LCD and a camera), or validate a "
        "config file (--check) without touching any hardware.",
    )
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--example", choices=("fake", "real"), help="print this example config")
    what.add_argument("--check", type=Path, metavar="FILE", help="validate this config file")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from station.acquisition.config import example_text, load_config

    if args.example:
        sys.stdout.write(example_text(args.example))
        return 0
    config = load_config(args.check)
    print(f"{args.check}: valid {config.backend} station config: {len(config.depths_mm)} depths "
          f"{config.depths_mm} mm, P = {config.patterns.period}, {config.patterns.steps}-step")
    return 0
