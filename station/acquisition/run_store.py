"""The run store (zarr v3) of an LTC acquisition run: raw frames, per-frame metadata and a
completion mask, written durably frame by frame so an interrupted run can resume, and checked
on every read so a damaged store is never read as data.

Layout, ``format_version`` 2 (HARDWARE.md "Acquisition runs", issues 3 and 13; docs/formats.md):

* ``frames[depth, pattern, row, col]`` in the camera's dtype (uint8 up to 8 bits, else
  uint16). One frame is one stored object, a zarr shard of ``tile_px`` x ``tile_px`` inner
  chunks, uncompressed (``bytes`` little-endian) each followed by its ``crc32c``; the shard's
  index (``bytes`` + ``crc32c``) is at its end. The store writes the shard itself (each chunk
  the bytes zarr writes, chunks in row-major order where zarr 3.1 uses Morton order; in
  milliseconds instead of seconds) and reads tiles from it directly, verifying each chunk's
  crc32c; any zarr v3 reader reads the array too. Chosen by measurement
  (``benchmarks/run_store_io.py``, numbers in ``benchmarks/README.md``).
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
  :func:`station.acquisition.patterns.apply_lut`; null when none).
* written by the acquisition through the store's methods only: ``code_mask[depth, row,
  col]`` (``add_code_mask``), attributes ``retry_log`` (``log_retries``), ``status`` and
  ``end_time`` (``set_status``), ``frame_check`` (``set_frame_check``).
* ``writer.lock``: present while a writer holds the store (:mod:`station.acquisition.lock`).

Opening cross-checks the attributes against the arrays and the per-frame records (e.g. every
done frame's recorded stage target against ``depths_mm``). Creating is atomic: the store is
built under a temporary name beside ``path`` and renamed into place when complete.
"""

from __future__ import annotations

import contextlib
import ctypes
import datetime as _dt
import errno
import fcntl
import functools
import json
import os
import platform
import shutil
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from importlib import metadata as _metadata
from pathlib import Path

import google_crc32c
import numpy as np
import pydantic
import zarr
from pydantic import BaseModel, ConfigDict, Field
from zarr.codecs import BytesCodec, Crc32cCodec
from zarr.codecs.bytes import Endian

from station.acquisition.patterns import StationPatternPlan, apply_lut
from station.acquisition.store_attrs import RunStoreAttrs, check_attrs, open_zarr_group
from station.errors import StationError

CODE_MASK = "code_mask"  # array [depth, row, col] bool: camera pixels that see the check code

FORMAT = "ltc-run-store"
FORMAT_VERSION = 2
_CRC_BYTES = 4  # a crc32c, little-endian uint32, after each inner chunk and after the index
_EMPTY = 2**64 - 1


class RunStoreError(StationError, ValueError):
    """The run store is missing, malformed, incomplete or misused; the message names the path."""


class FrameCorruptError(RunStoreError):
    """A frame marked done is missing, truncated or fails its checksum; the message names the
    store, depth and pattern."""


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


def _fsync(path: Path) -> None:
    """Flush a file's (or a folder's entries') data to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _barrier(store: Path, written: list[Path]) -> None:
    """Make everything written so far durable before what comes next: one ``syncfs`` of the
    store's filesystem on Linux (one journal commit, about as fast as one fsync), else an
    fsync of each file in ``written`` and of its folder."""
    syncfs = getattr(_libc(), "syncfs", None)
    if syncfs is not None:
        fd = os.open(store, os.O_RDONLY)
        try:
            if syncfs(fd) != 0:
                err = ctypes.get_errno()
                raise OSError(err, os.strerror(err), str(store))
        finally:
            os.close(fd)
        return
    for path in written:
        _fsync(path)
        _fsync(path.parent)


@functools.cache
def _libc() -> object:
    try:
        return ctypes.CDLL(None, use_errno=True) if platform.system() == "Linux" else None
    except OSError:
        return None


def _write(path: Path, fd: int, parts: list, offset: int | None = None) -> None:
    """Write every buffer of ``parts`` to the open file ``fd`` (``path``), at its position or
    at byte ``offset``; an OSError names ``path``. Every byte the store writes itself
    (shards, per-frame records) goes through here."""
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


@contextlib.contextmanager
def _new_file(path: Path, flags: int = 0) -> Iterator[int]:
    """A new file written atomically: yields the descriptor of a temporary file beside
    ``path`` (opened with extra ``flags``; one the filesystem refuses with ``EINVAL`` is
    dropped), renamed to ``path`` when the block completes (removed if it raises)."""
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.partial")
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
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


DIRECT_ALIGN = 4096  # bytes: address and length a buffer needs to bypass the page cache


def aligned_empty(shape: tuple[int, ...], dtype: np.dtype | type) -> np.ndarray:
    """An uninitialised C-contiguous array whose memory starts on a ``DIRECT_ALIGN`` boundary
    (what :func:`write_new_file` can write straight to the device)."""
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    raw = np.empty(nbytes + DIRECT_ALIGN, np.uint8)
    skip = -raw.ctypes.data % DIRECT_ALIGN
    return raw[skip : skip + nbytes].view(dtype).reshape(shape)


def write_new_file(path: Path, parts: list) -> None:
    """Write a new file of ``parts`` (bytes-like) atomically: a temporary name, then a rename
    (:func:`_new_file`); an OSError names the file.

    One C-contiguous array whose address and size are multiples of ``DIRECT_ALIGN`` (an LTC
    tile from :func:`aligned_empty`) goes straight to the device (``O_DIRECT``): the page
    cache's copy of new pages cost 2-4 us of kernel CPU per LTC pixel (2.3 kB), as much as
    the pixel's inverse FFT, against about 0.1 us direct (``benchmarks/README.md``). A
    filesystem that refuses ``O_DIRECT`` (``EINVAL``) gets the same bytes through the page
    cache. Durability is unchanged: what makes a file durable is the caller's barrier."""
    direct = _direct_buffer(parts)
    with _new_file(path, os.O_DIRECT if direct is not None else 0) as fd:
        if direct is None:
            _write(path, fd, parts)
            return
        try:
            _write(path, fd, [direct])
        except OSError as exc:
            if exc.errno != errno.EINVAL:
                raise
            fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) & ~os.O_DIRECT)
            _write(path, fd, [direct], 0)


def _direct_buffer(parts: list) -> memoryview | None:
    """The bytes of ``parts`` if they can be written with ``O_DIRECT`` (one aligned
    C-contiguous array of a whole number of ``DIRECT_ALIGN`` blocks on Linux), else None."""
    if len(parts) != 1 or not hasattr(os, "O_DIRECT") or not isinstance(parts[0], np.ndarray):
        return None
    a = parts[0]
    if not a.flags.c_contiguous or a.nbytes == 0 or a.nbytes % DIRECT_ALIGN or \
            a.ctypes.data % DIRECT_ALIGN:
        return None
    return memoryview(a).cast("B")


def _start_writeback(fd: int, offset: int, nbytes: int) -> None:
    """Ask the kernel to start writing a file's byte range to disk now, without waiting
    (Linux ``sync_file_range(SYNC_FILE_RANGE_WRITE)``; elsewhere nothing): the disk writes a
    shard while the rest of it is encoded, so the barrier after it has little left to wait
    for. Durability still comes from the barrier only."""
    fn = _sync_file_range()
    if fn is not None:
        fn(fd, offset, nbytes, 2)  # SYNC_FILE_RANGE_WRITE; a failure only loses the head start


@functools.cache
def _sync_file_range() -> object:
    fn = getattr(_libc(), "sync_file_range", None)
    if fn is not None:
        fn.argtypes = [ctypes.c_int, ctypes.c_int64, ctypes.c_int64, ctypes.c_uint]
        fn.restype = ctypes.c_int
    return fn


def _crc(data: bytes | np.ndarray) -> int:
    """crc32c of bytes or of a read-only C-contiguous array's memory (no copy)."""
    return google_crc32c.value(data)


def _readonly(a: np.ndarray) -> np.ndarray:
    """A read-only view of ``a`` (what ``google_crc32c`` takes without a copy)."""
    v = a.view()
    v.flags.writeable = False
    return v


def _frame_crc(image: np.ndarray) -> int:
    """crc32c of a frame's pixels, (rows, cols) in C order, little-endian; computed on the
    frame's own memory when it is C-contiguous and little-endian (else on a copy)."""
    return _crc(_readonly(np.ascontiguousarray(image, image.dtype.newbyteorder("<"))))


def _pixel_stats(image: np.ndarray, full: int) -> tuple[int, int]:
    """(pixels >= ``full``, largest pixel value) of an image: one pass (numpy's vectorised
    max) unless the image reaches ``full``; only then are the saturated pixels counted."""
    top = int(image.max()) if image.size else 0
    return (int(np.count_nonzero(image >= full)) if top >= full else 0), top


@dataclass(frozen=True)
class FrameShard:
    """What :meth:`ShardCodec.encode` makes of a frame: ``chunks`` (the shard without its
    index, uint8, a reused buffer), the frame's ``crc32c`` (:func:`_frame_crc`), the count of
    pixels at or above full scale (``saturated``) and the largest pixel value (``top``)."""

    chunks: np.ndarray
    crc32c: int
    saturated: int
    top: int


@dataclass(frozen=True)
class EncodedFrame:
    """A frame between the stages of :meth:`RunStore.write_frame`: its shard's chunks (a
    codec's buffer) and index, the per-frame values to record (:data:`META_ARRAYS`) and,
    once stored, the files written."""

    depth: int
    pattern: int
    chunks: np.ndarray
    index: bytes
    values: dict
    written: list = field(default_factory=list)


class ShardCodec:
    """The bytes of one frame's shard: ``tile`` x ``tile`` chunks in row-major order, each its
    little-endian pixels then their crc32c, then the index ((offset, nbytes) uint64 per chunk)
    and its crc32c: zarr v3 ``sharding_indexed`` with inner codecs ``[bytes, crc32c]``."""

    def __init__(self, height: int, width: int, tile: int, dtype: np.dtype) -> None:
        self.h, self.w, self.t = height, width, tile
        self.dtype = np.dtype(dtype).newbyteorder("<")
        self.nr, self.nc = -(-height // tile), -(-width // tile)
        self.data_bytes = tile * tile * self.dtype.itemsize
        self.chunk_bytes = self.data_bytes + _CRC_BYTES
        n = self.nr * self.nc
        offsets = np.arange(n, dtype="<u8") * self.chunk_bytes
        index = np.stack([offsets, np.full(n, self.chunk_bytes, "<u8")], axis=1).tobytes()
        self.index = index + np.uint32(_crc(index)).astype("<u4").tobytes()
        self.size = n * self.chunk_bytes + len(self.index)
        self._buf: np.ndarray | None = None

    def _allocate(self) -> None:
        """The shard buffer (allocated once, so no page faults per frame), its pixels seen as
        (chunk rows, chunk cols, tile, tile), read-only views of each chunk's pixel bytes for
        the crc32c, and a zeroed strip for chunk rows with edge padding."""
        t, n = self.t, self.nr * self.nc
        self._buf = np.zeros((self.nr, self.nc, self.chunk_bytes), np.uint8)
        self._pix = self._buf[:, :, : self.data_bytes].view(self.dtype).reshape(
            self.nr, self.nc, t, t)
        flat = _readonly(self._buf).reshape(n, self.chunk_bytes)
        self._chunk_views = [flat[i, : self.data_bytes] for i in range(n)]
        self._crcs = self._buf.reshape(n, self.chunk_bytes)[:, self.data_bytes :].view("<u4")
        self._strip = np.zeros((t, self.nc * t), self.dtype)

    def encode(self, image: np.ndarray, full: int) -> FrameShard:
        """One frame's shard chunks and what the store records of the frame, in one pass over
        its pixels, chunk row by chunk row (each block of ``tile`` camera rows is read while it
        is in the CPU cache): the frame's crc32c continued over the block, the saturation count
        and maximum, one copy into shard order (edge chunk rows through a zero-padded strip),
        then each chunk's crc32c on the buffer in place. The buffer is reused: valid until the
        next call, one thread at once."""
        if self._buf is None:
            self._allocate()
        t, nc, w = self.t, self.nc, self.w
        img = _readonly(np.ascontiguousarray(image, self.dtype))  # no copy for camera frames
        aligned = w == nc * t
        crc, saturated, top = 0, 0, 0
        crc32c = google_crc32c.value  # looked up once: 2,176 calls per full-size frame
        for r in range(self.nr):
            rows = img[r * t : (r + 1) * t]
            crc = google_crc32c.extend(crc, rows)
            n_sat, row_top = _pixel_stats(rows, full)
            saturated, top = saturated + n_sat, max(top, row_top)
            if aligned and len(rows) == t:
                self._pix[r] = rows.reshape(t, nc, t).transpose(1, 0, 2)
            else:  # padding (fill value 0): columns >= w stay 0, rows past the frame zeroed
                self._strip[: len(rows), :w] = rows
                self._strip[len(rows) :] = 0
                self._pix[r] = self._strip.reshape(t, nc, t).transpose(1, 0, 2)
            self._crcs[r * nc : (r + 1) * nc, 0] = [
                crc32c(v) for v in self._chunk_views[r * nc : (r + 1) * nc]]
        return FrameShard(self._buf.reshape(-1), crc, saturated, top)

    def decode_chunks(self, raw: bytes, n_chunks: int) -> tuple[np.ndarray, int]:
        """(chunks (n, t, t), index of the first chunk failing its crc32c or -1)."""
        for i in range(n_chunks):
            o = i * self.chunk_bytes
            stored = int.from_bytes(raw[o + self.data_bytes : o + self.chunk_bytes], "little")
            if _crc(raw[o : o + self.data_bytes]) != stored:
                return np.empty(0), i
        arr = np.frombuffer(raw, np.uint8, n_chunks * self.chunk_bytes).reshape(n_chunks, -1)
        pix = arr[:, : self.data_bytes].view(self.dtype).reshape(n_chunks, self.t, self.t)
        return pix, -1


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
        self._small_kinds = {name: (np.dtype(group[name].dtype).newbyteorder("<"),
                                    group[name].fill_value) for name in ("done", *META_ARRAYS)}
        w, h = self.camera_size
        self.codec = ShardCodec(h, w, self.tile_px, self._frames.dtype)
        self._unflushed: Path | None = None

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
                **extra,
            })
            for folder, _, files in os.walk(tmp):
                for f in files:
                    _fsync(Path(folder) / f)
                _fsync(Path(folder))
            if path.exists():
                raise RunStoreError(f"{path}: appeared while creating the run store; "
                                    "refusing to overwrite it")
            os.rename(tmp, path)
            _fsync(path.parent)
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
        _cross_check(path, g, plan)
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
        with _new_file(final) as fd:
            _write(final, fd, [frame.chunks, frame.index])
            _start_writeback(fd, 0, frame.chunks.nbytes + len(frame.index))
        written = [self._set_small(name, frame.depth, frame.pattern, frame.values[name])
                   for name in self._meta]
        return replace(frame, written=[final, *written])

    def commit(self, frame: EncodedFrame) -> None:
        """Make a stored frame durable (one barrier: its shard and metadata reach the disk),
        then set its done flag (durable at the next barrier)."""
        _barrier(self.path, frame.written)
        self._mark_done(frame.depth, frame.pattern)

    def _mark_done(self, depth: int, pattern: int) -> None:
        """Set a frame's done flag (durable at the next barrier: :meth:`flush` or a write)."""
        self._unflushed = self._set_small("done", depth, pattern, True)

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
            _write(path, fd, [element], pattern * dtype.itemsize)
        finally:
            os.close(fd)
        return path

    def flush(self) -> None:
        """Make the done flags written so far durable (else the next frame's write does; a
        flag lost in a crash only means that frame is captured again)."""
        if self._unflushed is not None:
            _barrier(self.path, [self._unflushed])
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

    # ---- reading ----------------------------------------------------------------------------
    def code_mask(self, depth: int) -> np.ndarray:
        """(rows, cols) bool: camera pixels that saw the check code at this depth (no LTC)."""
        return np.asarray(self.group[CODE_MASK][depth])

    def read_meta(self, depth: int) -> dict[str, np.ndarray]:
        """Per-frame metadata of one depth: name -> (patterns,) array (fill where not done)."""
        self._check_index(depth, 0)
        return {name: np.asarray(arr[depth]) for name, arr in self._meta.items()}

    def read_frame(self, depth: int, pattern: int) -> np.ndarray:
        """One whole frame (rows, cols), checked against its recorded crc32c; refuses a frame
        that is not done (:class:`RunStoreError`) or is damaged (:class:`FrameCorruptError`)."""
        self._check_index(depth, pattern)
        if not bool(self._done[depth, pattern]):
            raise RunStoreError(f"{self.path}: frame ({depth}, {pattern}) is not done; "
                                "it may be partial and is not trusted")
        c = self.codec
        raw = self._read_bytes(depth, pattern, 0, c.size, whole=True)
        if raw[-len(c.index):] != c.index:
            self._corrupt(depth, pattern, "has a damaged shard index")
        chunks, bad = c.decode_chunks(raw, c.nr * c.nc)
        if bad >= 0:
            self._corrupt(depth, pattern, f"fails the crc32c of chunk {divmod(bad, c.nc)}")
        t = c.t
        img = chunks.reshape(c.nr, c.nc, t, t).transpose(0, 2, 1, 3).reshape(c.nr * t, c.nc * t)
        img = np.ascontiguousarray(img[: c.h, : c.w]).astype(self.dtype)
        if _frame_crc(img) != int(self._meta["frame_crc32c"][depth, pattern]):
            self._corrupt(depth, pattern, "differs from its crc32c recorded in 'frame_crc32c'")
        return img

    def read_tile(self, depth: int, row0: int, col0: int, rows: int, cols: int,
                  check_index: bool = False) -> Tile:
        """All frames of ``depth`` over camera rows ``row0 : row0 + rows`` and columns
        ``col0 : col0 + cols`` (clipped to the sensor), every chunk read checked against its
        crc32c. Each frame is one open and one read per chunk row the tile spans, so tiles
        aligned to ``tile_px`` read fastest. ``check_index`` also verifies each shard's index.
        The depth must be complete."""
        self._check_index(depth, 0)
        missing = np.flatnonzero(~self.done()[depth])
        if len(missing):
            raise RunStoreError(f"{self.path}: depth {depth} has {len(missing)} frame(s) not "
                                f"done (first: pattern {missing[0]}); finish it with --resume")
        return self._read_tile(depth, row0, col0, rows, cols, check_index)

    @contextlib.contextmanager
    def _open_shard(self, path: str | Path, depth: int, pattern: int,
                    check_index: bool) -> Iterator[int]:
        """A frame's shard file opened for reading (a file descriptor), refused if missing,
        of the wrong size or (``check_index``) with a damaged index."""
        c = self.codec
        try:
            fd = os.open(path, os.O_RDONLY)
        except FileNotFoundError:
            self._corrupt(depth, pattern, "is missing")
        try:
            size = os.fstat(fd).st_size
            if size != c.size:
                self._corrupt(depth, pattern, f"is truncated or resized ({size} bytes, "
                                              f"expected {c.size})")
            if check_index and os.pread(fd, len(c.index), c.size - len(c.index)) != c.index:
                self._corrupt(depth, pattern, "has a damaged shard index")
            yield fd
        finally:
            os.close(fd)

    def _read_tile(self, depth: int, row0: int, col0: int, rows: int, cols: int,
                   check_index: bool) -> Tile:
        c, t = self.codec, self.codec.t
        r1, c1 = min(row0 + rows, c.h), min(col0 + cols, c.w)
        if not (0 <= row0 < r1 and 0 <= col0 < c1):
            raise RunStoreError(f"{self.path}: tile rows {row0}+{rows}, cols {col0}+{cols} "
                                f"outside the camera's {c.w} x {c.h} pixels")
        cr0, cr1 = row0 // t, -(-r1 // t)
        cc0, cc1 = col0 // t, -(-c1 // t)
        k = cc1 - cc0
        out = np.empty((self.n_patterns, r1 - row0, c1 - col0), self.dtype)
        band = np.empty(((cr1 - cr0) * t, k * t), c.dtype)
        for p in range(self.n_patterns):
            path = self._shard_path(depth, p)
            with self._open_shard(path, depth, p, check_index) as fd:
                for cr in range(cr0, cr1):
                    raw = os.pread(fd, k * c.chunk_bytes, (cr * c.nc + cc0) * c.chunk_bytes)
                    if len(raw) != k * c.chunk_bytes:
                        self._corrupt(depth, p, "is truncated")
                    chunks, bad = c.decode_chunks(raw, k)
                    if bad >= 0:
                        self._corrupt(depth, p, f"fails the crc32c of chunk {(cr, cc0 + bad)} "
                                                f"(camera rows {cr * t}.., columns "
                                                f"{(cc0 + bad) * t}..)")
                    band[(cr - cr0) * t : (cr - cr0 + 1) * t] = \
                        chunks.transpose(1, 0, 2).reshape(t, k * t)
            out[p] = band[row0 - cr0 * t : r1 - cr0 * t, col0 - cc0 * t : c1 - cc0 * t]
        return Tile(depth, row0, col0, out)

    def read_tile_row(self, depth: int, row0: int, col0: int, n_tiles: int,
                      check_index: bool = False, out: np.ndarray | None = None) -> list[Tile]:
        """``n_tiles`` tiles of the store's chunk grid (``tile_px``, clipped at the sensor's
        edge) side by side from camera row ``row0`` and column ``col0`` (multiples of
        ``tile_px``): all frames of ``depth`` over each, every chunk checked against its
        crc32c (``check_index``: each shard's index too). Per frame one open and one
        ``preadv`` that puts each chunk's pixels straight into its tile (a chunk of the shard
        is a tile of the frame) and its crc32c beside: no copy in user space. ``out``: a
        buffer of at least (k, patterns, tile_px, tile_px) in the camera's dtype to reuse
        (default: a new one); the tiles' ``frames`` are views of it, contiguous (patterns,
        rows, cols) except at the sensor's edge. The depth must be complete (the caller
        checks)."""
        self._check_index(depth, 0)
        c, t = self.codec, self.codec.t
        if row0 % t or col0 % t or not (0 <= row0 < c.h and 0 <= col0 < c.w) or n_tiles < 1:
            raise RunStoreError(f"{self.path}: tile row at ({row0}, {col0}) x {n_tiles} is not "
                                f"on the {t}-pixel chunk grid of the camera's {c.w} x {c.h} "
                                "pixels")
        cr, cc0 = row0 // t, col0 // t
        k, n = min(n_tiles, c.nc - cc0), self.n_patterns
        shape = (k, n, t, t)
        if out is None:
            out = np.empty(shape, self.dtype)
        elif out.dtype != self.dtype or not out.flags.c_contiguous or out.size < np.prod(shape):
            raise RunStoreError(f"{self.path}: tile buffer of {out.dtype} {out.shape} cannot "
                                f"hold {shape} {self.dtype}")
        out = out.reshape(-1)[: int(np.prod(shape))].reshape(shape)
        dest = out.view(np.uint8).reshape(k, n, c.data_bytes)
        check = _readonly(dest)
        crcs = np.empty((k, _CRC_BYTES), np.uint8)  # the frame's chunks' stored crc32c
        stored = crcs.view("<u4")[:, 0]
        offset = (cr * c.nc + cc0) * c.chunk_bytes
        nbytes = k * c.chunk_bytes
        crc32c = google_crc32c.value
        folder = str(self._shard_path(depth, 0).parents[2])  # frames/c/<depth>
        for p in range(n):
            parts = [x for i in range(k) for x in (dest[i, p], crcs[i])]
            path = f"{folder}/{p}/0/0"
            with self._open_shard(path, depth, p, check_index) as fd:
                if os.preadv(fd, parts, offset) != nbytes:
                    self._corrupt(depth, p, "is truncated")
            for i in range(k):  # while the frame's chunks are in the CPU cache
                if crc32c(check[i, p]) != stored[i]:
                    self._corrupt(depth, p, f"fails the crc32c of chunk {(cr, cc0 + i)} "
                                            f"(camera rows {row0}.., columns {(cc0 + i) * t}..)")
        th = min(t, c.h - row0)
        tiles = []
        for i in range(k):
            tw = min(t, c.w - (cc0 + i) * t)
            f = out[i] if (th, tw) == (t, t) else np.ascontiguousarray(out[i, :, :th, :tw])
            tiles.append(Tile(depth, row0, (cc0 + i) * t, f))
        return tiles

    def prefetch_tile_row(self, depth: int, row0: int, col0: int, n_tiles: int) -> None:
        """Ask the kernel to start reading, in the background, the bytes that
        :meth:`read_tile_row` with the same arguments will read (``posix_fadvise``
        ``WILLNEED`` on each frame's range; nothing where that is not available): the disk
        then gets every frame's request at once instead of one after the other, and a caller
        that prefetches the next row of tiles before computing this one reads it from the
        page cache. A hint only: nothing is checked here (missing or short frames are
        skipped; :meth:`read_tile_row` refuses them)."""
        advise = getattr(os, "posix_fadvise", None)
        c, t = self.codec, self.codec.t
        if advise is None or row0 % t or col0 % t or not (0 <= row0 < c.h and 0 <= col0 < c.w):
            return
        cr, cc0 = row0 // t, col0 // t
        k = min(n_tiles, c.nc - cc0)
        offset, nbytes = (cr * c.nc + cc0) * c.chunk_bytes, k * c.chunk_bytes
        folder = str(self._shard_path(depth, 0).parents[2])
        for p in range(self.n_patterns):
            try:
                fd = os.open(f"{folder}/{p}/0/0", os.O_RDONLY)
            except OSError:
                continue
            try:
                advise(fd, offset, nbytes, os.POSIX_FADV_WILLNEED)
            except OSError:
                pass
            finally:
                os.close(fd)

    def iter_tiles(self, depth: int, tile_px: int | None = None,
                   block_bytes: int = 256 * 2**20) -> Iterator[Tile]:
        """All frames of ``depth`` over square tiles in row-major order (edge tiles smaller),
        every byte checked (chunk crc32c, shard size and index). The depth must be complete;
        ``tile_px`` defaults to the store's inner chunk. Frames are read in blocks of one tile
        row by as many tiles as fit in ``block_bytes``, one read per frame and chunk row; for
        the store's own tiles each block and the next are prefetched
        (:meth:`prefetch_tile_row`) and every block is read into one buffer (a new 256 MiB
        array per block cost more CPU, in page faults, than the read): a tile's frames are
        then valid until the iteration moves past its block; copy them to keep them."""
        self._check_index(depth, 0)
        missing = np.flatnonzero(~self.done()[depth])
        if len(missing):
            raise RunStoreError(f"{self.path}: depth {depth} has {len(missing)} frame(s) not "
                                f"done (first: pattern {missing[0]}); finish it with --resume")
        t = self.tile_px if tile_px is None else int(tile_px)
        if t < 1:
            raise RunStoreError(f"{self.path}: tile_px must be >= 1, got {tile_px}")
        w, h = self.camera_size
        per_tile = self.n_patterns * t * t * self.dtype.itemsize
        cols = t * max(1, block_bytes // max(per_tile, 1))
        if t == self.tile_px:  # the store's own chunks: each read straight into its tile
            blocks = [(r0, b0) for r0 in range(0, h, t) for b0 in range(0, w, cols)]
            buf = np.empty((cols // t, self.n_patterns, t, t), self.dtype)
            for i, (r0, b0) in enumerate(blocks):
                # the disk gets every frame's request of this block and the next at once
                # (the next is read while the caller works on this one): 2-2.6x faster
                # than one blocking read after the other on a busy disk
                for r1, b1 in blocks[(i > 0) + i : i + 2]:
                    self.prefetch_tile_row(depth, r1, b1, cols // t)
                yield from self.read_tile_row(depth, r0, b0, cols // t,
                                              check_index=r0 == 0 and b0 == 0, out=buf)
            return
        for r0 in range(0, h, t):
            for b0 in range(0, w, cols):
                block = self._read_tile(depth, r0, b0, t, cols, check_index=r0 == 0 and b0 == 0)
                for c0 in range(b0, min(b0 + cols, w), t):
                    yield Tile(depth, r0, c0, np.ascontiguousarray(
                        block.frames[:, :, c0 - b0 : c0 - b0 + t]))

    def verify(self) -> int:
        """Check every done frame against its recorded crc32c (reads the whole store); returns
        the number of frames checked, raises :class:`FrameCorruptError` at the first bad one."""
        done = self.done()
        for d, p in np.argwhere(done):
            self.read_frame(int(d), int(p))
        return int(done.sum())

    # ---- internals --------------------------------------------------------------------------
    def _shard_path(self, depth: int, pattern: int) -> Path:
        return self.path / "frames" / "c" / str(depth) / str(pattern) / "0" / "0"

    def _small_chunk(self, name: str, depth: int) -> Path:
        return self.path / name / "c" / str(depth) / "0"

    def _read_bytes(self, depth: int, pattern: int, offset: int, n: int,
                    whole: bool = False) -> bytes:
        try:
            with open(self._shard_path(depth, pattern), "rb") as f:
                size = os.fstat(f.fileno()).st_size
                if whole and size != self.codec.size:
                    self._corrupt(depth, pattern, f"is truncated or resized ({size} bytes, "
                                                  f"expected {self.codec.size})")
                f.seek(offset)
                return f.read(n)
        except FileNotFoundError:
            self._corrupt(depth, pattern, "is missing")

    def _corrupt(self, depth: int, pattern: int, why: str) -> None:
        raise FrameCorruptError(
            f"{self.path}: frame (depth {depth} = {self.depths_mm[depth]:g} mm, pattern "
            f"{pattern}) is marked done but its data {why} "
            f"(frames/c/{depth}/{pattern}/0/0); the run store is damaged")

    def _check_index(self, depth: int, pattern: int) -> None:
        if not (0 <= depth < self.n_depths and 0 <= pattern < self.n_patterns):
            raise RunStoreError(f"{self.path}: frame index (depth={depth}, pattern={pattern}) "
                                f"outside (0..{self.n_depths - 1}, 0..{self.n_patterns - 1})")


def _cross_check(path: Path, g: zarr.Group, plan: StationPatternPlan) -> None:
    """Refuse a store whose attributes disagree with its arrays or per-frame records; the
    message names the attribute."""
    a = g.attrs
    frames = g["frames"]
    t, bits = a["tile_px"], a["bit_depth"]
    w, h = a["camera_size"]
    want_dtype = np.dtype("uint8" if int(bits) <= 8 else "uint16")
    if frames.dtype != want_dtype:
        raise RunStoreError(f"{path}: attribute 'bit_depth' ({bits}) disagrees with array "
                            f"'frames' dtype {frames.dtype}")
    if tuple(frames.chunks) != (1, 1, t, t) or tuple(frames.shards or ()) != \
            (1, 1, -(-h // t) * t, -(-w // t) * t):
        raise RunStoreError(f"{path}: attribute 'tile_px' ({t}) disagrees with array 'frames' "
                            f"chunks {frames.chunks} / shards {frames.shards}")
    if not (isinstance(frames.serializer, BytesCodec) and frames.filters == ()
            and len(frames.compressors) == 1 and isinstance(frames.compressors[0], Crc32cCodec)):
        raise RunStoreError(f"{path}: array 'frames' has codecs {frames.compressors}, expected "
                            "uncompressed chunks with crc32c (run-store format 2)")
    n = len(plan)
    for name in ("done", *META_ARRAYS):  # the store rewrites these chunks itself
        arr = g[name]
        if tuple(arr.chunks) != (1, n) or arr.filters != () or arr.compressors != () or \
                not isinstance(arr.serializer, BytesCodec) or \
                arr.serializer.endian not in (None, Endian.little):
            raise RunStoreError(f"{path}: array '{name}' has chunks {arr.chunks} and codecs "
                                f"{arr.serializer}, {arr.compressors}; expected one "
                                f"uncompressed little-endian chunk of {n} per depth "
                                "(run-store format 2)")
    if not plan.localisation.covers(a["lcd_size"]):
        raise RunStoreError(f"{path}: attribute 'lcd_size' {a['lcd_size']} disagrees with the "
                            "pattern set (its Gray code does not cover it)")
    config = a["config"] if isinstance(a["config"], dict) else {}
    for key, value in (("depths_mm", a["depths_mm"]),
                       ("display_lut", a["display_lut"])):
        if key in config and config[key] is not None and value is not None and \
                not np.array_equal(np.asarray(config[key], float), np.asarray(value, float)):
            raise RunStoreError(f"{path}: attribute '{key}' disagrees with the stored "
                                f"config's {key}")
    pitch = (config.get("display") or {}).get("pitch_mm") if isinstance(
        config.get("display"), dict) else None
    if pitch is not None and float(pitch) != float(a["lcd_pitch_mm"]):
        raise RunStoreError(f"{path}: attribute 'lcd_pitch_mm' ({a['lcd_pitch_mm']}) disagrees "
                            f"with the stored config's display.pitch_mm ({pitch})")
    done = np.asarray(g["done"][...], bool)
    if not done.any():
        return
    target = np.asarray(g["stage_target_mm"][...])
    depths = np.asarray(a["depths_mm"], float)
    bad = np.argwhere(done & (target != depths[:, None]))
    if len(bad):
        d, p = (int(v) for v in bad[0])
        raise RunStoreError(
            f"{path}: attribute 'depths_mm' {list(a['depths_mm'])} disagrees with the recorded "
            f"stage target of {len(bad)} done frame(s) (first: depth {d}, pattern {p} at "
            f"{target[d, p]} mm, attribute says {depths[d]} mm)")
    crc = np.asarray(g["frame_crc32c"][...])
    bad = np.argwhere(done & (crc < 0))
    if len(bad):
        d, p = (int(v) for v in bad[0])
        raise RunStoreError(f"{path}: frame (depth {d}, pattern {p}) is marked done but has "
                            "no checksum in 'frame_crc32c'; the run store is damaged")
