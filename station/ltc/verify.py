"""Check a stored output for damage without changing it: a run store (every done frame
against its checksums), an LTC store (every done tile's chunks against ``tile_crc32c``) or a
lens file (every member's ZIP CRC-32 and the file's fields)."""

from __future__ import annotations

import json
import zipfile
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from sim.storage.errors import StorageError


class NotAStoreError(StorageError):
    """The path is none of the outputs ``verify_store`` knows; the message names it."""


@dataclass(frozen=True)
class StoreReport:
    """What :func:`verify_store` found.

    path : the output checked; kind : "run store", "LTC store" or "lens file";
    checked : frames (run store), chunks (LTC store) or members (lens file) read;
    damaged : one message per damaged item, naming it; incomplete : what is not written yet
    (not damage: a resumable run or reconstruction)."""

    path: str
    kind: str
    checked: int
    damaged: list[str] = field(default_factory=list)
    incomplete: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when nothing is damaged."""
        return not self.damaged

    def to_json(self) -> dict:
        return {**asdict(self), "ok": self.ok}


def store_kind(path: Path) -> str:
    """"run store", "LTC store" or "lens file", from the output's own marker."""
    from station.acquisition.run_store import FORMAT as RUN_FORMAT
    from station.ltc.store import FORMAT as LTC_FORMAT

    if path.is_dir():
        try:
            fmt = json.loads((path / "zarr.json").read_text()).get("attributes", {}).get("format")
        except (OSError, ValueError, AttributeError):
            fmt = None
        if fmt == RUN_FORMAT:
            return "run store"
        if fmt == LTC_FORMAT:
            return "LTC store"
    elif path.is_file() and zipfile.is_zipfile(path):
        return "lens file"
    if not path.exists():
        raise NotAStoreError(f"{path}: no such store or file")
    raise NotAStoreError(f"{path}: not a run store, an LTC store or a lens file (no "
                         "readable format marker)")


def verify_store(path: str | Path) -> StoreReport:
    """Read every checksummed byte of the output at ``path`` and report damage; changes
    nothing. Raises :class:`NotAStoreError` for a path that is none of the kinds."""
    path = Path(path)
    kind = store_kind(path)
    if kind == "run store":
        return _verify_run(path)
    if kind == "LTC store":
        return _verify_ltc(path)
    return _verify_lens(path)


def _verify_run(path: Path) -> StoreReport:
    from station.acquisition.run_store import RunStore, RunStoreError

    try:
        store = RunStore.open(path)
    except RunStoreError as exc:
        return StoreReport(str(path), "run store", 0, [str(exc)])
    done = store.done()
    damaged = [msg for _, _, msg in store.damaged_frames()]
    todo = int((~done).sum())
    return StoreReport(str(path), "run store", int(done.sum()), damaged,
                       [f"{todo} frame(s) not acquired yet; finish with `ltc acquire "
                        "--resume`"] if todo else [])


def _verify_ltc(path: Path) -> StoreReport:
    from station.ltc.checked import damaged_chunks
    from station.ltc.store import LtcStoreError, incomplete_depths, open_ltc_store

    try:
        g = open_ltc_store(path)
    except LtcStoreError as exc:
        return StoreReport(str(path), "LTC store", 0, [str(exc)])
    done = np.asarray(g["tile_done"][...], bool)
    damaged = damaged_chunks(path, g)
    todo = incomplete_depths(g)
    n_arrays = sum(1 for name in ("ltc", "origin", "gain", "noise", "lcd_xy") if name in g)
    return StoreReport(str(path), "LTC store", int(done.sum()) * n_arrays, damaged,
                       [f"depth(s) {todo} not complete; finish with `ltc reconstruct "
                        "--resume`"] if todo else [])


def _verify_lens(path: Path) -> StoreReport:
    from sim.optics.lens_file import load_lens

    damaged = []
    with zipfile.ZipFile(path) as zf:
        names = zf.namelist()
        for name in names:
            try:
                with zf.open(name) as f:
                    while f.read(1 << 24):
                        pass
            except (zipfile.BadZipFile, OSError, ValueError) as exc:
                damaged.append(f"{path}: member {name}: {exc}")
    if not damaged:
        try:
            load_lens(path)
        except (ValueError, OSError) as exc:
            damaged.append(str(exc))
    return StoreReport(str(path), "lens file", len(names), damaged)
