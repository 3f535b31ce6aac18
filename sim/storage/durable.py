"""Durable writes: the one way this project puts a file or a folder on disk so that a crash
leaves either the old state or the complete new one, never a part.

A new file is written under a temporary name beside its final path (``.NAME.<id>.partial``),
flushed to disk (``fsync``), renamed into place (atomic on POSIX) and its folder's entry
flushed (``fsync`` of the folder). Large page-aligned numpy buffers go straight to the device
(``O_DIRECT``); a filesystem that refuses it gets the same bytes through the page cache.
Stores that write many files per step (the run store) skip the per-file ``fsync`` and make a
batch durable with one :func:`barrier`.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import fcntl
import functools
import os
import platform
import shutil
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from matplotlib.figure import Figure

DIRECT_ALIGN = 4096  # bytes: address and length a buffer needs to bypass the page cache


def fsync_path(path: str | os.PathLike) -> None:
    """Flush a file's data (or a folder's entries) to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@functools.cache
def _libc() -> object:
    try:
        return ctypes.CDLL(None, use_errno=True) if platform.system() == "Linux" else None
    except OSError:
        return None


def barrier(root: Path, written: list[Path]) -> None:
    """Make everything written so far durable before what comes next: one ``syncfs`` of the
    filesystem holding ``root`` on Linux (one journal commit, about as fast as one fsync),
    else an fsync of each file in ``written`` and of its folder."""
    syncfs = getattr(_libc(), "syncfs", None)
    if syncfs is not None:
        fd = os.open(root, os.O_RDONLY)
        try:
            if syncfs(fd) != 0:
                err = ctypes.get_errno()
                raise OSError(err, os.strerror(err), str(root))
        finally:
            os.close(fd)
        return
    for path in written:
        fsync_path(path)
        fsync_path(path.parent)


def write_all(path: str | os.PathLike, fd: int, parts: list, offset: int | None = None) -> None:
    """Write every buffer of ``parts`` to the open file ``fd`` (``path``), at its position or
    at byte ``offset``; an OSError names ``path``."""
    try:
        for part in (memoryview(p).cast("B") for p in parts):
            while part:
                n = os.write(fd, part) if offset is None else os.pwrite(fd, part, offset)
                part = part[n:]
                offset = None if offset is None else offset + n
    except OSError as exc:
        if exc.filename is None:
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        raise


def temporary_name(path: Path, kind: str = "partial") -> Path:
    """A hidden name beside ``path``, unique to one writer: ``.NAME.<id>.<kind>``."""
    return path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.{kind}")


@contextlib.contextmanager
def new_file(path: Path, flags: int = 0, sync: bool = False) -> Iterator[int]:
    """A new file written atomically: yields the descriptor of a temporary file beside
    ``path`` (opened with extra ``flags``; one the filesystem refuses with ``EINVAL`` is
    dropped), renamed to ``path`` when the block completes (removed if it raises).
    ``sync``: fsync the file before the rename and its folder after (else durability comes
    from the caller's :func:`barrier`)."""
    tmp = temporary_name(path)
    try:
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | flags, 0o644)
        except OSError as exc:
            if not flags or exc.errno != errno.EINVAL:
                raise
            tmp.unlink(missing_ok=True)  # some kernels create the file, then refuse the flag
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        try:
            yield fd
            if sync:
                os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
        if sync:
            fsync_path(path.parent)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def aligned_empty(shape: tuple[int, ...], dtype: np.dtype | type) -> np.ndarray:
    """An uninitialised C-contiguous array whose memory starts on a ``DIRECT_ALIGN`` boundary
    (what :func:`write_new_file` can write straight to the device)."""
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    raw = np.empty(nbytes + DIRECT_ALIGN, np.uint8)
    skip = -raw.ctypes.data % DIRECT_ALIGN
    return raw[skip : skip + nbytes].view(dtype).reshape(shape)


def _direct_buffer(parts: list) -> memoryview | None:
    """The bytes of ``parts`` if they can be written with ``O_DIRECT`` (one aligned
    C-contiguous array of a whole number of ``DIRECT_ALIGN`` blocks on Linux), else None."""
    if len(parts) != 1 or not hasattr(os, "O_DIRECT") or not isinstance(parts[0], np.ndarray):
        return None
    a = parts[0]
    if not a.flags.c_contiguous or a.nbytes == 0 or a.nbytes % DIRECT_ALIGN or \
            a.ctypes.data % DIRECT_ALIGN:
        return None
    return a.data.cast("B")


def write_new_file(path: Path, parts: list, sync: bool = False) -> None:
    """Write a new file of ``parts`` (bytes-like) atomically (:func:`new_file`); an OSError
    names the file. ``sync``: durable on return (else at the caller's :func:`barrier`).

    One C-contiguous array whose address and size are multiples of ``DIRECT_ALIGN`` (an LTC
    tile from :func:`aligned_empty`) goes straight to the device (``O_DIRECT``): the page
    cache's copy of new pages cost as much kernel CPU per LTC pixel as the pixel's inverse
    FFT. A filesystem that refuses ``O_DIRECT`` (``EINVAL``) gets the same bytes through the
    page cache."""
    direct = _direct_buffer(parts)
    with new_file(path, os.O_DIRECT if direct is not None else 0, sync=sync) as fd:
        if direct is None:
            write_all(path, fd, parts)
            return
        try:
            write_all(path, fd, [direct])
        except OSError as exc:
            if exc.errno != errno.EINVAL:
                raise
            fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) & ~os.O_DIRECT)
            write_all(path, fd, [direct], 0)


@contextlib.contextmanager
def durable_file(path: str | os.PathLike, mode: str = "w",
                 exclusive: bool = False) -> Iterator[IO]:
    """A file object for a new file written durably: the block writes a temporary file
    beside ``path`` (text modes UTF-8), which is fsynced, renamed to ``path`` and its folder
    fsynced when the block completes; removed if the block raises. ``exclusive``: refuse
    (``FileExistsError`` naming ``path``) if ``path`` exists when the block completes,
    instead of replacing it."""
    path = Path(path)
    tmp = temporary_name(path)
    try:
        with open(tmp, mode, encoding=None if "b" in mode else "utf-8") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        if exclusive:
            try:
                os.link(tmp, path)  # atomic: fails when ``path`` exists
            except FileExistsError as exc:
                raise FileExistsError(exc.errno, "appeared while this output was written "
                                      "(another writer?); not replaced", str(path)) from None
            tmp.unlink()
        else:
            os.replace(tmp, path)
        fsync_path(path.parent)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_json(path: str | os.PathLike, data: object) -> None:
    """Write ``data`` as indented JSON, durably (:func:`durable_file`)."""
    import json

    with durable_file(path) as f:
        json.dump(data, f, indent=2)


def durable_figure(fig: Figure, path: str | os.PathLike, **savefig: Any) -> Path:
    """Save a matplotlib figure durably (format from the path's suffix; ``savefig``: more
    ``Figure.savefig`` keywords); returns the path."""
    path = Path(path)
    with durable_file(path, "wb") as f:
        fig.savefig(f, format=path.suffix.lstrip(".") or "png", **savefig)
    return path


def sync_tree(root: Path, threads: int = 1) -> None:
    """fsync every file under ``root``, then every folder, deepest first and ``root`` last
    (a folder built before its rename). ``threads`` > 1 fsyncs the files on that many
    threads: a journalling file system commits concurrent fsyncs together, where one after
    the other each waits for its own commit."""
    files: list[Path] = []
    folders: list[Path] = []
    for folder, _, names in os.walk(root):
        files += [Path(folder) / n for n in names]
        folders.append(Path(folder))
    if threads > 1 and len(files) > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(fsync_path, files))
    else:
        for f in files:
            fsync_path(f)
    for folder_path in reversed(folders):
        fsync_path(folder_path)


def publish(tmp: Path, final: Path, replace: bool = False) -> None:
    """Rename a complete file or folder ``tmp`` to ``final`` and flush the folder's entry.
    Without ``replace`` an existing ``final`` is refused (``FileExistsError``, checked just
    before the rename); with it, an old file is replaced atomically and an old folder is
    moved aside, the new one renamed in, then the old one removed."""
    if final.exists() or final.is_symlink():
        if not replace:
            raise FileExistsError(errno.EEXIST, "exists; refusing to replace it", str(final))
        if final.is_dir() and not final.is_symlink():
            old = temporary_name(final, "old")
            os.rename(final, old)
            os.rename(tmp, final)
            fsync_path(final.parent)
            shutil.rmtree(old, ignore_errors=True)
            return
    if replace or tmp.is_dir():
        os.replace(tmp, final)  # a folder never replaces a non-empty folder
    else:
        os.link(tmp, final)  # fails if ``final`` appeared since the check
        tmp.unlink()
    fsync_path(final.parent)


def start_writeback(fd: int, offset: int, nbytes: int) -> None:
    """Ask the kernel to start writing a file's byte range to disk now, without waiting
    (Linux ``sync_file_range(SYNC_FILE_RANGE_WRITE)``; elsewhere nothing). Durability still
    comes from a :func:`barrier` only."""
    fn = _sync_file_range()
    if fn is not None:
        fn(fd, offset, nbytes, 2)  # SYNC_FILE_RANGE_WRITE; a failure only loses the head start


@functools.cache
def _sync_file_range() -> Callable[[int, int, int, int], int] | None:
    """libc's ``sync_file_range`` with its argument types set, or None where there is none."""
    fn = getattr(_libc(), "sync_file_range", None)
    if fn is not None:
        fn.argtypes = [ctypes.c_int, ctypes.c_int64, ctypes.c_int64, ctypes.c_uint]
        fn.restype = ctypes.c_int
    return fn
