"""Print a commented example config, or check one.

Print a commented starting config (--example fake: the built-in fake bench, runs anywhere;
--example real: a Zaber stage, an LCD and a camera), or validate a config file (--check)
without touching any hardware: every field, the [fake] section, the pattern period and the
check code against the LCD where its size is known; values still as the real example gives
them where it marks them CHECK are warnings.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def arguments(p: argparse.ArgumentParser) -> None:
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--example", choices=("fake", "real"), help="print this example config")
    what.add_argument("--check", type=Path, metavar="FILE", help="validate this config file")


def run(args: argparse.Namespace) -> str:
    from station.acquisition.backend import preflight
    from station.acquisition.config import example_text, load_config

    if args.example:
        return example_text(args.example)
    config = load_config(args.check)
    warnings = preflight(config, str(args.check), args.check.read_text(encoding="utf-8"))
    return "".join(f"warning: {w}\n" for w in warnings) + (
        f"{args.check}: valid {config.backend} station config"
        f"{f' with {len(warnings)} warning(s)' if warnings else ''}: {len(config.depths_mm)} "
        f"depths {config.depths_mm} mm, P = {config.patterns.period}, "
        f"{config.patterns.steps}-step\n")
