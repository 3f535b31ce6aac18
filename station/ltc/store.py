"""The LTC store (zarr v3): per depth and camera pixel, a P x P window of LTC weights.

Layout (docs/architecture.md, docs/formats.md):

* ``ltc[depth, row, col, P, P]`` float32, each pixel's LTC normalised to sum 1 (NaN where
  the pixel has no signal); window element ``[r, s]`` is LCD pixel
  ``(origin_col + s, origin_row + r)``.
* ``origin[depth, row, col, 2]`` int32, LCD (column, row) of window element ``[0, 0]``.
* ``gain[depth, row, col]`` float32, response to full white (ADU above black).
* ``noise[depth, row, col]`` float32, estimated std of one LTC weight.
* ``lcd_xy[depth, row, col, 2]`` float32, LCD (x, y) the pixel looks at, decoded from the
  localisation patterns (NaN where unknown).
* attributes: ``depths_mm``, ``pitch_mm``, ``period``, ``lcd_size`` (w, h),
  ``camera_size`` (w, h), ``format`` and ``format_version``, plus anything the writer adds.
* completion records (format version 2): ``tile_done[depth, tile_row, tile_col]`` bool,
  True once that ``tile_px`` x ``tile_px`` tile of every array above is written (set after the
  tile's data, so a killed writer loses at most the tiles in flight);
  ``tile_stats[depth, tile_row, tile_col, 4]`` float64, the tile's valid-pixel count and the
  medians of gain and noise and the 95th percentile of |edge mass| over its valid pixels
  (NaN when none); attribute ``tile_px``; attribute ``depths_complete`` (list of bool per
  depth), set True once every tile of the depth is done. Readers of a whole store
  (``open_ltc_volume``) refuse one with an incomplete depth, naming it.
* checksums (format version 3): ``tile_crc32c[depth, tile_row, tile_col, 5]`` int64, the
  crc32c of each done tile's chunk file of ``ltc``, ``origin``, ``gain``, ``noise`` and
  ``lcd_xy`` (:mod:`station.ltc.checked`), recorded with the tile's done flag; every read
  through ``open_ltc_volume`` verifies them. Attribute ``run_id``: the identity of the run
  store reconstructed (``RunStore.identity``), which ``--resume`` compares.
* ``writer.lock``: held by the one writer (:mod:`sim.storage.lock`).

Writing: ``create_ltc_store``, ``write_ltc_tile``, ``mark_tile_done`` (``TileRecords``) and
``mark_depth_complete``. Reading for the lens derivation: ``open_ltc_volume`` gives an
``LtcVolume`` that reads camera rows on demand.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp
import zarr

from sim.storage.attrs import LtcStoreAttrs, check_attrs, open_zarr_group
from sim.storage.checksum import NO_CRC, crc32c, readonly
from sim.storage.durable import (
    aligned_empty,
    publish,
    sync_tree,
    temporary_name,
    write_new_file,
)
from station.errors import StationError
from station.ltc.checked import (  # noqa: F401 - LtcChunkError, CheckedArray: store names
    CHECKED_ARRAYS,
    CRC_ARRAY,
    CheckedArray,
    LtcChunkError,
    checked_arrays,
    seal_tiles,
)

FORMAT = "ltc-store"
FORMAT_VERSION = 3
TILE_STATS = ("valid_px", "gain_median_adu", "noise_median", "edge_mass_p95")
ARRAYS = ("ltc", "origin", "gain", "noise")
OPTIONAL_ARRAYS = ("lcd_xy",)


class LtcStoreError(StationError, ValueError):
    """The LTC store is missing, malformed or of another format; the message names the path."""


def create_ltc_store(
    path: str | Path,
    *,
    depths_mm: list[float],
    camera_size: tuple[int, int],
    period: int,
    pitch_mm: float,
    lcd_size: tuple[int, int],
    tile_px: int = 64,
    attrs: dict | None = None,
) -> zarr.Group:
    """Create an empty LTC store, atomically (built under a temporary name beside ``path``,
    flushed and renamed); refuses to overwrite an existing path."""
    path = Path(path)
    if path.exists():
        raise LtcStoreError(f"{path}: already exists; refusing to overwrite an LTC store")
    w, h = camera_size
    d = len(depths_mm)
    # built under a temporary name and renamed: a writer killed here leaves no store at path
    tmp = temporary_name(path, "creating")
    g = zarr.open_group(str(tmp), mode="w-", zarr_format=3)
    t = (1, min(tile_px, h), min(tile_px, w))
    # uncompressed: noisy float32 windows compress to 0.93 with zstd, whose encoding cost
    # about as much as the tile's reconstruction (docs/decisions 0008)
    g.create_array("ltc", shape=(d, h, w, period, period), chunks=t + (period, period),
                   dtype="float32", fill_value=np.nan, compressors=None)
    # the per-pixel scalars too (1 % of the store): every tile's chunks are then written as
    # plain files (``_write_raw_chunk``), 20 ms less per tile than four zarr writes
    g.create_array("origin", shape=(d, h, w, 2), chunks=t + (2,), dtype="int32", fill_value=0,
                   compressors=None)
    g.create_array("gain", shape=(d, h, w), chunks=t, dtype="float32", fill_value=np.nan,
                   compressors=None)
    g.create_array("noise", shape=(d, h, w), chunks=t, dtype="float32", fill_value=np.nan,
                   compressors=None)
    g.create_array("lcd_xy", shape=(d, h, w, 2), chunks=t + (2,), dtype="float32",
                   fill_value=np.nan, compressors=None)
    tiles = (-(-h // t[1]), -(-w // t[2]))
    # completion records: small, one chunk per depth, rewritten whole (atomically) per tile
    g.create_array("tile_done", shape=(d,) + tiles, chunks=(1,) + tiles, dtype="bool",
                   fill_value=False, compressors=None)
    g.create_array("tile_stats", shape=(d,) + tiles + (len(TILE_STATS),),
                   chunks=(1,) + tiles + (len(TILE_STATS),), dtype="float64",
                   fill_value=np.nan, compressors=None)
    g.create_array(CRC_ARRAY, shape=(d,) + tiles + (len(CHECKED_ARRAYS),),
                   chunks=(1,) + tiles + (len(CHECKED_ARRAYS),), dtype="int64",
                   fill_value=NO_CRC, compressors=None)
    g.attrs.update(
        {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "depths_mm": [float(z) for z in depths_mm],
            "camera_size": [int(w), int(h)],
            "period": int(period),
            "pitch_mm": float(pitch_mm),
            "lcd_size": [int(v) for v in lcd_size],
            "tile_px": int(tile_px),
            "depths_complete": [False] * d,
            **(attrs or {}),
        }
    )
    try:
        sync_tree(tmp)
        publish(tmp, path)
    except FileExistsError as exc:
        import shutil

        shutil.rmtree(tmp, ignore_errors=True)
        raise LtcStoreError(f"{path}: appeared while creating the LTC store; refusing to "
                            "overwrite it") from exc
    return zarr.open_group(str(path), mode="r+")


def open_ltc_store(path: str | Path, mode: str = "r") -> zarr.Group:
    """Open and validate an LTC store."""
    path = Path(path)
    if not path.exists():
        raise LtcStoreError(f"{path}: no such LTC store")
    g = open_zarr_group(path, mode, LtcStoreError, "LTC store")
    if g.attrs.get("format") != FORMAT:
        raise LtcStoreError(f"{path}: attribute 'format' is {g.attrs.get('format')!r}, "
                            f"expected {FORMAT!r}")
    if g.attrs.get("format_version") == 2:
        raise LtcStoreError(f"{path}: attribute 'format_version' is 2, a layout without chunk "
                            f"checksums this software does not read (it reads {FORMAT_VERSION})"
                            "; reconstruct it again (`ltc reconstruct`)")
    if g.attrs.get("format_version") != FORMAT_VERSION:
        raise LtcStoreError(f"{path}: attribute 'format_version' is "
                            f"{g.attrs.get('format_version')!r}, expected {FORMAT_VERSION}; "
                            "reconstruct it again with this version (`ltc reconstruct`)")
    check_attrs(path, g.attrs, LtcStoreAttrs, LtcStoreError)
    missing = [a for a in ARRAYS + ("tile_done", "tile_stats", CRC_ARRAY) if a not in g]
    if missing:
        raise LtcStoreError(f"{path}: missing array(s) {missing}")
    return g


def mark_tile_done(group: zarr.Group, depth: int, tile_row: int, tile_col: int,
                   stats: np.ndarray) -> None:
    """Record a written tile: its statistics (``TILE_STATS``) and the checksums of its chunk
    files as they are now, then its done flag."""
    group["tile_stats"][depth, tile_row, tile_col] = np.asarray(stats, dtype=np.float64)
    group[CRC_ARRAY][depth, tile_row, tile_col] = seal_tiles(group, depth,
                                                             [(tile_row, tile_col)])[0]
    group["tile_done"][depth, tile_row, tile_col] = True


class TileRecords:
    """The completion records (``tile_stats``, ``tile_crc32c``, ``tile_done``) of an LTC store
    held by its one writer: read once, then each :meth:`mark` rewrites the depth's three
    chunks (statistics and checksums first, then done flags; each chunk file written whole
    and renamed into place, as zarr writes it) without reading them back."""

    def __init__(self, group: zarr.Group) -> None:
        self.group = group
        self.stats = np.asarray(group["tile_stats"][...], dtype=np.float64)
        self.crcs = np.asarray(group[CRC_ARRAY][...], dtype=np.int64)
        self.done = np.asarray(group["tile_done"][...], dtype=bool)

    def mark(self, depth: int, tile_row: int, tile_cols: list[int],
             stats: list[np.ndarray], crcs: list[np.ndarray] | None = None) -> None:
        """Record written tiles of one tile row: their statistics and chunk checksums
        (``crcs`` per tile, in ``CHECKED_ARRAYS`` order; None: computed from the files now),
        then their done flags."""
        cols = np.asarray(tile_cols, dtype=np.int64)
        self.stats[depth, tile_row, cols] = np.asarray(stats, np.float64).reshape(len(cols), -1)
        if crcs is None:
            crcs = list(seal_tiles(self.group, depth, [(tile_row, int(c)) for c in cols]))
        self.crcs[depth, tile_row, cols] = np.asarray(crcs, np.int64).reshape(len(cols), -1)
        self.done[depth, tile_row, cols] = True
        for name, values in (("tile_stats", self.stats), (CRC_ARRAY, self.crcs),
                             ("tile_done", self.done)):
            arr = self.group[name]
            if _write_raw_chunk(self.group, arr, depth, 0, 0, values[depth]) is None:
                arr[depth] = values[depth]


def mark_depth_complete(group: zarr.Group, depth: int, all_tiles: bool = False) -> None:
    """Mark a depth complete; refused unless every one of its tiles is done.
    all_tiles : first mark every tile done (a writer that filled the whole depth at once)."""
    done = np.asarray(group["tile_done"][depth])
    if all_tiles:
        tiles = [(int(r), int(c)) for r, c in np.argwhere(np.ones_like(done))]
        group[CRC_ARRAY][depth] = seal_tiles(group, depth, tiles).reshape(
            done.shape + (len(CHECKED_ARRAYS),))
        group["tile_done"][depth] = np.ones_like(done)
    elif not done.all():
        raise LtcStoreError(f"{group.store}: depth {depth} has {int((~done).sum())} tile(s) "
                            "not written; it cannot be marked complete")
    flags = list(group.attrs["depths_complete"])
    flags[depth] = True
    group.attrs["depths_complete"] = flags


def incomplete_depths(group: zarr.Group) -> list[int]:
    """Depth indices of an LTC store not recorded complete (attribute and tile flags)."""
    flags = list(group.attrs.get("depths_complete", []))
    d = group["ltc"].shape[0]
    done = np.asarray(group["tile_done"][...])
    return [i for i in range(d) if not (i < len(flags) and flags[i] and done[i].all())]


def require_complete(group: zarr.Group, path: str | Path) -> None:
    """Raise ``LtcStoreError`` naming the first incomplete depth, if any."""
    todo = incomplete_depths(group)
    if todo:
        z = group.attrs.get("depths_mm", [])
        i = todo[0]
        at = f" (z = {z[i]:g} mm)" if i < len(z) else ""
        n = int((~np.asarray(group["tile_done"][i])).sum())
        raise LtcStoreError(f"{path}: depth {i}{at} is incomplete ({n} tile(s) not written; "
                            f"{len(todo)} incomplete depth(s)); finish it with "
                            "`ltc reconstruct --resume`")


def write_ltc_tile(
    group: zarr.Group, depth: int, row0: int, col0: int, **arrays: np.ndarray
) -> None:
    """Write one tile of camera pixels into an LTC store at ``[depth, row0:, col0:]``.

    arrays : by name (``ltc`` (th, tw, P, P), ``origin`` (th, tw, 2), ``gain`` and ``noise``
    (th, tw), ``lcd_xy`` (th, tw, 2)); each is cast to the stored dtype. A tile aligned with
    the store's chunks rewrites whole chunks only. A writer of many tiles keeps one
    :class:`LtcTileWriter` instead (it looks the arrays up once).
    """
    LtcTileWriter(group).write(depth, row0, col0, **arrays)


class LtcTileWriter:
    """Writes tiles into one LTC store (:func:`write_ltc_tile`), its arrays looked up once
    (each zarr lookup reads metadata: ~0.35 ms of CPU, 0.4 us per pixel of a 64 x 64 tile
    for the five arrays)."""

    def __init__(self, group: zarr.Group) -> None:
        self.group = group
        self._arrays: dict[str, zarr.Array] = {}

    def write(self, depth: int, row0: int, col0: int, **arrays: np.ndarray) -> np.ndarray:
        """See :func:`write_ltc_tile`; returns the tile's chunk checksums in
        ``CHECKED_ARRAYS`` order (what :meth:`TileRecords.mark` records)."""
        crcs = {}
        for name, value in arrays.items():
            if name not in ARRAYS + OPTIONAL_ARRAYS:
                raise LtcStoreError(f"{self.group.store}: no LTC store array named {name!r}; "
                                    f"expected one of {ARRAYS + OPTIONAL_ARRAYS}")
            arr = self._arrays.get(name)
            if arr is None:
                arr = self._arrays[name] = self.group[name]
            v = np.asarray(value)
            crc = _write_raw_chunk(self.group, arr, depth, row0, col0, v)
            if crc is None:
                arr[depth, row0 : row0 + v.shape[0], col0 : col0 + v.shape[1]] = \
                    v.astype(arr.dtype)
            crcs[name] = crc
        ch, cw = self.group["ltc"].chunks[1:3]
        sealed = None
        out = np.empty(len(CHECKED_ARRAYS), np.int64)
        for k, name in enumerate(CHECKED_ARRAYS):
            crc = crcs.get(name)
            if crc is None:
                if sealed is None:
                    sealed = seal_tiles(self.group, depth, [(row0 // ch, col0 // cw)])[0]
                out[k] = sealed[k]
            else:
                out[k] = crc
        return out


def _write_raw_chunk(group: zarr.Group, arr: zarr.Array, depth: int, row0: int, col0: int,
                     v: np.ndarray) -> int | None:
    """Write ``v`` as the one whole chunk ``arr[depth, row0:, col0:]`` it covers, as the file
    zarr would write (uncompressed little-endian bytes, edge chunks padded with the fill
    value, written to a temporary name and renamed, as the run store writes its files), when
    the array is stored that way on a local folder and ``v`` is exactly one chunk (clipped at
    the sensor's edge), returning the file's crc32c; else None. 3x faster than zarr's write
    path for the ``ltc`` array (9.4 MB per 64 x 64 tile at P = 24)."""
    from zarr.codecs import BytesCodec
    from zarr.codecs.bytes import Endian
    from zarr.core.chunk_key_encodings import DefaultChunkKeyEncoding
    from zarr.storage import LocalStore

    chunks, shape = tuple(arr.chunks), tuple(arr.shape)
    enc = arr.metadata.chunk_key_encoding
    if not (isinstance(group.store, LocalStore) and arr.compressors == () and arr.filters == ()
            and isinstance(arr.serializer, BytesCodec)
            and arr.serializer.endian in (None, Endian.little)
            and isinstance(enc, DefaultChunkKeyEncoding) and enc.separator == "/"):
        return None
    th, tw = v.shape[:2]
    ch, cw = chunks[1], chunks[2]
    if chunks[0] != 1 or chunks[3:] != shape[3:] or v.shape[2:] != shape[3:] or \
            row0 % ch or col0 % cw or th != min(ch, shape[1] - row0) or \
            tw != min(cw, shape[2] - col0):
        return None
    dtype = np.dtype(arr.dtype).newbyteorder("<")
    if (th, tw) == (ch, cw):
        data = np.ascontiguousarray(v, dtype)
    else:
        data = aligned_empty(chunks[1:], dtype)
        data[...] = arr.fill_value
        data[:th, :tw] = v
    key = [depth, row0 // ch, col0 // cw] + [0] * (len(shape) - 3)
    path = Path(group.store.root) / arr.path / "c" / "/".join(str(k) for k in key)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_new_file(path, [data])  # atomic; an OSError names the file
    return crc32c(readonly(data))


def windows_from_sparse(
    m: sp.csr_array,
    lcd_size: tuple[int, int],
    period: int,
    origin: np.ndarray,
) -> np.ndarray:
    """Cut P x P windows out of per-pixel sparse LTC rows.

    m : (n, lcd_h*lcd_w) sparse, rows are pixels; origin : (n, 2) int LCD (col, row) of each
    window's element [0, 0]. Returns (n, P, P) float64 (weights outside the LCD are 0).
    """
    lw, lh = lcd_size
    m = sp.csr_array(m)
    origin = np.asarray(origin, dtype=np.int64).reshape(-1, 2)
    out = np.zeros((m.shape[0], period, period))
    counts = np.diff(m.indptr)
    rows = np.repeat(np.arange(m.shape[0]), counts)
    col, row = m.indices % lw, m.indices // lw
    s = col - origin[rows, 0]
    r = row - origin[rows, 1]
    ok = (s >= 0) & (s < period) & (r >= 0) & (r < period)
    np.add.at(out, (rows[ok], r[ok], s[ok]), m.data[ok])
    return out


def centred_origins(centres_xy: np.ndarray, period: int) -> np.ndarray:
    """Window origins (n, 2) int that centre a P x P window on LCD points (n, 2) (x, y)."""
    c = np.asarray(centres_xy, dtype=np.float64).reshape(-1, 2)
    return (np.floor(c + 0.5) - period // 2).astype(np.int32)


class LtcVolumeError(StationError, ValueError):
    """An LTC volume is unusable; the message names the source, array and element."""


@dataclass(frozen=True)
class LtcVolume:
    """The LTC of every pixel at every depth; arrays may be numpy or zarr (read by rows).

    ltc : (D, H, W, P, P) weights, each window summing to 1, NaN where no signal.
    origin : (D, H, W, 2) int, LCD (column, row) of window element [0, 0].
    gain : (D, H, W) response to full white, ADU above black (relative transmittance).
    noise : (D, H, W) std of one LTC weight.
    depths_mm : (D,) stage readings, mm; pitch_mm : LCD pixel pitch, mm.
    camera_matrix, dist_coeffs : the camera's K (3x3) and OpenCV distortion, if known.
    name : where it came from, for error messages.
    """

    ltc: Any
    origin: Any
    gain: Any
    noise: Any
    depths_mm: np.ndarray
    pitch_mm: float
    camera_matrix: np.ndarray | None = None
    dist_coeffs: np.ndarray | None = None
    name: str = "<memory>"

    def __post_init__(self) -> None:
        depths = np.asarray(self.depths_mm, dtype=np.float64).ravel()
        object.__setattr__(self, "depths_mm", depths)
        n = self.name
        if len(depths) < 2:
            raise LtcVolumeError(f"{n}: depths_mm has {len(depths)} depth(s); the lens "
                                 "derivation needs at least 2 depths (better 5-6)")
        if not np.all(np.isfinite(depths)) or len(np.unique(depths)) != len(depths):
            raise LtcVolumeError(f"{n}: depths_mm must be finite and distinct, got {depths}")
        if not (np.isfinite(self.pitch_mm) and self.pitch_mm > 0):
            raise LtcVolumeError(f"{n}: pitch_mm must be > 0, got {self.pitch_mm}")
        shape = tuple(self.ltc.shape)
        if len(shape) != 5 or shape[0] != len(depths) or shape[3] != shape[4]:
            raise LtcVolumeError(f"{n}: ltc has shape {shape}, expected (D={len(depths)}, H, W, "
                                 "P, P)")
        for field, want in (("origin", shape[:3] + (2,)), ("gain", shape[:3]),
                            ("noise", shape[:3])):
            got = tuple(getattr(self, field).shape)
            if got != want:
                raise LtcVolumeError(f"{n}: {field} has shape {got}, expected {want}")
        if self.camera_matrix is not None:
            k = np.asarray(self.camera_matrix, dtype=np.float64)
            if k.shape != (3, 3) or not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0:
                raise LtcVolumeError(f"{n}: camera_matrix must be a finite 3x3 K with "
                                     f"fx, fy > 0, got {k.tolist()}")
            object.__setattr__(self, "camera_matrix", k)

    @property
    def camera_size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return int(self.ltc.shape[2]), int(self.ltc.shape[1])

    @property
    def chunk_rows(self) -> int:
        """Camera rows per stored chunk of ``ltc`` (64 for in-memory arrays)."""
        chunks = getattr(self.ltc, "chunks", None)
        return int(chunks[1]) if chunks else 64

    def rows(self, r0: int, r1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``ltc, origin, gain, noise`` of camera rows ``r0:r1`` as float64/int64 arrays."""
        return (
            np.asarray(self.ltc[:, r0:r1], dtype=np.float64),
            np.asarray(self.origin[:, r0:r1], dtype=np.int64),
            np.asarray(self.gain[:, r0:r1], dtype=np.float64),
            np.asarray(self.noise[:, r0:r1], dtype=np.float64),
        )


def open_ltc_volume(path: str | Path) -> LtcVolume:
    """An ``LtcVolume`` reading from an LTC store (``station/ltc/store.py``) on demand, every
    chunk verified against its recorded crc32c (:class:`station.ltc.checked.CheckedArray`).

    Optional attributes ``camera_matrix`` (3x3) and ``dist_coeffs`` (5) give the camera's K.
    """
    g = open_ltc_store(path)
    require_complete(g, path)
    checked = checked_arrays(Path(path), g)
    a = g.attrs
    for key in ("depths_mm", "pitch_mm"):
        if key not in a:
            raise LtcStoreError(f"{path}: attribute {key!r} is missing")
    k = a.get("camera_matrix")
    d = a.get("dist_coeffs")
    return LtcVolume(
        ltc=checked["ltc"], origin=checked["origin"], gain=checked["gain"],
        noise=checked["noise"],
        depths_mm=np.asarray(a["depths_mm"], dtype=np.float64), pitch_mm=float(a["pitch_mm"]),
        camera_matrix=None if k is None else np.asarray(k, dtype=np.float64),
        dist_coeffs=None if d is None else np.asarray(d, dtype=np.float64),
        name=str(path),
    )
