"""The data set on disk (zarr v3; docs/formats.md, "Fringe data set") and its reader.

Layout of a data set folder ``DIR``::

    DIR/zarr.json                 root group; attributes: the manifest (format, version,
                                  config, rig, software version, samples: index -> split and
                                  checksum, once the run ends)
    DIR/samples/zarr.json         group of the samples
    DIR/samples/000042/           one group per sample: attributes ``scene`` (its full
                                  description), ``checksum``, ``split``, ``index``;
                                  subgroups camera_0, camera_1 with the arrays of
                                  ``sim.dataset.generate.CAMERA_KEYS``, one chunk each
    DIR/.lock                     the writer's lock
    DIR/.partial/                 samples being written (moved into samples/ when whole)

A sample is written into ``.partial/``, every file synced, then renamed into ``samples/`` and
the folder synced: a sample in ``samples/`` is whole, or absent. Its checksum (sha256 of its
scene and arrays) is in its attributes and, at the end of a run, in the manifest.

Durable writes and the writer lock are the storage layer's (``sim.storage``).
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr

from sim.dataset.config import Storage
from sim.dataset.generate import CAMERA_KEYS, Sample, checksum
from sim.dataset.randomise import SampleScene
from sim.errors import SimInputError
from sim.storage.durable import durable_file, publish
from sim.storage.durable import sync_tree as _sync_tree
from sim.storage.lock import StoreLock

FORMAT = "ltc-fpp-fringe-dataset"
FORMAT_VERSION = 1
SAMPLES = "samples"
PARTIAL = ".partial"
WRITE_THREADS = 4  # arrays compressed at once (zstd releases the GIL)
SYNC_THREADS = 16  # fsyncs in flight at once


# ---------------------------------------------------------------- durable writes and the lock


def write_durable(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` durably (:func:`sim.storage.durable.durable_file`)."""
    with durable_file(path, "wb") as f:
        f.write(data)


def sync_tree(folder: Path, threads: int = SYNC_THREADS) -> None:
    """fsync every file and folder under ``folder`` (:func:`sim.storage.durable.sync_tree`),
    the files on ``threads`` threads."""
    _sync_tree(folder, threads)


def writer_lock(folder: Path) -> StoreLock:
    """The data set's writer lock (:class:`sim.storage.lock.StoreLock`, ``writer.lock`` in
    ``folder``): a second writer is refused, naming the holder."""
    return StoreLock(folder)


# ---------------------------------------------------------------- writing


def codecs(storage: Storage) -> tuple:
    """The zarr v3 compressors of a storage setting."""
    from zarr.codecs import BloscCodec, GzipCodec, ZstdCodec

    if storage.codec == "none":
        return ()
    if storage.codec == "zstd":
        return (ZstdCodec(level=storage.level),)
    if storage.codec == "gzip":
        return (GzipCodec(level=min(storage.level, 9)),)
    cname = storage.codec.split("_")[1]
    return (BloscCodec(cname=cname, clevel=min(storage.level, 9), shuffle="bitshuffle"),)


def sample_name(index: int) -> str:
    return f"{index:06d}"


def write_group(path: Path, sample: Sample, digest: str | Future, storage: Storage,
                threads: int = WRITE_THREADS) -> None:
    """Write a sample as a zarr v3 group at ``path`` (a new folder); one chunk per array (a
    sample is read whole, and every file costs an fsync). The arrays are compressed and
    written on ``threads`` threads; ``digest`` (or a future of it, awaited once the arrays
    are written) goes into the group's attributes, written last."""
    scene = sample.scene
    comp = codecs(storage)
    jobs = []
    for i, cam in enumerate(sample.cameras):
        cg = zarr.open_group(str(Path(path) / f"camera_{i}"), mode="w-", zarr_format=3,
                             attributes={"name": scene.rig.cameras[i].name})
        jobs += [(cg, key, cam[key]) for key in CAMERA_KEYS]
    with ThreadPoolExecutor(max(1, threads)) as pool:
        list(pool.map(lambda j: j[0].create_array(j[1], data=j[2], chunks=j[2].shape,
                                                  compressors=comp), jobs))
    digest = digest.result() if isinstance(digest, Future) else digest
    attrs = {"index": scene.index, "split": scene.split, "checksum": digest,
             "scene": json.loads(scene.model_dump_json())}
    zarr.create_group(str(path), zarr_format=3, attributes=attrs)


def write_sample(root: Path, sample: Sample, storage: Storage | None = None) -> str:
    """Write a sample into the data set ``root`` durably (whole or not at all; one that is
    there is replaced); returns its checksum."""
    storage = storage or Storage()
    root = Path(root)
    name = sample_name(sample.index)
    tmp = root / PARTIAL / f"{name}-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.parent.mkdir(exist_ok=True)
    try:
        with ThreadPoolExecutor(1) as hasher:  # the sha256 runs while the arrays compress
            pending = hasher.submit(sample.checksum)
            write_group(tmp, sample, pending, storage)
            digest = pending.result()
        sync_tree(tmp)
        publish(tmp, root / SAMPLES / name, replace=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return digest


# ---------------------------------------------------------------- reading


@dataclass
class SampleArrays:
    """One sample read back: its scene, and per camera the arrays of ``CAMERA_KEYS``."""

    index: int
    split: str
    checksum: str
    scene: SampleScene
    cameras: list[dict[str, np.ndarray]]

    def verify(self) -> bool:
        """Whether the arrays and scene still give the checksum written with them."""
        return checksum(self.scene.model_dump_json(), self.cameras) == self.checksum


def read_sample(path: Path, keys: Sequence[str] = CAMERA_KEYS) -> SampleArrays:
    """The sample group at ``path`` (errors name it)."""
    try:
        g = zarr.open_group(str(path), mode="r", zarr_format=3)
        a = dict(g.attrs)
        cams = []
        i = 0
        while f"camera_{i}" in g:
            cg = g[f"camera_{i}"]
            cams.append({k: np.asarray(cg[k][...]) for k in keys})
            i += 1
        return SampleArrays(int(a["index"]), str(a["split"]), str(a["checksum"]),
                            SampleScene.model_validate(a["scene"]), cams)
    except Exception as exc:  # noqa: BLE001 - a damaged chunk raises anything (codecs, JSON)
        raise SimInputError(f"data set sample {path} cannot be read: {exc}") from exc


def verify_sample(path: Path) -> str | None:
    """The checksum of a whole sample group whose content still matches it, else None."""
    try:
        s = read_sample(path)
    except ValueError:
        return None
    return s.checksum if s.verify() else None


def read_manifest(root: Path) -> dict | None:
    """The manifest of data set ``root`` (its root group's attributes), or None when ``root``
    holds no data set."""
    meta = Path(root) / "zarr.json"
    if not meta.is_file():
        return None
    try:
        attrs = json.loads(meta.read_text()).get("attributes", {})
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SimInputError(f"{meta}: not valid JSON ({exc}); the data set's manifest is "
                         "damaged") from exc
    return attrs if attrs.get("format") == FORMAT else None


def write_manifest(root: Path, manifest: dict) -> None:
    """Write the root group (its attributes the manifest) and the samples group, durably."""
    root = Path(root)
    group = {"zarr_format": 3, "node_type": "group", "attributes": manifest}
    write_durable(root / "zarr.json", json.dumps(group, indent=1).encode())
    (root / SAMPLES).mkdir(exist_ok=True)
    if not (root / SAMPLES / "zarr.json").is_file():
        write_durable(root / SAMPLES / "zarr.json",
                      json.dumps({"zarr_format": 3, "node_type": "group",
                                  "attributes": {}}).encode())


class DatasetReader:
    """Numpy access to a data set (``open``): ``len``, ``ds[i]`` (the i-th sample of the
    manifest, ``SampleArrays``), ``indices(split)``, ``batch(...)``; no deep-learning
    framework needed."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        m = read_manifest(self.path)
        if m is None:
            raise SimInputError(f"{self.path} is not a fringe data set (no manifest with format "
                             f"{FORMAT!r} in zarr.json)")
        self.manifest = m
        samples = m.get("samples") or {}
        self._index = sorted(int(k) for k in samples)
        self._split = {int(k): v["split"] for k, v in samples.items()}

    def __len__(self) -> int:
        return len(self._index)

    @property
    def sample_indices(self) -> list[int]:
        """The data set's sample indices, ascending."""
        return list(self._index)

    def indices(self, split: str | None = None) -> list[int]:
        """Sample indices of a split ('train', 'val', 'test'; None: all), ascending."""
        return [i for i in self._index if split is None or self._split[i] == split]

    def sample(self, index: int, keys: Sequence[str] = CAMERA_KEYS) -> SampleArrays:
        """Sample ``index`` (its data-set index), the arrays ``keys`` of each camera."""
        if index not in self._split:
            raise KeyError(f"{self.path}: no sample {index}")
        return read_sample(self.path / SAMPLES / sample_name(index), keys)

    def __getitem__(self, i: int) -> SampleArrays:
        return self.sample(self._index[i])

    def batch(self, indices: Sequence[int], keys: Sequence[str], camera: int = 0
              ) -> dict[str, np.ndarray]:
        """Arrays ``keys`` of one camera for the samples ``indices``, stacked on a new first
        axis (samples must agree in shape, as they do within a data set's pattern set)."""
        parts = [self.sample(i, keys).cameras[camera] for i in indices]
        return {k: np.stack([p[k] for p in parts]) for k in keys}


def open(path: str | Path) -> DatasetReader:  # noqa: A001 - the package's reader, by design
    """Open the data set at ``path`` for reading (numpy arrays per sample and per batch)."""
    return DatasetReader(path)
