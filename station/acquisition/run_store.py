"""The run store (zarr v3) of an LTC acquisition run: raw frames, per-frame metadata and a
completion mask, written durably frame by frame so an interrupted run can resume, and checked
on every read so a damaged store is never read as data.

Layout, ``format_version`` 2 (docs/hardware.md "Resumable runs"; docs/formats.md):

* ``frames[depth, pattern, row, col]`` in the camera's dtype (uint8 up to 8 bits, else
  uint16). One frame is one stored object, a zarr shard of ``tile_px`` x ``tile_px`` inner
  chunks, uncompressed (``bytes`` little-endian) each followed by its ``crc32c``; the shard's
  index (``bytes`` + ``crc32c``) is at its end. The store writes the shard itself (each chunk
  the bytes zarr writes, chunks in row-major order where zarr 3.1 uses Morton order; in
  milliseconds instead of seconds) and reads tiles from it directly, verifying each chunk's
  crc32c; any zarr v3 reader reads the array too. Chosen by measurement
  (``benchmarks/run_store_io.py``, numbers in ``benchmarks/results/run_store_io-throughput.md``).
* ``done[depth, pattern]`` bool: True only after the frame and its metadata were written and
  flushed to disk (fsync). A frame whose flag is False is not trusted (readers refuse it).
* per-frame metadata ``[depth, pattern]``, one array per field of :class:`FrameMeta`, plus
  ``saturated_px`` (pixels at full scale, counted by the store) and ``frame_crc32c`` (crc32c of
  the frame's pixels, rows x cols in C order, little-endian; -1 while not done).
* attributes: ``format``, ``format_version``, ``config`` (the whole station config, a dict),
  ``pattern_set`` (:class:`station.acquisition.patterns.StationPatternPlan` as JSON), ``software``
  (versions), ``start_time`` (ISO 8601, UTC), ``depths_mm``, ``camera_size`` (w, h),
  ``bit_depth``, ``lcd_size`` (w, h), ``lcd_pitch_mm``, ``tile_px``, ``display_lut`` (the
  inverse response LUT the patterns were computed through, see
  :func:`station.acquisition.patterns.apply_lut`; null when none), ``run_id`` (a random
  hex id written at creation: the run's identity, see :meth:`RunStore.identity`).
* written by the acquisition through the store's methods only: ``code_mask[depth, row,
  col]`` (``add_code_mask``), attributes ``retry_log`` (``log_retries``), ``status`` and
  ``end_time`` (``set_status``), ``frame_check`` (``set_frame_check``).
* ``writer.lock``: present while a writer holds the store (:mod:`sim.storage.lock`).

Opening cross-checks the attributes against the arrays and the per-frame records (e.g. every
done frame's recorded stage target against ``depths_mm``). Creating is atomic: the store is
built under a temporary name beside ``path`` and renamed into place when complete.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import shutil
import uuid
from dataclasses import replace
from importlib import metadata as _metadata
from pathlib import Path

import numpy as np
import pydantic
import zarr
from pydantic import BaseModel, ConfigDict, Field
from zarr.codecs import BytesCodec, Crc32cCodec

from sim.storage.attrs import RunStoreAttrs, check_attrs, open_zarr_group
from sim.storage.checksum import sha256_hex
from sim.storage.durable import (
    barrier,
    fsync_path,
    new_file,
    start_writeback,
    write_all,
    write_new_file,
)
from station.acquisition.patterns import StationPatternPlan, apply_lut
from station.acquisition.run_reader import (  # noqa: F401 - the store's public names
    CODE_MASK,
    FrameCorruptError,
    RunStoreError,
    RunStoreReader,
    Tile,
    cross_check,
)
from station.acquisition.shard_codec import EncodedFrame, ShardCodec

FORMAT = "ltc-run-store"
FORMAT_VERSION = 2


class FrameMeta(BaseModel):
    """What the acquisition records with each frame."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    stage_target_mm: float = Field(description="stage target position, mm")
    stage_measured_mm: float = Field(description="stage position measured after settling, mm")
    swap_index: int = Field(description="display show() count of the swap showing the pattern")
    swap_time_s: float = Field(description="display swap time (time.monotonic), s")
    camera_timestamp_s: float = Field(description="camera timestamp of the frame, s")
    frame_id: int = Field(description="camera frame counter")
    exposure_ms: float = Field(gt=0, description="exposure time, ms")
    retries: int = Field(0, ge=0, description="re-captures before this frame was accepted")


_INT_FILL = -1
META_ARRAYS: dict[str, str] = {
    name: ("int64" if f.annotation is int else "float64")
    for name, f in FrameMeta.model_fields.items()
}
META_ARRAYS["saturated_px"] = "int64"
META_ARRAYS["frame_crc32c"] = "int64"


def _json_config(path: Path, config: dict) -> dict:
    """The config as it reads back from the store's JSON attributes (tuples become lists)."""
    if not isinstance(config, dict):
        raise RunStoreError(f"{path}: config must be a dict, got {type(config).__name__}")
    try:
        return json.loads(json.dumps(config))
    except (TypeError, ValueError) as exc:
        raise RunStoreError(f"{path}: config is not JSON-serialisable ({exc})") from exc


def software_versions() -> dict[str, str]:
    """Versions of Python and of the packages that shape the data."""
    out = {"python": platform.python_version()}
    for pkg in ("ltc-fpp", "numpy", "scipy", "zarr", "pydantic"):
        try:
            out[pkg] = _metadata.version(pkg)
        except _metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


class RunStore(RunStoreReader):
    """A run store on disk; create with :meth:`create`, open with :meth:`open`."""

    def __init__(self, path: Path, group: zarr.Group, plan: StationPatternPlan) -> None:
        self.path = path
        self.group = group
        self.plan = plan
        a = group.attrs
        self.depths_mm: list[float] = [float(z) for z in a["depths_mm"]]
        cw, ch = a["camera_size"]  # (width, height), two values (checked by open)
        self.camera_size: tuple[int, int] = (int(cw), int(ch))
        lw, lh = a["lcd_size"]
        self.lcd_size: tuple[int, int] = (int(lw), int(lh))
        self.lcd_pitch_mm = float(a["lcd_pitch_mm"])
        self.bit_depth = int(a["bit_depth"])
        self.tile_px = int(a["tile_px"])
        self._frames = group["frames"]
        self._done = group["done"]
        self._meta = {name: group[name] for name in META_ARRAYS}
        self._small_kinds = {name: (np.dtype(group[name].dtype).newbyteorder("<"),
                                    group[name].fill_value) for name in ("done", *META_ARRAYS)}
        w, h = self.camera_size
        self.codec = ShardCodec(h, w, self.tile_px, self._frames.dtype)
        self._unflushed: Path | None = None
        self.recaptured: list[list[int]] = []  # (depth, pattern) a resume found damaged

    # ---- creation and opening -------------------------------------------------------------
    @classmethod
    def create(
        cls,
        path: str | Path,
        *,
        config: dict,
        plan: StationPatternPlan,
        depths_mm: list[float],
        camera_size: tuple[int, int],
        bit_depth: int,
        lcd_size: tuple[int, int],
        lcd_pitch_mm: float,
        tile_px: int = 64,
        display_lut: np.ndarray | None = None,
        start_time: str | None = None,
        attrs: dict | None = None,
    ) -> RunStore:
        """Create an empty run store, atomically; refuses to overwrite anything at ``path``.

        config : the whole station config as a JSON-able dict (stored verbatim).
        camera_size, lcd_size : (width, height) in pixels; bit_depth : camera bits (1..16).
        tile_px : edge of the inner chunks readers fetch per frame, pixels.
        display_lut : the LUT given to ``StationPatternPlan.image`` for every pattern (None:
            identity); reconstruction models the levels shown through it.
        start_time : ISO 8601; default now (UTC). attrs : more attributes to store (JSON).

        The store is built as ``.NAME.creating-<id>`` beside ``path``, flushed, and renamed to
        ``path``: a process killed meanwhile leaves no store at ``path`` (the temporary folder
        may stay; delete it).
        """
        path = Path(path)
        if path.exists():
            raise RunStoreError(f"{path}: already exists; refusing to overwrite a run store")
        config = _json_config(path, config)
        if not 1 <= int(bit_depth) <= 16:
            raise RunStoreError(f"{path}: bit_depth must be 1..16, got {bit_depth}")
        if len(depths_mm) < 1:
            raise RunStoreError(f"{path}: depths_mm must list at least one depth")
        if int(tile_px) < 1:
            raise RunStoreError(f"{path}: tile_px must be >= 1, got {tile_px}")
        w, h = (int(v) for v in camera_size)
        if w < 1 or h < 1:
            raise RunStoreError(f"{path}: camera_size must be positive (width, height), "
                                f"got {camera_size}")
        if not plan.localisation.covers(lcd_size):
            raise RunStoreError(f"{path}: the pattern plan's Gray code does not cover the "
                                f"LCD of {tuple(lcd_size)} pixels")
        if display_lut is not None:
            try:
                apply_lut(np.zeros(1), display_lut)
            except ValueError as exc:
                raise RunStoreError(f"{path}: display_lut: {exc}") from exc
        extra = _json_config(path, dict(attrs or {}))
        d, n = len(depths_mm), len(plan)
        t = int(tile_px)
        dtype = "uint8" if int(bit_depth) <= 8 else "uint16"
        tmp = path.parent / f".{path.name}.creating-{uuid.uuid4().hex[:12]}"
        try:
            g = zarr.open_group(str(tmp), mode="w-", zarr_format=3)
            shard = (1, 1, -(-h // t) * t, -(-w // t) * t)
            g.create_array("frames", shape=(d, n, h, w), shards=shard, chunks=(1, 1, t, t),
                           dtype=dtype, fill_value=0, serializer=BytesCodec(endian="little"),
                           compressors=[Crc32cCodec()])
            # small arrays: one chunk per depth, rewritten whole (atomically) at every frame
            g.create_array("done", shape=(d, n), chunks=(1, n), dtype="bool",
                           fill_value=False, compressors=None)
            # camera pixels that see the acquisition's check code, per depth (excluded from LTC)
            g.create_array(CODE_MASK, shape=(d, h, w), chunks=(1, h, w), dtype="bool",
                           fill_value=False)
            for name, dt in META_ARRAYS.items():
                fill = np.nan if dt == "float64" else _INT_FILL
                g.create_array(name, shape=(d, n), chunks=(1, n), dtype=dt, fill_value=fill,
                               compressors=None)
            g.attrs.update({
                "format": FORMAT,
                "format_version": FORMAT_VERSION,
                "run_id": uuid.uuid4().hex,
                "config": config,
                "pattern_set": plan.model_dump(mode="json"),
                "software": software_versions(),
                "start_time": start_time or _dt.datetime.now(_dt.UTC).isoformat(),
                "depths_mm": [float(z) for z in depths_mm],
                "camera_size": [w, h],
                "bit_depth": int(bit_depth),
                "lcd_size": [int(v) for v in lcd_size],
                "lcd_pitch_mm": float(lcd_pitch_mm),
                "tile_px": t,
                "display_lut": None if display_lut is None
                else [float(v) for v in np.asarray(display_lut).ravel()],
                **extra,
            })
            for folder, _, files in os.walk(tmp):
                for f in files:
                    fsync_path(Path(folder) / f)
                fsync_path(Path(folder))
            if path.exists():
                raise RunStoreError(f"{path}: appeared while creating the run store; "
                                    "refusing to overwrite it")
            os.rename(tmp, path)
            fsync_path(path.parent)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return cls.open(path, mode="r+")

    @classmethod
    def open(cls, path: str | Path, mode: str = "r") -> RunStore:
        """Open, validate and cross-check a run store; ``mode`` "r" (read) or "r+" (resume
        writing)."""
        path = Path(path)
        if mode not in ("r", "r+"):
            raise RunStoreError(f"{path}: mode must be 'r' or 'r+', got {mode!r}")
        if not path.exists():
            raise RunStoreError(f"{path}: no such run store")
        g = open_zarr_group(path, mode, RunStoreError, "run store")
        a = g.attrs
        if a.get("format") != FORMAT:
            raise RunStoreError(f"{path}: attribute 'format' is {a.get('format')!r}, "
                                f"expected {FORMAT!r}")
        version = a.get("format_version")
        if isinstance(version, int) and version < FORMAT_VERSION:
            raise RunStoreError(
                f"{path}: attribute 'format_version' is {version}, an older run-store layout "
                f"this software does not read (it reads version {FORMAT_VERSION}: checksummed "
                "frames); acquire the run again, or read it with the ltc-fpp release that "
                "wrote it")
        if version != FORMAT_VERSION:
            raise RunStoreError(f"{path}: attribute 'format_version' is {version!r}, "
                                f"expected {FORMAT_VERSION}")
        keys = ("config", "pattern_set", "software", "start_time", "depths_mm", "camera_size",
                "bit_depth", "lcd_size", "lcd_pitch_mm", "tile_px", "display_lut")
        missing = [k for k in keys if k not in a]
        if missing:
            raise RunStoreError(f"{path}: missing attribute(s) {missing}")
        check_attrs(path, a, RunStoreAttrs, RunStoreError)
        try:
            plan = StationPatternPlan.model_validate(a["pattern_set"])
        except pydantic.ValidationError as exc:
            raise RunStoreError(f"{path}: attribute 'pattern_set' is not a pattern plan: "
                                f"{exc}") from exc
        absent = [k for k in ("frames", "done", *META_ARRAYS) if k not in g]
        if absent:
            raise RunStoreError(f"{path}: missing array(s) {absent}")
        d, n = len(a["depths_mm"]), len(plan)
        w, h = a["camera_size"]
        expect = {"frames": (d, n, h, w), "done": (d, n), **{k: (d, n) for k in META_ARRAYS}}
        for name, shape in expect.items():
            if tuple(g[name].shape) != shape:
                raise RunStoreError(f"{path}: array '{name}' has shape {tuple(g[name].shape)}, "
                                    f"expected {shape} from the attributes")
        cross_check(path, g, plan, tuple(META_ARRAYS))
        return cls(path, g, plan)

    # ---- state ------------------------------------------------------------------------------
    @property
    def config(self) -> dict:
        return dict(self.group.attrs["config"])

    @property
    def display_lut(self) -> np.ndarray | None:
        """The inverse response LUT the patterns went through, (N,) float64, or None."""
        lut = self.group.attrs["display_lut"]
        return None if lut is None else np.asarray(lut, dtype=np.float64)

    def identity(self) -> str:
        """The run's identity, which a store derived from it records and compares on resume:
        ``run_id`` (written at creation), or for a store written before run ids, a SHA-256 of
        its start time and frame checksums (``sha256:<hex>``). A new acquisition at the same
        path has another identity; the same store under another path name has the same."""
        run_id = self.group.attrs.get("run_id")
        if isinstance(run_id, str) and run_id:
            return run_id
        crc = np.ascontiguousarray(np.asarray(self._meta["frame_crc32c"][...]), "<i8")
        return "sha256:" + sha256_hex(str(self.group.attrs["start_time"]).encode(),
                                      crc.tobytes())

    def first_incomplete(self) -> tuple[int, int] | None:
        """(depth, pattern) of the first frame not done in plan order, None when complete."""
        todo = np.argwhere(~self.done())
        return None if len(todo) == 0 else (int(todo[0, 0]), int(todo[0, 1]))

    def is_complete(self) -> bool:
        return self.first_incomplete() is None

    def require_same_config(self, config: dict, plan: StationPatternPlan) -> None:
        """Raise unless ``config`` and ``plan`` are those the run was created with (for resume)."""
        stored, config = self.config, _json_config(self.path, config)
        diff = sorted(k for k in set(stored) | set(config) if stored.get(k) != config.get(k))
        if diff:
            raise RunStoreError(f"{self.path}: config differs from the stored run in {diff}; "
                                "start a new run store instead of resuming")
        if plan != self.plan:
            raise RunStoreError(f"{self.path}: pattern set differs from the stored run's")

    # ---- writing ----------------------------------------------------------------------------
    def write_frame(self, depth: int, pattern: int, image: np.ndarray, meta: FrameMeta) -> None:
        """Write one frame (its shard), then its metadata with the frame's crc32c, flush both
        to disk, then mark it done: an interruption loses at most this frame (a done flag
        not yet flushed by :meth:`flush` or the next write may be lost too, never set early).
        The three stages :meth:`encode_frame`, :meth:`store_encoded` and :meth:`commit` in
        series; a pipelined writer runs them in three threads on successive frames."""
        self.commit(self.store_encoded(self.encode_frame(depth, pattern, image, meta)))

    def new_codec(self) -> ShardCodec:
        """A shard encoder of this store's frames with its own buffer (one per frame being
        encoded or written at once)."""
        w, h = self.camera_size
        return ShardCodec(h, w, self.tile_px, self.dtype)

    def encode_frame(self, depth: int, pattern: int, image: np.ndarray, meta: FrameMeta,
                     codec: ShardCodec | None = None) -> EncodedFrame:
        """Check a frame and encode its shard in ``codec``'s buffer (default: the store's
        own), with what the store records of it; CPU only, nothing written. The buffer is
        valid until ``codec`` encodes again."""
        self._check_index(depth, pattern)
        img = np.asarray(image)
        w, h = self.camera_size
        if img.shape != (h, w):
            raise RunStoreError(f"{self.path}: frame ({depth}, {pattern}) has shape {img.shape}, "
                                f"expected (rows, cols) = {(h, w)}")
        if img.dtype != self.dtype:
            raise RunStoreError(f"{self.path}: frame ({depth}, {pattern}) has dtype {img.dtype}, "
                                f"expected the camera's {self.dtype}")
        if not isinstance(meta, FrameMeta):
            raise RunStoreError(f"{self.path}: meta must be a FrameMeta, got "
                                f"{type(meta).__name__}")
        if meta.stage_target_mm != self.depths_mm[depth]:
            raise RunStoreError(f"{self.path}: frame ({depth}, {pattern}) has stage target "
                                f"{meta.stage_target_mm} mm, but depth {depth} is "
                                f"{self.depths_mm[depth]} mm (attribute 'depths_mm')")
        full = 2**self.bit_depth - 1
        codec = self.codec if codec is None else codec
        enc = codec.encode(img, full)
        if enc.top > full:
            raise RunStoreError(f"{self.path}: frame ({depth}, {pattern}) has values above "
                                f"{full}, the camera's {self.bit_depth}-bit full scale")
        values = {**meta.model_dump(), "saturated_px": enc.saturated,
                  "frame_crc32c": enc.crc32c}
        return EncodedFrame(depth, pattern, enc.chunks, codec.index, values)

    def store_encoded(self, frame: EncodedFrame) -> EncodedFrame:
        """Write an encoded frame's shard (under a temporary name, renamed into place; the
        kernel starts writing it to disk at once) and its metadata, without waiting for the
        disk: not durable, not done. Returns the frame with the paths written."""
        final = self._shard_path(frame.depth, frame.pattern)
        final.parent.mkdir(parents=True, exist_ok=True)
        with new_file(final) as fd:
            write_all(final, fd, [frame.chunks, frame.index])
            start_writeback(fd, 0, frame.chunks.nbytes + len(frame.index))
        written = [self._set_small(name, frame.depth, frame.pattern, frame.values[name])
                   for name in self._meta]
        return replace(frame, written=[final, *written])

    def commit(self, frame: EncodedFrame) -> None:
        """Make a stored frame durable (one barrier: its shard and metadata reach the disk),
        then set its done flag (durable at the next barrier)."""
        barrier(self.path, frame.written)
        self._mark_done(frame.depth, frame.pattern)

    def _mark_done(self, depth: int, pattern: int) -> None:
        """Set a frame's done flag (durable at the next barrier: :meth:`flush` or a write)."""
        self._unflushed = self._set_small("done", depth, pattern, True)

    def mark_not_done(self, frames: list[tuple[int, int]]) -> None:
        """Clear the done flags of ``frames`` (depth, pattern), durably: a damaged frame is
        then captured again by a resumed acquisition."""
        written = [self._set_small("done", d, p, False) for d, p in frames]
        if written:
            barrier(self.path, written)

    def _set_small(self, name: str, depth: int, pattern: int, value: object) -> Path:
        """Set ``name[depth, pattern]`` of a per-frame array in its chunk (one per depth,
        uncompressed little-endian, the bytes zarr writes); returns the chunk's path. An
        existing chunk is updated in place: one aligned write of the one element (1 or 8
        bytes, within one disk sector, so the other frames' elements are never touched; a
        rename over the file costs about 1 ms on ext4). A missing chunk is created whole (fill
        values and this element) under a temporary name and renamed into place."""
        path = self._small_chunk(name, depth)
        dtype, fill = self._small_kinds[name]
        n = self.n_patterns
        element = np.asarray(value, dtype).tobytes()
        try:
            fd = os.open(path, os.O_WRONLY)
        except FileNotFoundError:
            chunk = np.full(n, fill, dtype)
            chunk[pattern] = value
            path.parent.mkdir(parents=True, exist_ok=True)
            write_new_file(path, [chunk])
            return path
        try:
            size = os.fstat(fd).st_size
            if size != n * dtype.itemsize:
                raise RunStoreError(f"{self.path}: chunk {name}/c/{depth}/0 has {size} bytes, "
                                    f"expected {n * dtype.itemsize}; the run store is damaged")
            write_all(path, fd, [element], pattern * dtype.itemsize)
        finally:
            os.close(fd)
        return path

    def flush(self) -> None:
        """Make the done flags written so far durable (else the next frame's write does; a
        flag lost in a crash only means that frame is captured again)."""
        if self._unflushed is not None:
            barrier(self.path, [self._unflushed])
            self._unflushed = None

    def add_code_mask(self, depth: int, mask: np.ndarray) -> None:
        """Mark camera pixels (rows, cols) bool that saw the check code at ``depth`` (OR-ed
        into ``code_mask``, so a resumed depth keeps what an earlier calibration found)."""
        self._check_index(depth, 0)
        arr = self.group[CODE_MASK]
        arr[depth] = np.asarray(arr[depth]) | np.asarray(mask, dtype=bool)

    def log_retries(self, depth: int, pattern: int, reasons: list[str]) -> None:
        """Append a frame's failed attempts to the ``retry_log`` attribute."""
        entries = list(self.group.attrs.get("retry_log", []))
        entries.append({"depth": depth, "pattern": pattern, "reasons": list(reasons)})
        self.group.attrs["retry_log"] = entries

    def set_status(self, status: str, end_time: str | None = None) -> None:
        """Record the run's ``status`` attribute ("running", "complete", "failed", ...) and,
        when given, its ``end_time`` (ISO 8601)."""
        attrs: dict = {"status": status}
        if end_time is not None:
            attrs["end_time"] = end_time
        self.group.attrs.update(attrs)

    def set_frame_check(self, frame_check: dict | None) -> None:
        """Record where the check code is drawn (``frame_check`` attribute; None: no code)."""
        self.group.attrs["frame_check"] = frame_check
