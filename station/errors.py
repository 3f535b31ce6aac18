"""The station's errors, and the kinds of failure the ``ltc`` command line turns into one line.

- :class:`StationError`: the root of every error the station raises on purpose (a device
  step, the data, a store, a lock); exit code 1. :class:`StationInputError` is an input the
  station refuses (a file, a field, a value) and is a ``ValueError`` too.
- :class:`UsageError`: what was typed is wrong (an option value, a missing option, an output
  that exists without ``--force``): exit code 2.
- ``drivers.DeviceError`` and ``sim.SimError`` (the other packages' roots), ``OSError`` (disk
  full, permission denied, path missing) and pydantic's validation errors are exit code 1 too.
- Anything else is a bug: exit code 3, see ``station.cli``.

Kept free of heavy imports: ``ltc --help`` loads it.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path


class StationError(RuntimeError):
    """Root of the station's errors: a step failed; the message names the device, file or step
    and what to do."""


class StationInputError(StationError, ValueError):
    """An input the station refuses: a file, a field or a value; the message names it."""


class UsageError(StationError, ValueError):
    """The command line is wrong; the message names the option and what to type (exit 2)."""


_HINTS = {
    errno.ENOSPC: "free some space, then run the command again (with --resume where it has one)",
    errno.EDQUOT: "free some space (disk quota), then run the command again",
    errno.EACCES: "check the permissions of the path",
    errno.EPERM: "check the permissions of the path",
    errno.ENOENT: "check the path",
    errno.EROFS: "the filesystem is read-only; write somewhere else",
    errno.EEXIST: "remove it, choose another path, or pass --force",
    errno.ENOTDIR: "a part of the path is a file, not a folder",
    errno.EISDIR: "the path is a folder, a file was expected",
}


def describe_os_error(exc: OSError) -> str:
    """One line for an ``OSError``: the path, what went wrong, and what to do."""
    path = exc.filename if exc.filename is not None else None
    reason = exc.strerror or str(exc)
    hint = _HINTS.get(exc.errno or -1)
    where = f"{path}: " if path is not None else ""
    if exc.filename2 is not None:
        where = f"{exc.filename} -> {exc.filename2}: "
    notes = "".join(f"; {n}" for n in getattr(exc, "__notes__", []))
    if exc.strerror is None and path is None:
        return str(exc) + (f"; {hint}" if hint else "") + notes
    return (f"{where}{reason[0].lower() + reason[1:] if reason else reason}"
            + (f"; {hint}" if hint else "") + notes)


def check_output(path: str | os.PathLike, force: bool, option: str = "--out") -> Path:
    """``path`` as a Path, refused (UsageError) when it exists and ``force`` is not set, or
    when ``force`` would replace something that is not a plain file (a folder, a device file,
    the working directory): the rules of :func:`station.outputs.check_output`, which commands
    writing a store, a folder or a file of a known kind call with that kind and their inputs.
    """
    from station.outputs import check_output as _check  # light; avoids an import cycle

    return _check(path, force, option)
