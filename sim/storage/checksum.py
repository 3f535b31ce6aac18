"""Checksums of stored bytes: crc32c (hardware-accelerated, ``google_crc32c``) of chunks and
frames, and a SHA-256 digest for identities.

A crc32c is stored as a little-endian uint32 after a chunk, or as an int64 in a record array
where -1 means "none recorded".
"""

from __future__ import annotations

import hashlib

import google_crc32c
import numpy as np

NO_CRC = -1  # record value: no checksum recorded (not written yet)


def readonly(a: np.ndarray) -> np.ndarray:
    """A read-only view of ``a`` (what ``google_crc32c`` takes without a copy)."""
    v = a.view()
    v.flags.writeable = False
    return v


def crc32c(data: bytes | memoryview | np.ndarray) -> int:
    """crc32c of bytes or of a read-only C-contiguous array's memory (no copy)."""
    return google_crc32c.value(data)


def crc32c_extend(crc: int, data: bytes | memoryview | np.ndarray) -> int:
    """crc32c continued over more bytes."""
    return google_crc32c.extend(crc, data)


def array_crc32c(a: np.ndarray) -> int:
    """crc32c of an array's values, C order, little-endian (a copy only when ``a`` is not
    C-contiguous little-endian already)."""
    return crc32c(readonly(np.ascontiguousarray(a, a.dtype.newbyteorder("<"))))


def sha256_hex(*parts: bytes) -> str:
    """Hex SHA-256 of the concatenated ``parts``."""
    h = hashlib.sha256()
    for p in parts:
        h.update(p)
    return h.hexdigest()
