"""Where a command writes its output, and what ``--force`` may replace there.

The one rule of every command with ``--out`` (and ``--force``):

- an output that exists is never replaced without ``--force``;
- ``--force`` replaces only an output of the same kind, recognised by its own marker (a run
  store's or an LTC store's ``format`` attribute, a render folder's ``summary.json`` beside
  ``render.zarr``, a lens file's ``format`` entry, a PLY header, a PNG signature);
- it never replaces one of the command's own inputs or a folder that holds one, and never
  writes inside an input store (zarr); nor a device file, a FIFO, a socket, a symbolic link,
  the working directory or a folder above it;
- it replaces by writing the new output beside the old one (in the hidden staging folder
  ``.NAME.force/``) and exchanging the two at the end, so a failed or killed ``--force`` run
  leaves the old output as it was (:func:`staged`).

Refusals are :class:`station.errors.UsageError` (exit code 2) naming the option and the path.
Kept free of heavy imports: command modules call it before loading the libraries.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import json
import os
import shutil
import stat
import zipfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from station.errors import UsageError

STAGING_MARKER = "force.json"  # in .NAME.force/: what is staged there, by whom


def _zarr_format(path: Path) -> str | None:
    """The ``format`` attribute in ``path/zarr.json`` (zarr v3 root group), or None."""
    try:
        meta = json.loads((path / "zarr.json").read_text(encoding="utf-8"))
        value = meta.get("attributes", {}).get("format")
    except (OSError, ValueError, AttributeError):
        return None
    return value if isinstance(value, str) else None


def _is_run_store(path: Path) -> bool:
    return path.is_dir() and _zarr_format(path) == "ltc-run-store"


def _is_ltc_store(path: Path) -> bool:
    return path.is_dir() and _zarr_format(path) == "ltc-store"


def _is_render_folder(path: Path) -> bool:
    """``summary.json`` and ``render.zarr`` and nothing but ``camera_<i>`` folders beside them."""
    if not path.is_dir() or not (path / "render.zarr" / "zarr.json").is_file():
        return False
    if not (path / "summary.json").is_file():
        return False
    return all(p.name in ("render.zarr", "summary.json")
               or (p.name.startswith("camera_") and p.name[7:].isdigit() and p.is_dir())
               for p in path.iterdir())


def _is_lens_file(path: Path) -> bool:
    """A ``.npz`` whose ``format`` entry is the measured-lens format (read without pickle)."""
    try:
        with zipfile.ZipFile(path) as z, z.open("format.npy") as f:
            return b"ltc-fpp-measured-lens" in f.read(4096)
    except (OSError, KeyError, zipfile.BadZipFile):
        return False


def _starts_with(signature: bytes) -> Callable[[Path], bool]:
    def check(path: Path) -> bool:
        try:
            with open(path, "rb") as f:
                return f.read(len(signature)) == signature
        except OSError:
            return False

    return check


def _is_check_folder(path: Path) -> bool:
    """An ``ltc check`` folder: its contact sheet(s) and reports, nothing else."""
    return path.is_dir() and all(p.is_file() and p.suffix in (".png", ".json")
                                 and p.name.startswith("check") for p in path.iterdir())


@dataclass(frozen=True)
class OutputKind:
    """What a command writes: a name for messages and how to recognise one that exists."""

    name: str
    recognise: Callable[[Path], bool]
    folder: bool


RUN_STORE = OutputKind("run store", _is_run_store, True)
LTC_STORE = OutputKind("LTC store", _is_ltc_store, True)
RENDER_FOLDER = OutputKind("render folder", _is_render_folder, True)
LENS_FILE = OutputKind("lens file", _is_lens_file, False)
PLY_FILE = OutputKind("PLY point cloud", _starts_with(b"ply"), False)
PNG_FILE = OutputKind("PNG image", _starts_with(b"\x89PNG\r\n\x1a\n"), False)
CHECK_FOLDER = OutputKind("ltc check folder", _is_check_folder, True)


def _is_calibration_capture(path: Path) -> bool:
    """``capture.json`` and nothing but ``pose_<n>`` folders beside it."""
    if not path.is_dir() or not (path / "capture.json").is_file():
        return False
    return all(p.name == "capture.json"
               or (p.name.startswith("pose_") and p.name[5:].isdigit() and p.is_dir())
               for p in path.iterdir())


CALIBRATION_CAPTURE = OutputKind("calibration capture", _is_calibration_capture, True)
def _is_lut(path: Path) -> bool:
    """A display LUT as ``ltc gamma`` writes it: ``.npy``, or text of one integer per line."""
    if _starts_with(b"\x93NUMPY")(path):
        return True
    try:
        if path.stat().st_size > 1 << 16:
            return False
        lines = path.read_text(encoding="ascii").split()
    except (OSError, UnicodeDecodeError):
        return False
    return bool(lines) and all(v.isdigit() for v in lines)


LUT_FILE = OutputKind("display LUT file", _is_lut, False)
FIGURES_FOLDER = OutputKind("figures folder (PNG files only)",
                            lambda p: p.is_dir() and all(q.is_file() and q.suffix == ".png"
                                                         for q in p.iterdir()), True)


def _special(path: Path) -> str | None:
    """What ``path`` is when it is neither a plain file nor a folder (None otherwise)."""
    st = path.lstat()
    if stat.S_ISLNK(st.st_mode):
        return "a symbolic link"
    if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode):
        return "a device file"
    if stat.S_ISFIFO(st.st_mode):
        return "a FIFO"
    if stat.S_ISSOCK(st.st_mode):
        return "a socket"
    if not (stat.S_ISREG(st.st_mode) or stat.S_ISDIR(st.st_mode)):
        return "not a plain file or folder"
    return None


def _is_store_or_inside(target: Path, src: Path) -> bool:
    """Whether the input folder ``src`` (or a folder of it above ``target``) is a zarr store,
    into which no output may go (a new file beside an input in a plain folder may)."""
    folder = target.parent
    while _within(folder, src):
        if (folder / "zarr.json").is_file():
            return True
        if folder == src:
            break
        folder = folder.parent
    return False


def _a(name: str) -> str:
    return ("an " if name[0] in "aeiouAEIOLR" else "a ") + name


def _within(inner: Path, outer: Path) -> bool:
    return inner == outer or outer in inner.parents


def check_output(path: str | os.PathLike, force: bool, option: str = "--out", *,
                 kind: OutputKind | None = None, inputs: Iterable[str | os.PathLike] = (),
                 parent_must_exist: bool = False) -> Path:
    """``path`` as a Path once the output rules (module docstring) allow writing there.

    kind : what the command writes; with ``force`` an existing path is replaced only when it
        is one (None: any plain file, for commands that write one file of no fixed format).
    inputs : the command's inputs; ``path`` may not be one, hold one or lie inside an input
        store.
    parent_must_exist : refuse a path whose folder does not exist (rather than creating it).
    Raises :class:`UsageError` naming ``option`` and the path.
    """
    path = Path(path)
    where = f"{option} {path}"
    target = path.resolve()
    for item in inputs:
        src = Path(item).resolve()
        in_store = _within(target, src) and _is_store_or_inside(target, src)
        if target == src or in_store or _within(src, target):
            rel = ("is" if target == src else "is inside" if in_store else "holds")
            raise UsageError(f"{where} {rel} the command's input {item}; write the output "
                             "somewhere else (nothing was changed)")
    if parent_must_exist and not path.parent.resolve().is_dir():
        raise UsageError(f"{where}: the folder {path.parent} does not exist; create it first or "
                         "choose another path")
    exists = path.exists() or path.is_symlink()
    if not exists:
        return path
    if not force:
        raise UsageError(f"{where} exists; pass --force to overwrite it, or choose another path")
    special = _special(path)
    what = kind.name if kind is not None else "plain file"
    if special is not None:
        raise UsageError(f"{where} is {special}; --force replaces only {_a(what)}, never this "
                         "(nothing was changed); choose another path")
    cwd = Path.cwd().resolve()
    if _within(cwd, target):
        raise UsageError(f"{where} is the working directory or a folder above it; --force "
                         "never replaces it (nothing was changed); choose another path")
    if kind is None:
        ok = path.is_file()
    else:
        ok = kind.recognise(path)
    if not ok:
        has = "a folder" if path.is_dir() else "a file"
        raise UsageError(f"{where} is {has} but not {_a(what)}; --force replaces only {_a(what)} "
                         "(nothing was changed); remove it yourself or choose another path")
    return path


def staging_folder(path: Path) -> Path:
    """The hidden sibling folder where a ``--force`` run writes the new ``path``."""
    return path.with_name(f".{path.name}.force")


def _clear_stale_staging(staging: Path) -> None:
    """Remove a staging folder a killed ``--force`` run left (recognised by its marker)."""
    if not (staging.exists() or staging.is_symlink()):
        return
    if _special(staging) is not None or not (staging / STAGING_MARKER).is_file():
        raise UsageError(f"{staging} exists and is not a staging folder of ltc; remove it "
                         "yourself (nothing was changed)")
    shutil.rmtree(staging)


_RENAME_EXCHANGE = 2


def _exchange(a: Path, b: Path) -> None:
    """Swap the names ``a`` and ``b`` atomically (Linux ``renameat2``); elsewhere two renames."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        renameat2 = None
    if renameat2 is not None:
        AT_FDCWD = -100
        rc = renameat2(AT_FDCWD, os.fsencode(a), AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)
        if rc == 0:
            return
        err = ctypes.get_errno()
        if err not in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP):
            raise OSError(err, os.strerror(err), str(a), None, str(b))
    tmp = a.with_name(a.name + ".old")
    os.rename(b, tmp)
    os.rename(a, b)
    os.rename(tmp, a)


def _name(exc: OSError, written: Path, path: Path) -> None:
    """Make ``exc`` name the output ``path`` (written as ``written``) when it names no file (a
    full disk seen by a library) or a file in the staging folder, which is gone."""
    if exc.errno is None:  # an error built from a message alone names what it means
        return
    name = None if exc.filename is None else str(exc.filename)
    if name is None or name == str(written) or name.startswith(f"{written}{os.sep}"):
        exc.filename = str(path) + ("" if name is None else name[len(str(written)):])
        if exc.strerror is None and exc.errno is not None:
            exc.strerror = os.strerror(exc.errno)



@contextlib.contextmanager
def naming(path: str | os.PathLike) -> Iterator[None]:
    """An ``OSError`` raised inside that names no file (a full disk seen by a library) is
    made to name the output ``path``."""
    try:
        yield
    except OSError as exc:
        _name(exc, Path(path), Path(path))
        raise


@contextlib.contextmanager
def staged(path: str | os.PathLike, kind: OutputKind, always: bool = False) -> Iterator[Path]:
    """Yield where to write the output ``path``: ``path`` itself when nothing is there (unless
    ``always``), else ``.NAME.force/NAME`` beside it, renamed into place (exchanged with the
    old output, which is then removed) when the block ends without an error. An error or a
    kill inside the block leaves the old output untouched (and, with ``always``, nothing at
    ``path``: the command can simply run again); the staging folder of a killed run is
    removed by the next run. An ``OSError`` naming no file is made to name ``path``. Call
    :func:`check_output` first."""
    path = Path(path)
    staging = staging_folder(path)
    if not always and not (path.exists() or path.is_symlink()):
        try:
            yield path
        except OSError as exc:
            _name(exc, path, path)
            raise
        return
    if kind.folder and (path / "writer.lock").exists():
        from sim.storage.lock import StoreLock  # the store's own writer lock

        with StoreLock(path, force=True):  # refuses an output a live writer holds
            pass
    _clear_stale_staging(staging)
    staging.mkdir()
    (staging / STAGING_MARKER).write_text(json.dumps(
        {"replaces": str(path), "kind": kind.name, "pid": os.getpid()}) + "\n")
    new = staging / path.name
    try:
        yield new
    except BaseException as exc:
        shutil.rmtree(staging, ignore_errors=True)
        if isinstance(exc, OSError):
            _name(exc, new, path)
        raise
    if not (new.exists() or new.is_symlink()):
        shutil.rmtree(staging, ignore_errors=True)
        return
    from sim.storage.durable import fsync_path, sync_tree

    if new.is_dir() and not new.is_symlink():  # every file of the new output on the disk
        sync_tree(new)
    elif not new.is_symlink():
        fsync_path(new)
    if (path.exists() or path.is_symlink()) and (kind.folder or path.is_dir()):
        _exchange(new, path)  # ``new`` now names the old output, inside the staging folder
    else:
        os.replace(new, path)
    fsync_path(path.parent.resolve())
    shutil.rmtree(staging, ignore_errors=True)
