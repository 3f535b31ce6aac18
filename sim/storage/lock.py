"""One writer per store or output: an exclusive ``flock`` on a lock file naming its holder.

``StoreLock(folder)`` locks the store folder ``folder`` through ``folder / LOCK_NAME``;
``StoreLock.for_file(path)`` locks a single-file output (a lens file) through the hidden
``.NAME.lock`` beside it. On enter the lock file is opened (created if missing) and locked
with ``fcntl.flock(LOCK_EX | LOCK_NB)``; the kernel grants that lock to one open file at a
time and drops it when its holder's process ends, however it ends. The holder then writes
JSON ``{"host", "pid", "start_time", "token", "command"}`` into the file, so a second writer
is refused with :class:`StoreLockedError` naming the holder. On exit the file is removed
(while still locked) and the lock dropped.

A lock file left by a process that is gone is not held by anyone: the next writer takes it,
with no ``--force`` and no race (two takers cannot both hold a ``flock``). A taker that
locked a file just removed by its releasing holder notices (the path no longer names the
inode it locked) and starts again, so two writers never hold locks on two different files.
"""

from __future__ import annotations

import datetime as _dt
import fcntl
import json
import os
import socket
import sys
import uuid
from pathlib import Path

from sim.storage.errors import StorageError

LOCK_NAME = "writer.lock"
_RECORD_BYTES = 4096  # a lock record is read up to this size


class StoreLockedError(StorageError):
    """The store or output is locked by another writer; the message names the holder."""


def _flock(fd: int) -> bool:
    """Try to take the exclusive lock of open file ``fd`` without waiting."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


def current_command() -> str:
    """The command line of this process, as a user typed it (``ltc ...`` for the CLI)."""
    argv = list(sys.argv) or ["python"]
    head = Path(argv[0]).name
    if head in ("cli.py", "__main__.py", "ltc"):
        head = "ltc"
    return " ".join([head, *argv[1:]])[:300]


def describe_holder(held: dict | None) -> str:
    """One phrase naming a lock's holder from its record."""
    if not held:
        return "a writer whose lock record is not readable yet"
    text = (f"host {held.get('host', '?')}, PID {held.get('pid', '?')}, since "
            f"{held.get('start_time', '?')}")
    if held.get("command"):
        text += f", command `{held['command']}`"
    return text


class StoreLock:
    """Exclusive writer lock (see the module docstring); a context manager.

    path : the store folder (lock file ``path / LOCK_NAME``). lock_file : another lock file
    (:meth:`for_file`). force : accepted for the callers' ``--force``; a lock left by a
    process that is gone is taken over anyway, a live holder's never.
    """

    def __init__(self, path: str | os.PathLike, force: bool = False, *,
                 lock_file: str | os.PathLike | None = None) -> None:
        self.store = Path(path)
        self.path = Path(lock_file) if lock_file is not None else self.store / LOCK_NAME
        self.force = force
        self.record = {"host": socket.gethostname(), "pid": os.getpid(), "start_time": "",
                       "token": uuid.uuid4().hex, "command": current_command()}
        self.held = False
        self.previous: dict | None = None  # the record a gone holder left, when taken over
        self._fd: int | None = None

    @classmethod
    def for_file(cls, path: str | os.PathLike, force: bool = False) -> StoreLock:
        """The lock of a single-file output ``path``: ``.NAME.lock`` beside it."""
        path = Path(path)
        return cls(path, force, lock_file=path.with_name(f".{path.name}.lock"))

    def holder(self) -> dict | None:
        """The lock file's record, None when there is none ({} when it cannot be read)."""
        try:
            text = self.path.read_text()
        except FileNotFoundError:
            return None
        except OSError:
            return {}
        return _parse(text)

    def acquire(self) -> None:
        """Take the lock or raise :class:`StoreLockedError` naming the holder."""
        if not self.path.parent.is_dir():
            raise StoreLockedError(f"{self.store}: no such folder to lock ({self.path.parent})")
        for _ in range(20):
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            if not _flock(fd):
                held = _parse(os.pread(fd, _RECORD_BYTES, 0).decode("utf-8", "replace"))
                os.close(fd)
                raise StoreLockedError(f"{self.store}: locked by another writer "
                                       f"({describe_holder(held)}); wait for it to finish "
                                       "or stop it")
            try:
                same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if not same:  # its holder removed it as we opened it: lock the new one
                os.close(fd)
                continue
            old = _parse(os.pread(fd, _RECORD_BYTES, 0).decode("utf-8", "replace"))
            self.previous = old or None
            self.record["start_time"] = _dt.datetime.now(_dt.UTC).isoformat()
            data = json.dumps(self.record).encode()
            os.ftruncate(fd, 0)
            os.pwrite(fd, data, 0)
            os.fsync(fd)
            self._fd, self.held = fd, True
            return
        raise StoreLockedError(f"{self.path}: could not take the lock (other writers keep "
                               "taking and releasing it)")

    def check(self) -> None:
        """Raise unless this lock is held and its file is still the one at the path."""
        try:
            same = self._fd is not None and \
                os.stat(self.path).st_ino == os.fstat(self._fd).st_ino
        except FileNotFoundError:
            same = False
        if not (self.held and same):
            raise StoreLockedError(f"{self.store}: this writer's lock {self.path} is gone; "
                                   "another process removed it")

    def release(self) -> None:
        """Remove the lock file (while locked, when it is still this lock's) and unlock."""
        if self._fd is not None:
            try:
                if os.stat(self.path).st_ino == os.fstat(self._fd).st_ino:
                    self.path.unlink()
            except FileNotFoundError:
                pass
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
        self._fd, self.held = None, False

    def __enter__(self) -> StoreLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def _parse(text: str) -> dict:
    try:
        value = json.loads(text)
    except ValueError:
        return {}
    return value if isinstance(value, dict) else {}
