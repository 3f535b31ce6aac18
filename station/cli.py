"""The ``ltc`` command line: one subcommand per module in ``station.commands``.

Every command is a thin wrapper over the Python API (``station``, ``sim``): it parses
arguments, calls the API, prints, and sets the exit code. Rules shared by every command:

- exit code 0 on success, 1 when the run failed (a device, the data, the disk), 2 when the
  command line is wrong (argparse's own errors, an option value, an output that exists
  without ``--force``);
- an expected failure prints one line, ``ltc <command>: error: ...``, naming the file, field
  or device and what to do: no traceback, no Python class names;
- command modules import the heavy libraries inside ``run`` so ``ltc --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from importlib import metadata

from station.commands import add_command
from station.errors import StationError, UsageError, describe_os_error

# One module per subcommand, declared as ``station.commands`` describes.
COMMAND_MODULES = (
    "check",
    "cameras",
    "config",
    "acquire",
    "gamma",
    "align",
    "reconstruct",
    "lens",
    "run",
    "render",
    "scan",
    "measure",
    "validate",
    "experiment",
    "demo",
)


def version() -> str:
    """The installed package version ("unknown" when run from a source tree)."""
    try:
        return metadata.version("ltc-fpp")
    except metadata.PackageNotFoundError:
        return "unknown"


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every available subcommand."""
    parser = argparse.ArgumentParser(
        prog="ltc",
        description="LTC measurement station and virtual fringe-projection scanner.",
        epilog="Exit codes: 0 success, 1 the run failed, 2 bad usage. "
        "'ltc COMMAND --help' documents each command.",
    )
    parser.add_argument("--version", action="version", version=f"ltc {version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        add_command(sub, name, importlib.import_module(f"station.commands.{name}"))
    return parser


def _print(module, args: argparse.Namespace, result: dict | str | None) -> int:
    """Print what a command's ``run`` returned; the exit code (1 for a report not ``ok``)."""
    if isinstance(result, str):
        sys.stdout.write(result)
        return 0
    if result is None:
        return 0
    print(json.dumps(result) if getattr(args, "json", False) else module.text(result))
    return 0 if result.get("ok", True) else 1


def _fail(command: str, message: str, code: int) -> int:
    print(f"ltc {command}: error: {message}", file=sys.stderr)
    return code


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``ltc``; returns the process exit code."""
    args = build_parser().parse_args(argv)
    command = args.command
    try:
        return _print(args.module, args, args.module.run(args))
    except UsageError as exc:
        return _fail(command, str(exc), 2)
    except KeyboardInterrupt:
        return _fail(command, "interrupted" + getattr(args, "resume_hint", ""), 130)
    except OSError as exc:  # a full disk, a missing path: say what to do, and how to finish
        message = describe_os_error(exc)
        hint = getattr(args, "resume_hint", "")
        return _fail(command, message if "--resume" in message else message + hint, 1)
    except (ValueError, StationError) as exc:
        return _fail(command, _one_line(exc), 1)
    except Exception as exc:
        from drivers.interfaces import DeviceError  # imported here: --help stays light

        if not isinstance(exc, DeviceError):
            raise
        return _fail(command, _one_line(exc), 1)


def _one_line(exc: BaseException) -> str:
    """An expected error's message with its notes (what cleanup reported), on one line."""
    notes = "".join(f"; {n}" for n in getattr(exc, "__notes__", []))
    return " ".join(f"{exc}{notes}".split())


if __name__ == "__main__":
    sys.exit(main())
