"""The ``ltc`` command line: one subcommand per module in ``station.commands``."""

from __future__ import annotations

import argparse
import importlib
import sys

# Each module defines ``register(subparsers)`` which adds its parser and sets ``func``.
COMMAND_MODULES = (
    "check",
    "config",
    "acquire",
    "gamma",
    "align",
    "reconstruct",
    "lens",
    "render",
    "scan",
    "measure",
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every available subcommand."""
    parser = argparse.ArgumentParser(
        prog="ltc",
        description="LTC measurement station and virtual fringe-projection scanner.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(f"station.commands.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``ltc``; returns the process exit code."""
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
