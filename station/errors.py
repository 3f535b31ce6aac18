"""Error kinds the ``ltc`` command line turns into one line and an exit code.

- :class:`UsageError`: what was typed is wrong (an option value, a missing option, an output
  that exists without ``--force``): exit code 2.
- :class:`StationError`: a run failed for a reason its message names (a device, the data, the
  disk): exit code 1. ``ValueError`` (bad data in a file, a corrupt store), ``OSError`` (disk
  full, permission denied, path missing) and ``drivers.DeviceError`` are exit code 1 too.

Kept free of heavy imports: ``ltc --help`` loads it.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path


class UsageError(ValueError):
    """The command line is wrong; the message names the option and what to type (exit 2)."""


class StationError(RuntimeError):
    """A station step failed; the message names the device, file or step and what to do."""


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
