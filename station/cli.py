"""The ``ltc`` command line: one subcommand per module in ``station.commands``.

Every command is a thin wrapper over the Python API (``station``, ``sim``): it parses
arguments, calls the API, prints, and sets the exit code. Rules shared by every command:

- exit code 0 on success, 1 when the run failed (a device, the data, the disk), 2 when the
  command line is wrong (argparse's own errors, an option value, an output that exists
  without ``--force``), 3 for a bug, 130 when interrupted;
- an expected failure prints one line, ``ltc <command>: error: ...``, naming the file, field
  or device and what to do: no traceback, no Python class names. Expected failures are the
  error roots of the three packages (``drivers.DeviceError``, ``sim.SimError``,
  ``station.StationError``, of which ``UsageError`` exits 2), ``OSError`` and pydantic's
  validation errors;
- anything else (a numpy shape error, a ``KeyError``) is a bug: one line ``ltc <command>: bug:
  ...`` saying so, exit code 3; its traceback goes to stderr with ``ltc --debug`` (or
  ``LTC_DEBUG=1``) and always into the command's log file when it has one (a command sets
  ``args.log_file``: ``ltc run`` its ``DIR/run.log``);
- command modules import the heavy libraries inside ``run`` so ``ltc --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import os
import sys
from importlib import metadata
from pathlib import Path

from station.commands import add_command
from station.errors import StationError, UsageError, describe_os_error

EXIT_FAILED = 1  # the run failed: a device, the data, the disk
EXIT_USAGE = 2  # the command line is wrong
EXIT_BUG = 3  # an internal error: a bug to report
EXIT_INTERRUPTED = 130
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s %(message)s"  # as ``station.sequence``'s run.log

# The error roots that are expected failures (exit 1), by module and class name: looked up in
# sys.modules, so an error of a package that was never imported cannot match and ``ltc
# --help`` imports none of them.
EXPECTED_ROOTS = (("drivers.errors", "DeviceError"), ("sim.errors", "SimError"),
                  ("pydantic_core", "ValidationError"))

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
    "verify",
    "run",
    "render",
    "dataset",
    "scan",
    "patterns",
    "calibrate",
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
        epilog="Exit codes: 0 success, 1 the run failed, 2 bad usage, 3 a bug (an internal "
        "error: run again with --debug to see its traceback, and report it). "
        "'ltc COMMAND --help' documents each command.",
    )
    parser.add_argument("--version", action="version", version=f"ltc {version()}")
    parser.add_argument("--debug", action="store_true",
                        help="print the traceback of an internal error (exit 3) to stderr; "
                        "also LTC_DEBUG=1")
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


def _fail(command: str, message: str, code: int, kind: str = "error") -> int:
    print(f"ltc {command}: {kind}: {message}", file=sys.stderr)
    return code


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``ltc``; returns the process exit code."""
    args = build_parser().parse_args(argv)
    command = args.command
    try:
        return _print(args.module, args, args.module.run(args))
    except UsageError as exc:
        return _fail(command, str(exc), EXIT_USAGE)
    except KeyboardInterrupt:
        return _fail(command, "interrupted" + getattr(args, "resume_hint", ""), EXIT_INTERRUPTED)
    except OSError as exc:  # a full disk, a missing path: say what to do, and how to finish
        message = describe_os_error(exc)
        hint = getattr(args, "resume_hint", "")
        return _fail(command, message if "--resume" in message else message + hint, EXIT_FAILED)
    except Exception as exc:
        if _expected(exc):
            return _fail(command, _one_line(exc), EXIT_FAILED)
        return _bug(command, args, exc)


def _expected(exc: BaseException) -> bool:
    """Whether ``exc`` is an expected failure: a root of ours or a validation error."""
    if isinstance(exc, StationError):
        return True
    for module, name in EXPECTED_ROOTS:
        root = getattr(sys.modules.get(module), name, None)
        if root is not None and isinstance(exc, root):
            return True
    return False


def debug_wanted(args: argparse.Namespace) -> bool:
    """Whether tracebacks go to stderr: ``--debug``, or ``LTC_DEBUG`` set and not 0."""
    return bool(getattr(args, "debug", False)) or os.environ.get("LTC_DEBUG", "0") not in ("", "0")


def _bug(command: str, args: argparse.Namespace, exc: Exception) -> int:
    """Report an internal error: its traceback to the command's log file (always) and to
    stderr (with ``--debug``), then one line saying it is a bug; exit code 3."""
    kept = _keep_traceback(getattr(args, "log_file", None), command, exc)
    debug = debug_wanted(args)
    if debug:
        import traceback

        traceback.print_exception(exc, file=sys.stderr)
    where = [f"it is in {kept}"] if kept else []
    if not debug:
        where.insert(0, "run again with 'ltc --debug' (or LTC_DEBUG=1) to see it")
    return _fail(command, f"{type(exc).__name__}: {_one_line(exc)}; this is an internal error "
                 "(not a problem with the input or the bench): please report it with its "
                 f"traceback" + (f" ({'; '.join(where)})" if where else ""), EXIT_BUG, kind="bug")


def _keep_traceback(log_file: str | os.PathLike | None, command: str,
                    exc: Exception) -> Path | None:
    """Append the bug and its traceback to ``log_file`` in the run log's format; the path, or
    None when there is none (no log file, or its folder does not exist or is not writable)."""
    if log_file is None or not Path(log_file).parent.is_dir():
        return None
    record = logging.LogRecord("station.cli", logging.ERROR, __file__, 0, "ltc %s: bug: %s",
                               (command, _one_line(exc)), (type(exc), exc, exc.__traceback__))
    text = logging.Formatter(LOG_FORMAT).format(record)
    try:
        with open(log_file, "a", encoding="utf-8") as f:
            f.write(text + "\n")
    except OSError:  # a full disk: the one line on stderr still says what happened
        return None
    return Path(log_file)


def _one_line(exc: BaseException) -> str:
    """An expected error's message with its notes (what cleanup reported), on one line."""
    notes = "".join(f"; {n}" for n in getattr(exc, "__notes__", []))
    return " ".join(f"{exc}{notes}".split())


if __name__ == "__main__":
    sys.exit(main())
