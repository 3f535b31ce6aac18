"""The bytes of a run store's frames: one frame is one zarr v3 shard of ``tile_px`` x ``tile_px``
inner chunks, uncompressed (``bytes`` little-endian), each followed by its crc32c, then the
shard index and its crc32c (``sharding_indexed`` with inner codecs ``[bytes, crc32c]``).
:class:`ShardCodec` encodes a frame in one pass and decodes chunks, checking each crc32c.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import google_crc32c
import numpy as np

from sim.storage.checksum import crc32c, readonly

CRC_BYTES = 4  # a crc32c, little-endian uint32, after each inner chunk and after the index


def frame_crc(image: np.ndarray) -> int:
    """crc32c of a frame's pixels, (rows, cols) in C order, little-endian; computed on the
    frame's own memory when it is C-contiguous and little-endian (else on a copy)."""
    return crc32c(readonly(np.ascontiguousarray(image, image.dtype.newbyteorder("<"))))


def _pixel_stats(image: np.ndarray, full: int) -> tuple[int, int]:
    """(pixels >= ``full``, largest pixel value) of an image: one pass (numpy's vectorised
    max) unless the image reaches ``full``; only then are the saturated pixels counted."""
    top = int(image.max()) if image.size else 0
    return (int(np.count_nonzero(image >= full)) if top >= full else 0), top


@dataclass(frozen=True)
class FrameShard:
    """What :meth:`ShardCodec.encode` makes of a frame: ``chunks`` (the shard without its
    index, uint8, a reused buffer), the frame's ``crc32c`` (:func:`frame_crc`), the count of
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
        self.chunk_bytes = self.data_bytes + CRC_BYTES
        n = self.nr * self.nc
        offsets = np.arange(n, dtype="<u8") * self.chunk_bytes
        index = np.stack([offsets, np.full(n, self.chunk_bytes, "<u8")], axis=1).tobytes()
        self.index = index + np.uint32(crc32c(index)).astype("<u4").tobytes()
        self.size = n * self.chunk_bytes + len(self.index)
        self._buf: np.ndarray | None = None

    def _allocate(self) -> np.ndarray:
        """The shard buffer (allocated once, so no page faults per frame; returned), its
        pixels seen as (chunk rows, chunk cols, tile, tile), read-only views of each chunk's
        pixel bytes for the crc32c, and a zeroed strip for chunk rows with edge padding."""
        t, n = self.t, self.nr * self.nc
        self._buf = np.zeros((self.nr, self.nc, self.chunk_bytes), np.uint8)
        self._pix = self._buf[:, :, : self.data_bytes].view(self.dtype).reshape(
            self.nr, self.nc, t, t)
        flat = readonly(self._buf).reshape(n, self.chunk_bytes)
        self._chunk_views = [flat[i, : self.data_bytes] for i in range(n)]
        self._crcs = self._buf.reshape(n, self.chunk_bytes)[:, self.data_bytes :].view("<u4")
        self._strip = np.zeros((t, self.nc * t), self.dtype)
        return self._buf

    def encode(self, image: np.ndarray, full: int) -> FrameShard:
        """One frame's shard chunks and what the store records of the frame, in one pass over
        its pixels, chunk row by chunk row (each block of ``tile`` camera rows is read while it
        is in the CPU cache): the frame's crc32c continued over the block, the saturation count
        and maximum, one copy into shard order (edge chunk rows through a zero-padded strip),
        then each chunk's crc32c on the buffer in place. The buffer is reused: valid until the
        next call, one thread at once."""
        buf = self._allocate() if self._buf is None else self._buf
        t, nc, w = self.t, self.nc, self.w
        img = readonly(np.ascontiguousarray(image, self.dtype))  # no copy for camera frames
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
        return FrameShard(buf.reshape(-1), crc, saturated, top)

    def decode_chunks(self, raw: bytes, n_chunks: int) -> tuple[np.ndarray, int]:
        """(chunks (n, t, t), index of the first chunk failing its crc32c or -1)."""
        for i in range(n_chunks):
            o = i * self.chunk_bytes
            stored = int.from_bytes(raw[o + self.data_bytes : o + self.chunk_bytes], "little")
            if crc32c(raw[o : o + self.data_bytes]) != stored:
                return np.empty(0), i
        arr = np.frombuffer(raw, np.uint8, n_chunks * self.chunk_bytes).reshape(n_chunks, -1)
        pix = arr[:, : self.data_bytes].view(self.dtype).reshape(n_chunks, self.t, self.t)
        return pix, -1
