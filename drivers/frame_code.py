"""Camera-readable frame code: an integer drawn as a row of black/white blocks in a display corner.

Layout, in blocks of ``block_px`` x ``block_px`` display pixels, one row, most significant bit first::

    white | black | data bits ... | even parity | black | white

surrounded by a black quiet zone one block wide, so the drawn area is ``(bits + 7) * block_px``
wide and ``3 * block_px`` high. The white end guards fix the code's extent (and so the block
width) whatever the magnification; the black guards and the parity bit reject misreads. Block
values are 0 (black) and 255 (white) on screen, drawn after the inverse response LUT.

Pure numpy; the display drivers draw it, a camera-side reader decodes it with
:func:`decode_frame_code`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

Corner = Literal["top-left", "top-right", "bottom-left", "bottom-right"]
CORNERS: tuple[Corner, ...] = ("top-left", "top-right", "bottom-left", "bottom-right")
_GUARD_BLOCKS = 4  # white + black at the start, black + white at the end
_QUIET_BLOCKS = 1  # black margin around the strip, on every side


class FrameCodeError(ValueError):
    """A frame code could not be read from an image region."""


@dataclass(frozen=True)
class FrameCodeLayout:
    """Where and how large the frame code is drawn."""

    bits: int = 10  # data bits: codes 0 .. 2**bits - 1
    block_px: int = 16  # block edge, display pixels
    corner: Corner = "top-left"

    def __post_init__(self) -> None:
        if not 1 <= self.bits <= 32:
            raise ValueError(f"frame code bits must be 1..32, got {self.bits}")
        if self.block_px < 1:
            raise ValueError(f"frame code block_px must be >= 1, got {self.block_px}")
        if self.corner not in CORNERS:
            raise ValueError(f"frame code corner must be one of {CORNERS}, got {self.corner!r}")

    @property
    def n_blocks(self) -> int:
        """Blocks in the strip: guards, data bits and parity (quiet zone not counted)."""
        return self.bits + 1 + _GUARD_BLOCKS

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) in display pixels of the drawn code, quiet zone included."""
        b = self.block_px
        return (1 + 2 * _QUIET_BLOCKS) * b, (self.n_blocks + 2 * _QUIET_BLOCKS) * b


def code_blocks(value: int, bits: int) -> np.ndarray:
    """The strip as ``(bits + 5,)`` bool, True = white: guards, data MSB first, parity."""
    if not 0 <= value < 2**bits:
        raise ValueError(f"frame code {value} out of range 0..{2**bits - 1} for {bits} bits")
    data = [(value >> (bits - 1 - i)) & 1 for i in range(bits)]
    return np.array([1, 0, *data, sum(data) % 2, 0, 1], dtype=bool)


def render_frame_code(value: int, layout: FrameCodeLayout) -> np.ndarray:
    """The code as drawn: ``layout.shape`` uint8, 0 and 255, quiet zone included."""
    b, q = layout.block_px, _QUIET_BLOCKS
    blocks = np.zeros((1 + 2 * q, layout.n_blocks + 2 * q), dtype=np.uint8)
    blocks[q, q:-q] = code_blocks(value, layout.bits) * np.uint8(255)
    return np.repeat(np.repeat(blocks, b, axis=0), b, axis=1)


def frame_code_rect(layout: FrameCodeLayout, display_size: tuple[int, int]) -> tuple[int, int, int, int]:
    """(x, y, width, height) of the code in display pixels, (x, y) its top-left; row 0 at the top."""
    width, height = display_size
    rows, cols = layout.shape
    if cols > width or rows > height:
        raise ValueError(
            f"frame code of {cols}x{rows} px ({layout.bits} bits, {layout.block_px} px blocks) "
            f"does not fit the {width}x{height} display"
        )
    x = 0 if layout.corner.endswith("left") else width - cols
    y = 0 if layout.corner.startswith("top") else height - rows
    return x, y, cols, rows


def stamp_frame_code(image: np.ndarray, value: int, layout: FrameCodeLayout) -> np.ndarray:
    """A copy of ``image`` ((rows, cols) or (rows, cols, 3) uint8) with the code drawn in its corner."""
    out = np.array(image, copy=True)
    x, y, w, h = frame_code_rect(layout, (out.shape[1], out.shape[0]))
    code = render_frame_code(value, layout)
    out[y : y + h, x : x + w] = code if out.ndim == 2 else code[:, :, None]
    return out


def _edge(profile: np.ndarray, inside: int, outside: int, threshold: float) -> float:
    """Sub-pixel position where ``profile`` crosses ``threshold`` between two neighbouring pixels."""
    a, b = profile[outside], profile[inside]
    return outside + (threshold - a) / (b - a) * (inside - outside)


def decode_frame_code(region: np.ndarray, bits: int = 10, *, min_margin: float = 0.25) -> int:
    """Read a frame code from a camera image region.

    Parameters
    ----------
    region : (rows, cols) or (rows, cols, channels) array, any real dtype
        The code's area in a captured image, upright (strip horizontal, start guard on the
        left), with some of its black quiet zone around it and nothing else bright.
    bits : int
        Data bits of the code (as in :class:`FrameCodeLayout`).
    min_margin : float
        Every block's level, as a fraction of the black-to-white range, must be at least this far
        from the midpoint; a blend of two codes (an exposure spanning two frames) fails here.

    Returns
    -------
    int
        The decoded value. Raises :class:`FrameCodeError` when the code cannot be read reliably.
    """
    img = np.asarray(region, dtype=np.float64)
    if img.ndim == 3:
        img = img.mean(axis=2)
    if img.ndim != 2:
        raise FrameCodeError(f"region must be a 2-D image, got shape {np.shape(region)}")
    lo, hi = np.percentile(img, [1.0, 99.0])
    if hi - lo <= 0:
        raise FrameCodeError(f"no contrast in the region (level {lo:g} everywhere)")
    threshold = 0.5 * (lo + hi)
    bright_per_row = (img > threshold).sum(axis=1)
    band = np.flatnonzero(bright_per_row >= 0.5 * bright_per_row.max())
    quarter = len(band) // 4
    band = band[quarter : len(band) - quarter]
    profile = img[band].mean(axis=0)
    bright = np.flatnonzero(profile > threshold)
    if bright.size == 0:
        raise FrameCodeError("no bright blocks along the strip: not a frame code")
    first, last = bright[0], bright[-1]
    if first == 0 or last == len(profile) - 1:
        raise FrameCodeError("frame code touches the region's edge: include its black quiet zone")
    left = _edge(profile, first, first - 1, threshold)
    right = _edge(profile, last, last + 1, threshold)
    n_blocks = bits + 1 + _GUARD_BLOCKS
    block = (right - left) / n_blocks
    if block < 2.0:
        raise FrameCodeError(f"frame code blocks are {block:.2f} px wide in the region; need >= 2 px")
    centres = left + (np.arange(n_blocks) + 0.5) * block
    half = max(block / 4.0, 0.5)
    levels = np.array(
        [profile[int(np.ceil(c - half)) : int(np.floor(c + half)) + 1].mean() for c in centres]
    )
    levels = (levels - lo) / (hi - lo)
    unsure = np.flatnonzero(np.abs(levels - 0.5) < min_margin)
    if unsure.size:
        raise FrameCodeError(
            f"frame code blocks {unsure.tolist()} are neither black nor white "
            f"(levels {np.round(levels[unsure], 2).tolist()}): blurred, or two frames mixed"
        )
    blocks = levels > 0.5
    if blocks[1] or blocks[-2]:
        raise FrameCodeError("frame code guard blocks not found: wrong bits, or not a frame code")
    data = blocks[2 : 2 + bits]
    if int(data.sum()) % 2 != int(blocks[2 + bits]):
        raise FrameCodeError("frame code parity check failed")
    return int(sum(int(bit) << (bits - 1 - i) for i, bit in enumerate(data)))
