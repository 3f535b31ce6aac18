"""Fringe data sets at scale: ``ltc dataset CONFIG --out DIR --samples N`` from Python.

The samples and the format are ``sim.dataset``'s; this module runs them on the project's
compute engine (``station.compute``: every local core by default, one process, or Dask)
and keeps the run whole:

- bad input is refused before anything is written: a missing or unreadable mesh, an empty
  mesh folder, a lens file for another camera, a rig whose common working volume cannot
  hold the largest object (one line each, naming the file or field);
- one writer at a time (the data set's lock);
- resumable: run the same command again. Samples already written are kept when their arrays
  still match their checksum, and made again otherwise; a sample is written whole or not at
  all, so a killed run, or a full disk, loses no finished sample;
- deterministic: sample i is a pure function of (config, seed, i), so the data set is the
  same bit for bit whatever the engine, the worker count or the interruptions.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from station.compute import Engine, run_ordered
from station.errors import UsageError

MANIFEST_EVERY_S = 30.0  # the manifest is rewritten at most this often during a run


@dataclass
class DatasetReport:
    """What a data-set run did: samples asked, made and kept, time, engine, splits, bytes."""

    out: str
    samples: int
    made: int
    kept: int
    seconds: float
    samples_per_second: float
    engine: str
    splits: dict[str, int] = field(default_factory=dict)
    bytes: int = 0
    ok: bool = True

    def to_json(self) -> dict:
        return asdict(self)


def software_version() -> str:
    """The installed package's version ("unknown" from a source tree)."""
    from importlib import metadata

    try:
        return metadata.version("ltc-fpp")
    except metadata.PackageNotFoundError:
        return "unknown"


def preflight(cfg, rig, where: str) -> None:
    """Refuse bad input before anything is written (errors name ``where`` and the field or
    file): the mesh folder and every mesh in it, the measured lens files, and the working
    volume."""
    from sim.dataset.objects import check_mesh, mesh_files
    from sim.dataset.randomise import check_fits

    src = cfg.objects
    if src.mesh_folder is not None and src.mesh_fraction > 0:
        try:
            for f in mesh_files(src.mesh_folder):
                check_mesh(f)
        except (OSError, ValueError) as exc:
            raise ValueError(f"{where}: field 'objects.mesh_folder': {exc}") from exc
    from sim.dataset.config import MeasuredChoice
    from sim.dataset.generate import build_lens
    from sim.dataset.randomise import MeasuredLensDraw

    for i, choices in enumerate(cfg.lenses):
        for j, c in enumerate(choices):
            if isinstance(c, MeasuredChoice) and c.weight > 0:
                if not c.path.is_file():
                    raise ValueError(f"{where}: field 'lenses.{i}.{j}.path': lens file "
                                     f"{c.path} not found")
                try:
                    build_lens(MeasuredLensDraw(path=str(c.path)), rig.cameras[i])
                except (OSError, ValueError) as exc:
                    raise ValueError(f"{where}: field 'lenses.{i}.{j}.path': {exc}") from exc
    check_fits(rig, cfg, where)


def _manifest(cfg, rig, samples: dict) -> dict:
    from sim.dataset.store import FORMAT, FORMAT_VERSION

    return {"format": FORMAT, "format_version": FORMAT_VERSION,
            "software_version": software_version(),
            "config": json.loads(cfg.model_dump_json()), "rig": json.loads(rig.model_dump_json()),
            "samples": {str(k): samples[k] for k in sorted(samples)}}


def _same_run(existing: dict, fresh: dict) -> bool:
    return all(existing.get(k) == fresh[k] for k in ("format", "format_version", "config", "rig"))


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def generate_dataset(config, out: str | Path, samples: int, *, workers: int | None = None,
                     dask: bool = False, scheduler: str | None = None, progress: bool = True,
                     force: bool = False) -> DatasetReport:
    """Make (or finish) the data set ``out`` of ``samples`` samples of ``config`` (a config
    file path, or a ``sim.dataset.DatasetConfig``). ``out`` may exist only as a data set of
    the same config and rig (it is then continued) unless ``force`` (it is then replaced)."""
    from tqdm import tqdm

    from sim.dataset.config import DatasetConfig, load_config
    from sim.dataset.randomise import config_rig
    from sim.dataset.store import PARTIAL, read_manifest, write_manifest, writer_lock
    from sim.dataset.task import ensure_sample

    if samples < 1:
        raise UsageError(f"--samples must be >= 1, got {samples}")
    out = Path(out)
    if out.exists() and not force and not (out.is_dir() and (
            read_manifest(out) is not None or not any(out.iterdir()))):
        raise UsageError(f"--out {out} exists and is not a data set; pass --force to "
                         "replace it, or choose another path")
    where = "config" if isinstance(config, DatasetConfig) else str(config)
    cfg = config if isinstance(config, DatasetConfig) else load_config(config)
    rig = config_rig(cfg, where)
    preflight(cfg, rig, where)
    fresh = _manifest(cfg, rig, {})
    if out.exists() and force:
        shutil.rmtree(out) if out.is_dir() else out.unlink()
    if out.exists():
        existing = read_manifest(out)
        if existing is not None and not _same_run(existing, fresh):
            raise UsageError(f"--out {out} is a data set of another config or rig; pass "
                             "--force to replace it, or choose another path")
    existing = read_manifest(out) if out.is_dir() else None
    out.mkdir(parents=True, exist_ok=True)
    done: dict[int, dict] = {}
    made = kept = 0
    config_json, rig_json = cfg.model_dump_json(), rig.model_dump_json()
    t0 = time.perf_counter()
    with writer_lock(out):
        shutil.rmtree(out / PARTIAL, ignore_errors=True)
        listed = (existing or {}).get("samples") or {}
        write_manifest(out, _manifest(cfg, rig, {int(k): v for k, v in listed.items()
                                                 if int(k) < samples}))
        last = [time.perf_counter()]
        bar = tqdm(total=samples, desc="dataset", unit="sample", disable=not progress)

        def finished(_key, value) -> None:
            nonlocal made, kept
            index, digest, split, was_kept = value
            done[index] = {"split": split, "checksum": digest}
            kept += was_kept
            made += not was_kept
            bar.update(1)
            bar.set_postfix(made=made, kept=kept, refresh=False)
            if time.perf_counter() - last[0] > MANIFEST_EVERY_S:
                write_manifest(out, _manifest(cfg, rig, done))
                last[0] = time.perf_counter()

        try:
            with Engine(workers, dask=dask, scheduler=scheduler) as engine:
                tasks = ((i, ensure_sample, (config_json, rig_json, str(out), i))
                         for i in range(samples))
                run_ordered(engine, tasks, finished)
                kind = engine.describe()
        finally:
            bar.close()
            try:  # what is finished stays listed, even when the run failed
                write_manifest(out, _manifest(cfg, rig, done))
            except OSError:
                pass  # (a full disk): the previous manifest stays; the samples are whole
    seconds = time.perf_counter() - t0
    splits = {s: sum(1 for d in done.values() if d["split"] == s) for s in ("train", "val", "test")}
    return DatasetReport(str(out), samples, made, kept, seconds,
                         made / seconds if seconds > 0 else 0.0, kind, splits, _size(out))
