"""Checksummed chunks of an LTC store: what each tile's chunk files hold is recorded in
``tile_crc32c[depth, tile_row, tile_col, array]`` when the tile is recorded done, and every
read of a done tile's chunk is verified against it.

A record is the crc32c of the chunk file's bytes (int64), :data:`ABSENT` for a chunk zarr did
not write because it holds only the fill value, -1 while not recorded. A chunk whose file is
missing, has the wrong size or fails its crc32c is refused with :class:`LtcChunkError`
naming the store, the array, the depth and the tile. A process verifies a chunk when it first
reads it whole; later reads of a few of its rows read only those rows while the chunk's file
is unchanged (same inode, size and modification time), else the chunk is verified again.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import zarr

from sim.storage.checksum import NO_CRC, crc32c, readonly
from station.errors import StationError

CHECKED_ARRAYS = ("ltc", "origin", "gain", "noise", "lcd_xy")  # order of tile_crc32c's last axis
CRC_ARRAY = "tile_crc32c"
ABSENT = -2  # record: the chunk holds only the fill value and has no file


class LtcChunkError(StationError, ValueError):
    """A chunk of an LTC store is missing, truncated or altered; the message names the store,
    array, depth and tile."""


def chunk_path(root: Path, name: str, depth: int, tile_row: int, tile_col: int,
               ndim: int) -> Path:
    """The file of chunk (depth, tile_row, tile_col, 0, ...) of array ``name`` (zarr v3
    default chunk keys, ``/`` separated)."""
    key = [depth, tile_row, tile_col] + [0] * (ndim - 3)
    return root / name / "c" / "/".join(str(k) for k in key)


def file_crc(path: Path) -> int:
    """The record of a chunk file as it is on disk: its crc32c, or :data:`ABSENT`."""
    try:
        with open(path, "rb") as f:
            return crc32c(f.read())
    except FileNotFoundError:
        return ABSENT


def seal_tiles(group: zarr.Group, depth: int, tiles: list[tuple[int, int]]) -> np.ndarray:
    """Records (n, len(CHECKED_ARRAYS)) of tiles (tile_row, tile_col) of ``depth`` computed
    from their chunk files as they are now (for tiles written through zarr)."""
    root = Path(group.store.root)
    out = np.full((len(tiles), len(CHECKED_ARRAYS)), NO_CRC, np.int64)
    for k, name in enumerate(CHECKED_ARRAYS):
        if name not in group:
            continue
        ndim = group[name].ndim
        for i, (tr, tc) in enumerate(tiles):
            out[i, k] = file_crc(chunk_path(root, name, depth, tr, tc, ndim))
    return out


class CheckedArray:
    """Read-only view of one array of an LTC store whose reads verify each chunk of a done
    tile against its recorded crc32c. Indexing: ints and unit-step slices on the first three
    axes (depth, row, col), anything numpy takes on the rest; returns numpy arrays. Picklable
    (worker processes read through it too)."""

    def __init__(self, root: Path, array: zarr.Array, records: np.ndarray,
                 done: np.ndarray, verify: bool = True) -> None:
        self.root = Path(root)
        self.verify = verify  # False only to measure what verifying costs (benchmarks)
        self.name = array.basename
        self.shape = tuple(int(v) for v in array.shape)
        self.chunks = tuple(int(v) for v in array.chunks)
        self.dtype = np.dtype(array.dtype)
        self.ndim = len(self.shape)
        fill = array.fill_value
        self.fill = np.asarray(fill if fill is not None else 0, self.dtype)
        self.records = np.asarray(records, np.int64)  # (D, TR, TC)
        self.done = np.asarray(done, bool)  # (D, TR, TC)
        self._stored = np.dtype(self.dtype).newbyteorder("<")
        self._nbytes = int(np.prod(self.chunks)) * self.dtype.itemsize
        self._row_bytes = self._nbytes // self.chunks[1]
        self._last: tuple[tuple[int, int, int], np.ndarray] | None = None
        # chunks verified whole by this process: key -> the file's (inode, size, mtime_ns)
        self._verified: dict[tuple[int, int, int], tuple[int, int, int]] = {}

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_last"], state["_verified"] = None, {}
        return state

    def __len__(self) -> int:
        return self.shape[0]

    def __array__(self, dtype=None, copy=None) -> np.ndarray:  # noqa: ANN001 - numpy protocol
        a = self[...]
        return a if dtype is None else a.astype(dtype)

    def __getitem__(self, key: object) -> np.ndarray:
        key = key if isinstance(key, tuple) else (key,)
        if any(k is Ellipsis for k in key):
            i = next(i for i, k in enumerate(key) if k is Ellipsis)
            key = key[:i] + (slice(None),) * (self.ndim - len(key) + 1) + key[i + 1:]
        head, rest = key[:3], key[3:]
        ranges, drop = [], []
        for ax in range(3):
            k = head[ax] if ax < len(head) else slice(None)
            n = self.shape[ax]
            if isinstance(k, (int, np.integer)):
                i = int(k) + (n if int(k) < 0 else 0)
                if not 0 <= i < n:
                    raise IndexError(f"{self.root}: index {int(k)} out of range for axis {ax} "
                                     f"of array '{self.name}' of size {n}")
                ranges.append((i, i + 1))
                drop.append(ax)
            elif isinstance(k, slice):
                a, b, step = k.indices(n)
                if step != 1:
                    raise IndexError(f"{self.root}: array '{self.name}': only unit-step slices "
                                     "on (depth, row, col)")
                ranges.append((a, max(a, b)))
            else:
                raise IndexError(f"{self.root}: array '{self.name}': index {k!r} not supported")
        out = np.empty(tuple(b - a for a, b in ranges) + self.shape[3:], self.dtype)
        (d0, d1), (r0, r1), (c0, c1) = ranges
        _, ch, cw = self.chunks[:3]
        for d in range(d0, d1):
            for tr in range(r0 // ch, -(-r1 // ch)):
                a0, a1 = max(r0, tr * ch), min(r1, (tr + 1) * ch)
                for tc in range(c0 // cw, -(-c1 // cw)):
                    b0, b1 = max(c0, tc * cw), min(c1, (tc + 1) * cw)
                    rows = self._rows(d, tr, tc, a0 - tr * ch, a1 - tr * ch)
                    out[d - d0, a0 - r0 : a1 - r0, b0 - c0 : b1 - c0] = \
                        rows[:, b0 - tc * cw : b1 - tc * cw]
        out = out[tuple(0 if ax in drop else slice(None) for ax in range(3))]
        if rest:
            out = out[(slice(None),) * (3 - len(drop)) + tuple(rest)]
        return out

    def _rows(self, depth: int, tile_row: int, tile_col: int, r0: int, r1: int) -> np.ndarray:
        """Rows ``r0:r1`` of a chunk. A chunk this process verified whole is read in part
        while its file is unchanged (same inode, size and modification time); any other read
        verifies the whole chunk first (:meth:`chunk`)."""
        key = (depth, tile_row, tile_col)
        seen = self._verified.get(key)
        if seen is None or (r1 - r0) * 4 > self.chunks[1] or \
                (self._last is not None and self._last[0] == key):
            return self.chunk(depth, tile_row, tile_col)[r0:r1]
        path = chunk_path(self.root, self.name, depth, tile_row, tile_col, self.ndim)
        try:
            fd = os.open(path, os.O_RDONLY)
        except FileNotFoundError:
            return self.chunk(depth, tile_row, tile_col)[r0:r1]
        try:
            st = os.fstat(fd)
            if (st.st_ino, st.st_size, st.st_mtime_ns) != seen:
                return self.chunk(depth, tile_row, tile_col)[r0:r1]
            n = (r1 - r0) * self._row_bytes
            buf = os.pread(fd, n, r0 * self._row_bytes)
        finally:
            os.close(fd)
        if len(buf) != n:
            return self.chunk(depth, tile_row, tile_col)[r0:r1]
        rows = np.frombuffer(buf, self._stored).reshape((r1 - r0,) + self.chunks[2:])
        return rows.astype(self.dtype, copy=False)

    def chunk(self, depth: int, tile_row: int, tile_col: int) -> np.ndarray:
        """Chunk (depth, tile_row, tile_col) as stored (ch, cw, ...), verified when its tile is
        done (a tile not done reads as stored, fill where no file)."""
        key = (depth, tile_row, tile_col)
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        path = chunk_path(self.root, self.name, depth, tile_row, tile_col, self.ndim)
        done = bool(self.done[key])
        record = int(self.records[key])
        where = (f"{self.root}: array '{self.name}', depth {depth}, tile ({tile_row}, "
                 f"{tile_col}) (camera rows {tile_row * self.chunks[1]}.., columns "
                 f"{tile_col * self.chunks[2]}..; {path.relative_to(self.root)})")
        if done and record == NO_CRC:
            raise LtcChunkError(f"{where}: the tile is recorded done but has no checksum; the "
                                "LTC store is damaged")
        try:
            with open(path, "rb") as f:
                buf = bytearray(self._nbytes)
                n = f.readinto(buf)
                extra = f.read(1)
                st = os.fstat(f.fileno())
        except FileNotFoundError:
            if done and record != ABSENT:
                raise LtcChunkError(f"{where}: chunk file is missing; the LTC store is damaged; "
                                    "reconstruct the tile again (`ltc reconstruct --force`)"
                                    ) from None
            chunk = np.full(self.chunks[1:], self.fill, self.dtype)
            self._last = (key, chunk)
            return chunk
        if done and self.verify:
            if record == ABSENT:
                raise LtcChunkError(f"{where}: a chunk file exists where none was written; "
                                    "the LTC store is damaged")
            if n != self._nbytes or extra:
                raise LtcChunkError(f"{where}: chunk file is truncated or resized "
                                    f"({os.path.getsize(path)} bytes, expected "
                                    f"{self._nbytes}); the LTC store is damaged")
            if crc32c(readonly(np.frombuffer(buf, np.uint8))) != record:
                raise LtcChunkError(f"{where}: chunk fails its crc32c (recorded in "
                                    f"'{CRC_ARRAY}'); the LTC store is damaged")
        elif n != self._nbytes or extra:
            raise LtcChunkError(f"{where}: chunk file has the wrong size")
        if done:
            self._verified[key] = (st.st_ino, st.st_size, st.st_mtime_ns)
        chunk = np.frombuffer(buf, self._stored).reshape(self.chunks[1:])
        chunk = chunk.astype(self.dtype, copy=False)
        self._last = (key, chunk)
        return chunk


def checked_arrays(path: Path, group: zarr.Group,
                   verify: bool = True) -> dict[str, CheckedArray]:
    """The checked view of every array of ``CHECKED_ARRAYS`` in an LTC store (``verify``
    False: the same reads without the checks, for measuring their cost only)."""
    records = np.asarray(group[CRC_ARRAY][...], np.int64)
    done = np.asarray(group["tile_done"][...], bool)
    return {name: CheckedArray(path, group[name], records[..., k], done, verify)
            for k, name in enumerate(CHECKED_ARRAYS) if name in group}


def damaged_chunks(path: Path, group: zarr.Group) -> list[str]:
    """Every chunk of a done tile that fails its check, one message each (reads the whole
    store; changes nothing)."""
    out = []
    for arr in checked_arrays(path, group).values():
        for d, tr, tc in np.argwhere(arr.done):
            try:
                arr.chunk(int(d), int(tr), int(tc))
            except LtcChunkError as exc:
                out.append(str(exc))
            arr._last = None
    return out
