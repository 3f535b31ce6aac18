"""One writer per store: a lock file in the store's folder naming its holder.

``StoreLock(path)`` is a context manager over the store folder ``path``: on enter it creates
``path / LOCK_NAME`` exclusively, holding JSON ``{"host", "pid", "start_time", "token"}``; on exit
it removes the file (only while it is still its own). A second writer is refused with a
:class:`StoreLockedError` naming the holder. A lock left by a process that is gone (same host,
PID not running) is stale: it is taken over only with ``force=True``, and the message says so. A
lock of a live process, or of another host (whose processes cannot be checked from here), is
never taken over; the message says which file to delete when the holder is known to be gone.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import socket
import uuid
from pathlib import Path

from station.errors import StationError

LOCK_NAME = "writer.lock"


class StoreLockedError(StationError):
    """The store is locked by another writer, or its lock is stale; the message names it."""


def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this host (a process we may not signal counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class StoreLock:
    """Exclusive writer lock of the store folder ``path`` (see the module docstring)."""

    def __init__(self, path: str | os.PathLike, force: bool = False) -> None:
        self.store = Path(path)
        self.path = self.store / LOCK_NAME
        self.force = force
        self.record = {"host": socket.gethostname(), "pid": os.getpid(),
                       "start_time": "", "token": uuid.uuid4().hex}
        self.held = False

    def holder(self) -> dict | None:
        """The lock file's record, None when there is none ({} when it cannot be read)."""
        try:
            return json.loads(self.path.read_text())
        except FileNotFoundError:
            return None
        except (OSError, ValueError):
            return {}

    def acquire(self) -> None:
        if not self.store.is_dir():
            raise StoreLockedError(f"{self.store}: no such store folder to lock")
        for _ in range(3):
            if self._create():
                return
            held = self.holder()
            if held is None:
                continue  # released in between: try again
            self._take_over_or_refuse(held)
        raise StoreLockedError(f"{self.path}: could not take the lock (other writers keep "
                               "taking it)")

    def _create(self) -> bool:
        self.record["start_time"] = _dt.datetime.now(_dt.UTC).isoformat()
        tmp = self.store / f".{LOCK_NAME}.{self.record['token']}"
        tmp.write_text(json.dumps(self.record))
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        try:
            os.link(tmp, self.path)  # atomic, fails when a lock exists; the file is complete
        except FileExistsError:
            return False
        finally:
            tmp.unlink()
        self.held = True
        return True

    def _take_over_or_refuse(self, held: dict) -> None:
        who = (f"host {held.get('host', '?')}, PID {held.get('pid', '?')}, since "
               f"{held.get('start_time', '?')}") if held else "an unreadable lock file"
        host, pid = held.get("host"), held.get("pid")
        if host == socket.gethostname() and isinstance(pid, int) and not _pid_alive(pid):
            if not self.force:
                raise StoreLockedError(
                    f"{self.store}: stale lock of a process that is gone ({who}); pass --force "
                    "to take it over")
            stale = self.store / f".{LOCK_NAME}.stale.{self.record['token']}"
            try:
                os.rename(self.path, stale)  # only one taker wins the rename
            except FileNotFoundError:
                return
            stale.unlink()
            return
        if held and host != socket.gethostname():
            raise StoreLockedError(
                f"{self.store}: locked by another writer ({who}); if that process is gone, "
                f"delete {self.path} and run again")
        if not held:
            raise StoreLockedError(f"{self.store}: locked ({who}: {self.path}); if no other "
                                   "writer runs, delete it and run again")
        raise StoreLockedError(f"{self.store}: locked by another writer ({who}); wait for it "
                               "to finish or stop it")

    def release(self) -> None:
        """Remove the lock file when it is still this lock's."""
        if self.held and (self.holder() or {}).get("token") == self.record["token"]:
            self.path.unlink(missing_ok=True)
        self.held = False

    def __enter__(self) -> StoreLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
