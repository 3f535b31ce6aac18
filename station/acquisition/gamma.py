"""Display response (``ltc gamma``): show uniform grey levels, capture them, fit the display's
response and write the inverse lookup table that makes it linear (docs/optics.md section 5).

Relative response of drive level g: ``y(g) = (R(g) - R(0)) / (R(255) - R(0))`` with R a camera
pixel's reading (so the camera's black level and each pixel's gain cancel), pooled over the
pixels that see the display well as a ratio of sums. The fit is monotone: isotonic regression
of the measured points, then a shape-preserving cubic (PCHIP) through them. The LUT entry i is
the drive level whose response is ``i / 255``, rounded (not truncated) to an integer; it is
what ``PatternDisplay.set_lut`` and ``station.acquisition.patterns.apply_lut`` take.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.interpolate import PchipInterpolator

from drivers.errors import CameraError, CameraTimeout
from sim.storage.durable import durable_file
from station.acquisition.backend import Hardware, open_hardware
from station.acquisition.config import StationConfig
from station.errors import StationError, StationInputError

MIN_LEVELS = 64
MIN_CONTRAST_FRACTION = 0.5  # pixels used: white-black contrast >= this fraction of the best
MAX_DEVIATION = 0.05  # ...and a curve within this of the median curve (not seeing a code)


class GammaError(StationError):
    """The display response could not be measured; the message says why."""


def grey_levels(n: int = 65) -> np.ndarray:
    """``n`` (>= 64) drive levels spread evenly over 0..255, both ends included, (n,) int."""
    if n < MIN_LEVELS or n > 256:
        raise StationInputError(f"levels must be {MIN_LEVELS}..256 grey levels, got {n}")
    return np.unique(np.rint(np.linspace(0, 255, n)).astype(np.int64))


def relative_response(frames: np.ndarray, levels: np.ndarray) -> tuple[np.ndarray, int]:
    """Pooled relative response (n,) of the levels (n,) from frames (n, rows, cols) ADU.

    ``levels`` must include 0 and 255. Returns the response (0 at level 0, 1 at 255) and the
    number of pixels pooled (those with good contrast whose curve follows the median curve).
    """
    lv = np.asarray(levels)
    f = np.asarray(frames, dtype=np.float64).reshape(len(lv), -1)
    if 0 not in lv or 255 not in lv:
        raise GammaError(f"levels must include 0 and 255, got {lv.min()}..{lv.max()}")
    black, white = f[np.flatnonzero(lv == 0)[0]], f[np.flatnonzero(lv == 255)[0]]
    contrast = white - black
    best = np.percentile(contrast, 99)
    if not best > 0:
        raise GammaError("the camera sees no difference between black and white: check the "
                         "display, the exposure and that the camera looks at the LCD")
    use = contrast >= MIN_CONTRAST_FRACTION * best
    curves = (f[:, use] - black[use]) / contrast[use]
    median = np.median(curves, axis=1, keepdims=True)
    follow = np.abs(curves - median).max(axis=0) <= MAX_DEVIATION
    if follow.sum() < 10:
        raise GammaError(f"only {int(follow.sum())} pixels give a consistent response; "
                         "the display or the camera is unstable")
    idx = np.flatnonzero(use)[follow]
    y = (f[:, idx] - black[idx]).sum(axis=1) / contrast[idx].sum()
    return y, int(idx.size)


def isotonic(y: np.ndarray) -> np.ndarray:
    """Least-squares non-decreasing fit to y (n,) (pool adjacent violators)."""
    blocks: list[list[float]] = []  # [mean, count]
    for v in np.asarray(y, dtype=np.float64):
        blocks.append([v, 1.0])
        while len(blocks) > 1 and blocks[-2][0] > blocks[-1][0]:
            m2, n2 = blocks.pop()
            m1, n1 = blocks.pop()
            blocks.append([(m1 * n1 + m2 * n2) / (n1 + n2), n1 + n2])
    return np.concatenate([np.full(int(n), m) for m, n in blocks])


def fit_inverse_lut(levels: np.ndarray, response: np.ndarray) -> np.ndarray:
    """Inverse LUT (256,) uint8 from a measured response (n,) at drive levels (n,): entry i is
    the drive level of relative response ``i / 255``, rounded to the nearest integer."""
    lv = np.asarray(levels, dtype=np.float64)
    y = isotonic(np.clip(response, 0.0, 1.0))
    curve = PchipInterpolator(lv, y)
    g = np.linspace(0.0, 255.0, 255 * 16 + 1)
    yg = np.maximum.accumulate(curve(g))
    yg = yg + g * 1e-12  # strictly increasing for the interpolation below
    drive = np.interp(np.arange(256) / 255.0, yg, g)
    return np.clip(np.rint(drive), 0, 255).astype(np.uint8)


def save_lut(path: str | Path, lut: np.ndarray) -> Path:
    """Write a LUT as ``.npy`` or, for any other suffix, as text (one value per line); both are
    what ``station.acquisition.backend.load_lut`` (``display.lut_path``) reads."""
    path = Path(path)
    lut = np.asarray(lut, dtype=np.uint8)
    with durable_file(path, "wb") as f:
        if path.suffix == ".npy":
            np.save(f, lut, allow_pickle=False)
        else:
            np.savetxt(f, lut, fmt="%d")
    return path


def capture_levels(hw: Hardware, levels: np.ndarray, config: StationConfig) -> np.ndarray:
    """Show each level full screen (display LUT as set) and capture it: (n, rows, cols)."""
    w, h = hw.display.size
    frames = []
    for g in levels:
        shown = hw.show_settled(np.full((h, w), int(g), np.uint8), config.display.settled_s)
        frames.append(capture_after(hw, shown.swap_time, config))
    return np.stack(frames)


def capture_after(hw: Hardware, after: float, config: StationConfig) -> np.ndarray:
    """A camera frame taken after ``after`` (time.monotonic), timeouts and stale frames retried."""
    why = ""
    for _ in range(config.acquire.max_retries + 1):
        try:
            frame = hw.camera.capture(config.camera.timeout_s)
        except (CameraTimeout, CameraError) as exc:
            why = str(exc)
            continue
        if frame.timestamp >= after:
            return frame.image
        why = f"stale frame {frame.frame_id}"
    raise GammaError(f"no fresh camera frame in {config.acquire.max_retries + 1} attempts: {why}")


def measure_lut(config: StationConfig, *, n_levels: int = 65, hw: Hardware | None = None) -> dict:
    """Measure the display response with the display's LUT set to identity; return a summary
    with ``lut`` (256 ints), ``levels``, ``response`` and the pixels pooled. Nothing moves."""
    levels = grey_levels(n_levels)
    if hw is None:
        with open_hardware(config) as opened:
            return measure_lut(config, n_levels=n_levels, hw=opened)
    hw.display.set_lut(None)
    frames = capture_levels(hw, levels, config)
    response, pixels = relative_response(frames, levels)
    lut = fit_inverse_lut(levels, response)
    # effective gamma: least squares of log y on log g over the middle of the range
    mid = (levels > 25) & (levels < 250) & (response > 0)
    gamma = float(np.polyfit(np.log(levels[mid] / 255.0), np.log(response[mid]), 1)[0])
    return {"levels": levels.tolist(), "response": [round(float(v), 6) for v in response],
            "pixels": pixels, "gamma_fit": round(gamma, 4), "lut": lut.tolist()}
