"""The experiment folder across runs: starting or resuming it, the measured lenses' digests
and each finished position's durable record (``positions/NAME.npz`` then ``NAME.json``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from sim.storage.durable import durable_file, write_json
from sim.storage.lock import LOCK_NAME
from station.errors import StationError, UsageError
from station.experiment.config import ExperimentConfig
from station.experiment.objects import Position
from station.experiment.rows import PositionRow
from station.experiment.scan import Maps

POSITIONS = "positions"  # one finished position per file pair: NAME.npz, then NAME.json


def start_or_resume(cfg: ExperimentConfig, out: Path) -> bool:
    """Make ``out`` this experiment's folder, or take up the unfinished one there; returns
    whether it resumes. Refuses a finished experiment, one with another config, and a folder
    that is not an experiment's."""
    config_path = out / "experiment.json"
    data = cfg.model_dump(mode="json")
    if config_path.exists():
        if (out / "results.json").exists():
            raise UsageError(f"{out} holds a finished experiment ({out / 'results.json'}); "
                             "choose a new --out folder")
        try:
            same = json.loads(config_path.read_text(encoding="utf-8")) == data
        except (OSError, ValueError):
            same = False
        if not same:
            raise UsageError(f"{out} holds an experiment started with another config "
                             f"({config_path}); use a new --out, or the same config to "
                             "resume it")
        return True
    if out.exists() and any(p.name != LOCK_NAME for p in out.iterdir()):
        raise UsageError(f"--out {out} exists and is not an experiment's folder; choose a new "
                         "--out folder")
    out.mkdir(parents=True, exist_ok=True)
    write_json(config_path, data)
    return False


def _sha256(path: str | Path) -> str:
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


def check_lenses(out: Path, lens_paths: list[str]) -> None:
    """Record the measured lenses' digests (``out/lenses.json``) before the first position is
    scanned; on resume, refuse lenses that differ from those the scanned positions used."""
    record = out / "lenses.json"
    now = [{"file": str(p), "sha256": _sha256(p)} for p in lens_paths]
    if not record.exists():
        write_json(record, {"lenses": now})
        return
    before = json.loads(record.read_text(encoding="utf-8"))["lenses"]
    for i, (a, b) in enumerate(zip(before, now, strict=False)):
        if a["sha256"] != b["sha256"]:
            raise UsageError(f"{b['file']}: camera {i}'s measured lens differs from the one "
                             f"this experiment's positions were scanned with ({record}: "
                             f"{a['file']}); use a new --out")


def image_position(poss: list[Position]) -> str | None:
    """The position whose fringe images the report shows: the first large-defocus sphere or
    ball bar, else the first one."""
    objects = [p for p in poss if p.kind != "cad"]
    pick = [p for p in objects if p.defocus == "large"] or objects
    return pick[0].name if pick else None


def save_position(folder: Path, name: str, row: PositionRow, maps: Maps,
                  images: dict[str, np.ndarray] | None) -> None:
    """One finished position, durably: its arrays (``NAME.npz``: per map
    ``KEY.points_mm`` (n, 3) and ``KEY.distances_mm`` (n,), per model ``images.MODEL``),
    then its numbers (``NAME.json``), which mark it done."""
    folder.mkdir(exist_ok=True)
    arrays: dict[str, Any] = {}  # names and arrays for np.savez
    for key, (pts, d) in maps.items():
        arrays[f"{key}.points_mm"] = np.asarray(pts)
        arrays[f"{key}.distances_mm"] = np.asarray(d)
    for model, im in (images or {}).items():
        arrays[f"images.{model}"] = np.asarray(im)
    with durable_file(folder / f"{name}.npz", "wb") as f:
        np.savez(f, **arrays)
    write_json(folder / f"{name}.json", row.to_json())


def load_position(folder: Path, name: str
                  ) -> tuple[PositionRow, Maps, dict[str, np.ndarray] | None] | None:
    """A position finished in an earlier run (row, maps, images or None), or None."""
    import zipfile

    row_path, arr_path = folder / f"{name}.json", folder / f"{name}.npz"
    if not row_path.exists():
        return None
    again = f"delete {row_path} and {arr_path} to scan position {name} again"
    try:
        data = json.loads(row_path.read_text(encoding="utf-8"))
        row = PositionRow.from_json(data)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise StationError(f"{row_path}: unreadable ({exc}); {again}") from exc
    try:
        with np.load(arr_path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}  # every member's CRC-32 is checked here
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
        raise StationError(f"{arr_path}: unreadable ({exc}); {again}") from exc
    if row.name != name:
        raise StationError(f"{row_path}: holds position {row.name!r}, not {name}; {again}")
    maps = {k[: -len(".points_mm")]: (v, arrays[k[: -len(".points_mm")] + ".distances_mm"])
            for k, v in arrays.items() if k.endswith(".points_mm")}
    images = {k[len("images."):]: v for k, v in arrays.items() if k.startswith("images.")}
    return row, maps, images or None
