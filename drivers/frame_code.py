"""Camera-readable frame code: an integer drawn as black/white blocks on the display.

Two styles (:class:`FrameCodeLayout`):

* ``"strip"`` (default), self-clocking, for a camera that sees the code sharply. In blocks of
  ``block_px`` x ``block_px`` display pixels, one row, most significant bit first::

      white | black | data bits ... | even parity | black | white

  surrounded by a black quiet zone one block wide, so the drawn area is ``(bits + 7) * block_px``
  wide and ``3 * block_px`` high. The white end guards fix the code's extent (and so the block
  width) whatever the magnification; the black guards and the parity bit reject misreads.
  Read with :func:`decode_frame_code`.
* ``"blocks"``: the bare data bits, ``columns`` blocks per row, most significant bit first in
  row-major order, nothing else: as compact as a code can be, for a camera that sees it
  defocused or distorted. It is read by comparison with captures of every value made through
  the same lens from the same place (:func:`calibrate_code`, :func:`read_code`), so blur,
  crosstalk between blocks and vignetting do not matter; a few bits catch a repeated or
  skipped pattern.

The code sits in a display corner, or at ``origin`` (x, y of its top-left pixel) anywhere on
the display. Block values are 0 (black) and 255 (white) on screen, drawn after the inverse
response LUT. Pure numpy; the display drivers (or the caller, with :func:`stamp_frame_code`)
draw it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from drivers.errors import DeviceError, DeviceSettingError

Corner = Literal["top-left", "top-right", "bottom-left", "bottom-right"]
CORNERS: tuple[Corner, ...] = ("top-left", "top-right", "bottom-left", "bottom-right")
Style = Literal["strip", "blocks"]
STYLES: tuple[Style, ...] = ("strip", "blocks")
_GUARD_BLOCKS = 4  # white + black at the start, black + white at the end
_QUIET_BLOCKS = 1  # black margin around the strip, on every side


class FrameCodeError(DeviceError, ValueError):
    """A frame code could not be read from an image region."""


@dataclass(frozen=True)
class FrameCodeLayout:
    """Where and how large the frame code is drawn."""

    bits: int = 10  # data bits: codes 0 .. 2**bits - 1
    block_px: int = 16  # block edge, display pixels
    corner: Corner = "top-left"
    style: Style = "strip"
    columns: int = 0  # "blocks" style: blocks per row; 0 puts every bit in one row
    origin: tuple[int, int] | None = None  # (x, y) display pixels of the top-left; None: corner

    def __post_init__(self) -> None:
        if not 1 <= self.bits <= 32:
            raise DeviceSettingError(f"frame code bits must be 1..32, got {self.bits}")
        if self.block_px < 1:
            raise DeviceSettingError(f"frame code block_px must be >= 1, got {self.block_px}")
        if self.corner not in CORNERS:
            raise DeviceSettingError(f"frame code corner must be one of {CORNERS}, "
                                     f"got {self.corner!r}")
        if self.style not in STYLES:
            raise DeviceSettingError(f"frame code style must be one of {STYLES}, "
                                     f"got {self.style!r}")
        if self.columns < 0:
            raise DeviceSettingError(f"frame code columns must be >= 0, got {self.columns}")
        if self.origin is not None and (len(self.origin) != 2 or min(self.origin) < 0):
            raise DeviceSettingError(f"frame code origin must be (x, y) >= 0 display pixels, "
                             f"got {self.origin}")

    @property
    def n_blocks(self) -> int:
        """Blocks drawn: the strip's guards, data bits and parity (quiet zone not counted);
        the data bits alone for the "blocks" style."""
        return self.bits if self.style == "blocks" else self.bits + 1 + _GUARD_BLOCKS

    @property
    def grid(self) -> tuple[int, int]:
        """(rows, columns) of blocks, quiet zone included."""
        if self.style == "blocks":
            cols = min(self.columns or self.bits, self.bits)
            return -(-self.bits // cols), cols
        return 1 + 2 * _QUIET_BLOCKS, self.n_blocks + 2 * _QUIET_BLOCKS

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) in display pixels of the drawn code, quiet zone included."""
        rows, cols = self.grid
        return rows * self.block_px, cols * self.block_px


def code_blocks(value: int, bits: int) -> np.ndarray:
    """The strip as ``(bits + 5,)`` bool, True = white: guards, data MSB first, parity."""
    if not 0 <= value < 2**bits:
        raise DeviceSettingError(f"frame code {value} out of range 0..{2**bits - 1} for {bits} "
                                 "bits")
    data = [(value >> (bits - 1 - i)) & 1 for i in range(bits)]
    return np.array([1, 0, *data, sum(data) % 2, 0, 1], dtype=bool)


def render_frame_code(value: int, layout: FrameCodeLayout) -> np.ndarray:
    """The code as drawn: ``layout.shape`` uint8, 0 and 255, quiet zone included."""
    b, q = layout.block_px, _QUIET_BLOCKS
    rows, cols = layout.grid
    blocks = np.zeros((rows, cols), dtype=np.uint8)
    if layout.style == "blocks":
        if not 0 <= value < 2**layout.bits:
            raise DeviceSettingError(f"frame code {value} out of range 0..{2**layout.bits - 1} "
                             f"for {layout.bits} bits")
        bits = [(value >> (layout.bits - 1 - i)) & 1 for i in range(layout.bits)]
        blocks.ravel()[: layout.bits] = np.array(bits, dtype=np.uint8) * np.uint8(255)
    else:
        blocks[q, q:-q] = code_blocks(value, layout.bits) * np.uint8(255)
    return np.repeat(np.repeat(blocks, b, axis=0), b, axis=1)


def frame_code_rect(layout: FrameCodeLayout, display_size: tuple[int, int]) -> tuple[int, int, int, int]:
    """(x, y, width, height) of the code in display pixels, (x, y) its top-left; row 0 at the top."""
    width, height = display_size
    rows, cols = layout.shape
    if layout.origin is not None:
        x, y = (int(v) for v in layout.origin)
        if x + cols > width or y + rows > height:
            raise DeviceSettingError(
                f"frame code of {cols}x{rows} px at origin ({x}, {y}) reaches ({x + cols}, "
                f"{y + rows}), outside the {width}x{height} display"
            )
        return x, y, cols, rows
    if cols > width or rows > height:
        raise DeviceSettingError(
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


@dataclass(frozen=True)
class CodeCalibration:
    """How a "blocks" frame code looks to one camera from one place (:func:`calibrate_code`).

    pixels : (n,) int, flat indices of the camera pixels that read the code.
    templates : (values, n) float64, their expected response to each code value, ADU, with
        the rest of the display at mid level.
    separation : (values,) float64, RMS (over ``pixels``) distance from each template to its
        nearest other template, ADU.
    polluted : (rows, cols) bool, camera pixels whose view includes part of the code.
    """

    pixels: np.ndarray
    templates: np.ndarray
    separation: np.ndarray
    polluted: np.ndarray


def calibrate_code(
    code_images: np.ndarray,
    background: np.ndarray,
    background_value: int,
    *,
    leak_max: float = 0.2,
    pollution: float = 0.005,
    min_separation: float = 0.1,
) -> CodeCalibration:
    """Learn how each value of a "blocks" code looks through the camera.

    Parameters
    ----------
    code_images : (2**bits, rows, cols) camera frames of code value v (index) drawn on a black
        display.
    background : (rows, cols) camera frame of code ``background_value`` on a white display.
    leak_max : a pixel reads the code only if the rest of the display adds at most this
        fraction of the code's full response to it.
    pollution : a pixel is polluted when the code's full response exceeds this fraction of
        its response to the whole white display (floored at a tenth of the brightest pixels'
        response, so dark pixels are not flagged on noise).
    min_separation : every two values' templates must differ (RMS over the reading pixels) by
        at least this fraction of the median full response, or the code is not readable.

    Raises :class:`FrameCodeError` when the code cannot be read from here.
    """
    imgs = np.asarray(code_images, dtype=np.float64)
    if imgs.ndim != 3 or imgs.shape[0] < 2 or imgs.shape[0] & (imgs.shape[0] - 1):
        raise FrameCodeError(f"code_images must be (2**bits, rows, cols) with bits >= 1, "
                             f"got shape {imgs.shape}")
    bg = np.asarray(background, dtype=np.float64)
    if bg.shape != imgs.shape[1:]:
        raise FrameCodeError(f"background frame {bg.shape} differs from the code frames "
                             f"{imgs.shape[1:]}")
    if not 0 <= background_value < imgs.shape[0]:
        raise FrameCodeError(f"background_value {background_value} is not a code value "
                             f"0..{imgs.shape[0] - 1}")
    code = imgs[-1] - imgs[0]  # every block white minus every block black
    rest = bg - imgs[background_value]  # the rest of the display white minus black
    total = code + rest
    floor = 0.1 * np.percentile(total, 99)
    polluted = code > pollution * np.maximum(total, floor)
    peak = code.max()
    reading = (code >= 0.25 * peak) & (rest <= leak_max * code) if peak > 0 else code > 0
    pixels = np.flatnonzero(reading)
    if pixels.size == 0:
        raise FrameCodeError(
            f"no camera pixel sees the frame code clearly (largest code response {peak:.1f} "
            f"ADU): the code is outside the camera's view, or too small for the blur"
        )
    flat = imgs.reshape(imgs.shape[0], -1)
    templates = flat[:, pixels] + 0.5 * rest.ravel()[pixels]
    dist = _rms_distances(templates, templates)
    np.fill_diagonal(dist, np.inf)
    separation = dist.min(axis=1)
    scale = float(np.median(code.ravel()[pixels]))
    worst = int(np.argmin(separation))
    if separation[worst] < min_separation * scale:
        other = int(np.argmin(dist[worst]))
        raise FrameCodeError(
            f"frame code values {worst} and {other} look alike to the camera (RMS difference "
            f"{separation[worst]:.1f} ADU over {pixels.size} pixels, need >= "
            f"{min_separation * scale:.1f}): a block is out of view or blurred away, or the "
            f"display did not show every calibration value"
        )
    return CodeCalibration(pixels, templates, separation, polluted)


def _rms_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """RMS distances (len(a), len(b)) between rows of a (m, n) and b (k, n)."""
    return np.sqrt(np.mean((a[:, None, :] - b[None, :, :]) ** 2, axis=-1))


def read_code(image: np.ndarray, calibration: CodeCalibration, *, min_margin: float = 0.25) -> int:
    """The value of a "blocks" frame code in a camera frame (rows, cols).

    The nearest template wins if the frame lies within ``0.5 - min_margin`` of the way to the
    template nearest to it; a frame between two values (an exposure spanning two patterns) or
    unlike any (the code hidden or changed) raises :class:`FrameCodeError`.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.size != calibration.polluted.size:
        raise FrameCodeError(f"frame of shape {img.shape} does not match the calibration's "
                             f"{calibration.polluted.shape}")
    x = img.ravel()[calibration.pixels]
    dist = _rms_distances(x[None, :], calibration.templates)[0]
    best = int(np.argmin(dist))
    limit = (0.5 - min_margin) * calibration.separation[best]
    if dist[best] > limit:
        raise FrameCodeError(
            f"frame code unreadable: nearest value {best} is {dist[best]:.1f} ADU RMS away, "
            f"more than {limit:.1f} (a frame between two patterns, or the code not shown)"
        )
    return best
