"""The ``ltc`` subcommands, one module each: ``register(subparsers)`` adds the parser, ``run``
calls the Python API. Heavy libraries are imported inside ``run`` (``ltc --help`` stays fast).
Errors are raised, not printed: ``station.cli.main`` turns them into one line and an exit code.
"""

from __future__ import annotations

import argparse


def at_least(minimum: int):
    """An argparse type: an integer >= ``minimum`` (argparse reports a bad value, exit 2)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        return value

    return parse


def positive_float(text: str) -> float:
    """An argparse type: a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value
