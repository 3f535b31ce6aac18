"""The run store (zarr v3) of an LTC acquisition run: raw frames, per-frame metadata and a
completion mask, written durably frame by frame so an interrupted run can resume.

Layout (HARDWARE.md "Acquisition runs", issue 3):

* ``frames[depth, pattern, row, col]`` in the camera's dtype (uint8 up to 8 bits, else
  uint16). One frame is one stored object (a zarr shard), so each frame write is a single
  atomic file replacement; inside it, ``tile_px`` x ``tile_px`` inner chunks let readers
  fetch one tile of every frame without decoding whole frames.
* ``done[depth, pattern]`` bool: True only after the frame and its metadata were written.
  A frame whose flag is False is not trusted (readers refuse it).
* per-frame metadata ``[depth, pattern]``, one array per field of :class:`FrameMeta`, plus
  ``saturated_px`` (pixels at full scale, counted by the store).
* attributes: ``format``, ``format_version``, ``config`` (the whole station config, a dict),
  ``pattern_set`` (:class:`station.acquisition.patterns.StationPatternPlan` as JSON), ``software``
  (versions), ``start_time`` (ISO 8601, UTC), ``depths_mm``, ``camera_size`` (w, h),
  ``bit_depth``, ``lcd_size`` (w, h), ``lcd_pitch_mm``, ``tile_px``, ``display_lut`` (the
  inverse response LUT the patterns were computed through, see
  :func:`station.acquisition.patterns.apply_lut`; null when none).
* written by the acquisition through the store's methods only: ``code_mask[depth, row,
  col]`` (``add_code_mask``), attributes ``retry_log`` (``log_retries``), ``status`` and
  ``end_time`` (``set_status``), ``frame_check`` (``set_frame_check``).
"""

from __future__ import annotations

import asyncio
import datetime as _dt
import json
import platform
from collections.abc import Iterator
from dataclasses import dataclass
from importlib import metadata as _metadata
from pathlib import Path

import numpy as np
import pydantic
import zarr
from pydantic import BaseModel, ConfigDict, Field
from zarr.core.sync import sync as zarr_sync

from station.acquisition.patterns import StationPatternPlan, apply_lut

CODE_MASK = "code_mask"  # array [depth, row, col] bool: camera pixels that see the check code

FORMAT = "ltc-run-store"
FORMAT_VERSION = 1


class RunStoreError(ValueError):
    """The run store is missing, malformed, incomplete or misused; the message names the path."""


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


@dataclass(frozen=True)
class Tile:
    """All frames of one depth over one tile: ``frames`` (patterns, rows, cols), camera dtype;
    the tile covers camera rows ``row0 : row0 + rows`` and columns ``col0 : col0 + cols``."""

    depth: int
    row0: int
    col0: int
    frames: np.ndarray


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


class RunStore:
    """A run store on disk; create with :meth:`create`, open with :meth:`open`."""

    def __init__(self, path: Path, group: zarr.Group, plan: StationPatternPlan) -> None:
        self.path = path
        self.group = group
        self.plan = plan
        a = group.attrs
        self.depths_mm: list[float] = [float(z) for z in a["depths_mm"]]
        self.camera_size: tuple[int, int] = tuple(int(v) for v in a["camera_size"])
        self.lcd_size: tuple[int, int] = tuple(int(v) for v in a["lcd_size"])
        self.lcd_pitch_mm = float(a["lcd_pitch_mm"])
        self.bit_depth = int(a["bit_depth"])
        self.tile_px = int(a["tile_px"])
        self._frames = group["frames"]
        self._done = group["done"]
        self._meta = {name: group[name] for name in META_ARRAYS}

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
    ) -> RunStore:
        """Create an empty run store; refuses to overwrite anything at ``path``.

        config : the whole station config as a JSON-able dict (stored verbatim).
        camera_size, lcd_size : (width, height) in pixels; bit_depth : camera bits (1..16).
        tile_px : edge of the inner chunks readers fetch per frame, pixels.
        display_lut : the LUT given to ``StationPatternPlan.image`` for every pattern (None:
            identity); reconstruction models the levels shown through it.
        start_time : ISO 8601; default now (UTC).
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
        d, n = len(depths_mm), len(plan)
        t = int(tile_px)
        dtype = "uint8" if int(bit_depth) <= 8 else "uint16"
        g = zarr.open_group(str(path), mode="w-", zarr_format=3)
        shard = (1, 1, -(-h // t) * t, -(-w // t) * t)
        g.create_array("frames", shape=(d, n, h, w), shards=shard, chunks=(1, 1, t, t),
                       dtype=dtype, fill_value=0)
        # small arrays: one chunk per depth, rewritten whole (atomically) at every frame
        g.create_array("done", shape=(d, n), chunks=(1, n), dtype="bool", fill_value=False,
                       compressors=None)
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
            "config": config,
            "pattern_set": plan.model_dump(mode="json"),
            "software": software_versions(),
            "start_time": start_time or _dt.datetime.now(_dt.timezone.utc).isoformat(),
            "depths_mm": [float(z) for z in depths_mm],
            "camera_size": [w, h],
            "bit_depth": int(bit_depth),
            "lcd_size": [int(v) for v in lcd_size],
            "lcd_pitch_mm": float(lcd_pitch_mm),
            "tile_px": t,
            "display_lut": None if display_lut is None
            else [float(v) for v in np.asarray(display_lut).ravel()],
        })
        return cls(path, g, plan)

    @classmethod
    def open(cls, path: str | Path, mode: str = "r") -> RunStore:
        """Open and validate a run store; ``mode`` "r" (read) or "r+" (resume writing)."""
        path = Path(path)
        if mode not in ("r", "r+"):
            raise RunStoreError(f"{path}: mode must be 'r' or 'r+', got {mode!r}")
        if not path.exists():
            raise RunStoreError(f"{path}: no such run store")
        try:
            g = zarr.open_group(str(path), mode=mode)
        except (FileNotFoundError, ValueError, KeyError) as exc:
            raise RunStoreError(f"{path}: not a zarr group ({exc})") from exc
        a = g.attrs
        if a.get("format") != FORMAT:
            raise RunStoreError(f"{path}: attribute 'format' is {a.get('format')!r}, "
                                f"expected {FORMAT!r}")
        if a.get("format_version") != FORMAT_VERSION:
            raise RunStoreError(f"{path}: attribute 'format_version' is "
                                f"{a.get('format_version')!r}, expected {FORMAT_VERSION}")
        keys = ("config", "pattern_set", "software", "start_time", "depths_mm", "camera_size",
                "bit_depth", "lcd_size", "lcd_pitch_mm", "tile_px", "display_lut")
        missing = [k for k in keys if k not in a]
        if missing:
            raise RunStoreError(f"{path}: missing attribute(s) {missing}")
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

    @property
    def n_depths(self) -> int:
        return len(self.depths_mm)

    @property
    def n_patterns(self) -> int:
        return len(self.plan)

    @property
    def dtype(self) -> np.dtype:
        return self._frames.dtype

    def done(self) -> np.ndarray:
        """Completion mask (depths, patterns) bool, read from disk now."""
        return np.asarray(self._done[...], dtype=bool)

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
        """Write one frame, then its metadata, then mark it done: each step a completed,
        atomically replaced zarr chunk, so an interruption loses at most this frame."""
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
        full = 2**self.bit_depth - 1
        if img.size and int(img.max()) > full:
            raise RunStoreError(f"{self.path}: frame ({depth}, {pattern}) has values above "
                                f"{full}, the camera's {self.bit_depth}-bit full scale")
        self._frames[depth, pattern] = img
        values = {**meta.model_dump(), "saturated_px": int(np.count_nonzero(img >= full))}

        async def write_meta() -> None:  # one batch: the fields are independent chunks
            await asyncio.gather(*(arr.async_array.setitem((depth, pattern), values[name])
                                   for name, arr in self._meta.items()))

        zarr_sync(write_meta())
        self._done[depth, pattern] = True

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

    # ---- reading ----------------------------------------------------------------------------
    def code_mask(self, depth: int) -> np.ndarray:
        """(rows, cols) bool: camera pixels that saw the check code at this depth (no LTC)."""
        if CODE_MASK not in self.group:  # stores written before the mask existed
            h, w = self.camera_size[1], self.camera_size[0]
            return np.zeros((h, w), bool)
        return np.asarray(self.group[CODE_MASK][depth])

    def read_meta(self, depth: int) -> dict[str, np.ndarray]:
        """Per-frame metadata of one depth: name -> (patterns,) array (fill where not done)."""
        self._check_index(depth, 0)
        return {name: np.asarray(arr[depth]) for name, arr in self._meta.items()}

    def read_frame(self, depth: int, pattern: int) -> np.ndarray:
        """One whole frame (rows, cols); refuses a frame that is not done."""
        self._check_index(depth, pattern)
        if not bool(self._done[depth, pattern]):
            raise RunStoreError(f"{self.path}: frame ({depth}, {pattern}) is not done; "
                                "it may be partial and is not trusted")
        return np.asarray(self._frames[depth, pattern])

    def iter_tiles(self, depth: int, tile_px: int | None = None) -> Iterator[Tile]:
        """All frames of ``depth`` over square tiles in row-major order (edge tiles smaller).
        The depth must be complete; ``tile_px`` defaults to the store's inner chunk."""
        self._check_index(depth, 0)
        missing = np.flatnonzero(~self.done()[depth])
        if len(missing):
            raise RunStoreError(f"{self.path}: depth {depth} has {len(missing)} frame(s) not "
                                f"done (first: pattern {missing[0]}); finish it with --resume")
        t = self.tile_px if tile_px is None else int(tile_px)
        if t < 1:
            raise RunStoreError(f"{self.path}: tile_px must be >= 1, got {tile_px}")
        w, h = self.camera_size
        for r0 in range(0, h, t):
            for c0 in range(0, w, t):
                block = np.asarray(self._frames[depth, :, r0 : r0 + t, c0 : c0 + t])
                yield Tile(depth, r0, c0, block)

    def _check_index(self, depth: int, pattern: int) -> None:
        if not (0 <= depth < self.n_depths and 0 <= pattern < self.n_patterns):
            raise RunStoreError(f"{self.path}: frame index (depth={depth}, pattern={pattern}) "
                                f"outside (0..{self.n_depths - 1}, 0..{self.n_patterns - 1})")
