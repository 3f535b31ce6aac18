"""The ``ltc`` subcommands, one module each, declared rather than wired by hand.

A command module holds:

- its docstring: the first paragraph is the one-line help of ``ltc --help``, the rest the
  description of ``ltc COMMAND --help`` (plain text, no markup);
- ``OPTIONS``: the shared options it takes, in order, each mapped to its help text or ``None``
  for the shared default (see :data:`SHARED`);
- optionally ``arguments(parser)``: the command's own arguments;
- ``run(args)``: calls the Python API and returns what to print: a report ``dict`` (printed as
  one JSON object with ``--json``, else through the module's ``text(report)``; a report with
  ``"ok": False`` exits 1) or a ``str`` printed as it is.

Heavy libraries are imported inside ``run`` (``ltc --help`` stays fast). Errors are raised,
not printed: ``station.cli.main`` turns them into one line and an exit code.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from types import ModuleType
from typing import Any


def add_command(sub: argparse._SubParsersAction, name: str, module: ModuleType) -> None:
    """Add the subcommand ``name`` declared by ``module`` (see the package docstring)."""
    summary, _, description = (module.__doc__ or name).strip().partition("\n\n")
    parser = sub.add_parser(name, help=" ".join(summary.split()).rstrip("."),
                            description=" ".join(f"{summary}\n{description}".split()))
    for option, help_text in getattr(module, "OPTIONS", {}).items():
        flags, keywords, default_help = SHARED[option]
        parser.add_argument(*flags, help=help_text or default_help, **keywords)
    if hasattr(module, "arguments"):
        module.arguments(parser)
    parser.set_defaults(module=module)


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


# The options several commands share: name -> (flags, argparse keywords, default help).
SHARED: dict[str, tuple[tuple[str, ...], dict[str, Any], str]] = {
    "config": (("config",), {"type": Path}, "station config (TOML)"),
    "out": (("--out",), {"type": Path, "required": True}, "output to create"),
    "force": (("--force",), {"action": "store_true"}, "overwrite --out if it exists"),
    "json": (("--json",), {"action": "store_true"}, "print one JSON object"),
    "quiet": (("--quiet",), {"action": "store_true"}, "no progress bars"),
    # the compute engines (station.compute)
    "workers": (("--workers",), {"type": at_least(1), "default": None, "metavar": "N"},
                "worker processes (default: every core; 1: in this process)"),
    "dask": (("--dask",), {"action": "store_true"},
             "compute on a local Dask cluster of --workers processes"),
    "scheduler": (("--scheduler",), {"metavar": "ADDRESS"},
                  "compute on an existing Dask cluster (e.g. tcp://host:8786); the stores "
                  "must be on a path every worker can read"),
}
