"""Grey-scale centroids and second moments of every pixel's LTC at every depth (docs/optics.md section 6).

A pixel's LTC window is searched for its peak (after a 3 x 3 box smoothing); the region is
the connected set of smoothed weights above a noise threshold that holds the peak, grown by
REGION_MARGIN_PX. Over that region

    x_g = sum x h / sum h,   var(x_g) = sigma_h^2 sum (x - x_g)^2 / (sum h)^2

and the central second moments ``m_xx, m_yy, m_xy``; the aperture samples are drawn from the
same weights (``station.lens.derive``). The region must hold the LTC's tails: a centroid over
a tighter region (the smoothed core alone) has half the noise on the fake bench (p95 0.059 vs
0.118 px at 40 mm, P = 16, default noise) but is biased towards the peak of an asymmetric LTC:
the reduced experiment's measured-LTC scanner then had a mean distance of -190 um to the real
one at large defocus and failed its ordering test (tests/station/experiment). With the margin
the errors are the noise ``var(x_g)`` predicts and nothing more (tests/station/ltc/test_spi.py;
``sigma_h`` is the store's per-weight noise estimate). Not the whole P x P window: the noise of
a centroid grows with the area summed over (docs/optics.md section 5). Station-frame points are
``(x_g * pitch, y_g * pitch, z)`` mm with ``z`` the stage reading of the depth
(``fakes/bench.py`` documents the frame: the LCD plane lies at ``z = stage reading``).

The LTC store writes NaN windows for pixels without signal; such a pixel is "no signal" at
that depth. A window mixing NaN and finite weights, or one whose weights sum to <= 0, is a
broken store and raises. This is the project's one LTC centroid: the reconstruction
(``station/ltc/spi.py``) and its tests grade their LTCs with ``window_stats`` too.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm import tqdm

from station.lens.kernels import stats_kernel
from station.ltc.store import LtcVolume, LtcVolumeError

if TYPE_CHECKING:
    from station.compute import Engine

STATUS_OK = 0
STATUS_NO_SIGNAL = 1  # NaN window, or no weight above the noise threshold
STATUS_TRUNCATED = 2  # the region reaches the window border: LTC folded or cut off
NOISE_SIGMAS = 3.0  # region threshold on the 3x3-smoothed weights, in their noise stds
PEAK_FRACTION = 0.02  # ...and at least this fraction of the smoothed peak
REGION_MARGIN_PX = 2  # the region (moments, aperture) is the core grown by this, LCD px
WINDOWS_PER_BATCH = 4096  # windows analysed at once (temporaries ~ 10 x this x P^2 x 8 B)


@dataclass(frozen=True)
class WindowStats:
    """Per window (n of them): centroid and moments in window pixel coordinates.

    centroid : (n, 2) (col, row) = (x, y); centroid_std : (n, 2) its std.
    moments : (n, 3) central second moments m_xx, m_yy, m_xy, px^2; trace_std : (n,) std of
    m_xx + m_yy. region : (n, P, P) bool; status : (n,) STATUS_*.
    """

    centroid: np.ndarray
    centroid_std: np.ndarray
    moments: np.ndarray
    trace_std: np.ndarray
    region: np.ndarray
    status: np.ndarray


def _check_windows(h: np.ndarray, sigma: np.ndarray, where: np.ndarray | None, name: str) -> None:
    finite = np.isfinite(h).reshape(len(h), -1)
    mixed = finite.any(axis=1) & ~finite.all(axis=1)
    full = finite.all(axis=1)
    sums = np.where(full, np.nansum(h.reshape(len(h), -1), axis=1), 1.0)
    for bad, what in ((mixed, ("mixes NaN and finite weights; expected all finite or all NaN "
                               "(no signal)")),
                      (sums <= 0, ("has finite weights summing to <= 0; expected an LTC "
                                   "normalised to sum 1 (or NaN for no signal)")),
                      (full & ~(np.isfinite(sigma) & (sigma >= 0)),
                       "has a finite LTC but its noise estimate is NaN or negative")):
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            loc = f"[{', '.join(str(int(v)) for v in where[i])}]" if where is not None else f"[{i}]"
            raise LtcVolumeError(f"{name}: ltc{loc} {what} ({int(bad.sum())} window(s))")


def window_stats(
    h: np.ndarray, sigma: np.ndarray, *, where: np.ndarray | None = None,
    name: str = "window_stats"
) -> WindowStats:
    """Centroid, its std and second moments of n LTC windows ``h`` (n, P, P) with per-weight
    noise std ``sigma`` (n,). ``where`` (n, k) int labels windows in error messages."""
    h = np.asarray(h, dtype=np.float64)
    sigma = np.asarray(sigma, dtype=np.float64).ravel()
    n, p = h.shape[0], h.shape[1]
    _check_windows(h, sigma, where, name)
    signal = np.isfinite(h).reshape(n, -1).all(axis=1)
    hz = np.where(signal[:, None, None], h, 0.0)
    cen, std = np.empty((n, 2)), np.empty((n, 2))
    mom, tr_std = np.empty((n, 3)), np.empty(n)
    region, status = np.empty((n, p, p), dtype=bool), np.empty(n, dtype=np.int8)
    stats_kernel(hz, sigma, signal, NOISE_SIGMAS, PEAK_FRACTION, REGION_MARGIN_PX,
                 cen, std, mom, tr_std, region, status)
    return WindowStats(centroid=cen, centroid_std=std, moments=mom, trace_std=tr_std,
                       region=region, status=status)


def region_stats(h: np.ndarray, use: np.ndarray, sigma: np.ndarray) -> WindowStats:
    """``window_stats`` of windows already checked (the centroid pass checked every one):
    h (n, P, P) float64 C-contiguous, finite where ``use`` (n,), zero elsewhere (no signal);
    no NaN copy of the windows, no checks (the aperture pass: the same regions and
    centroids). ``h`` is set to 0 outside each window's region, in place."""
    if h.dtype != np.float64 or not h.flags.c_contiguous:
        raise ValueError("region_stats: h must be a C-contiguous float64 array (set in place)")
    sigma = np.ascontiguousarray(sigma, dtype=np.float64).ravel()
    n, p = h.shape[0], h.shape[1]
    cen, std = np.empty((n, 2)), np.empty((n, 2))
    mom, tr_std = np.empty((n, 3)), np.empty(n)
    region, status = np.empty((n, p, p), dtype=bool), np.empty(n, dtype=np.int8)
    stats_kernel(h, sigma, np.ascontiguousarray(use, dtype=bool), NOISE_SIGMAS, PEAK_FRACTION,
                 REGION_MARGIN_PX, cen, std, mom, tr_std, region, status, True)
    return WindowStats(centroid=cen, centroid_std=std, moments=mom, trace_std=tr_std,
                       region=region, status=status)


@dataclass(frozen=True)
class Centroids:
    """Centroids of every pixel at every depth.

    xy_lcd_px : (D, H, W, 2) float64 LCD (x, y) pixels; std_lcd_px : (D, H, W, 2) float32
    (both None in a ``LensGeometry``: only the principal-ray fit reads them, from the
    float64 ones as each block arrives).
    moments_px2 : (D, H, W, 3) float32 m_xx, m_yy, m_xy in LCD px^2; trace_std_px2 :
    (D, H, W) float32 (float32: relative precision 6e-8, far below their noise; half the
    memory of a full-size sensor's six depths; None in a ``LensGeometry``: only its focus
    fits read it).
    status : (D, H, W) int8 STATUS_*; valid : status == STATUS_OK.
    depths_mm : (D,); pitch_mm.
    """

    xy_lcd_px: np.ndarray | None
    std_lcd_px: np.ndarray | None
    moments_px2: np.ndarray
    trace_std_px2: np.ndarray | None
    status: np.ndarray
    depths_mm: np.ndarray
    pitch_mm: float

    @property
    def valid(self) -> np.ndarray:
        return self.status == STATUS_OK

    def points_mm(self) -> np.ndarray:
        """Station-frame points (D, H, W, 3): ``(x_g pitch, y_g pitch, z)`` mm (NaN if invalid)."""
        xy = self._held(self.xy_lcd_px)
        d = xy.shape[0]
        z = np.broadcast_to(self.depths_mm.reshape(d, 1, 1, 1), xy.shape[:3] + (1,))
        return np.concatenate([xy * self.pitch_mm, z], axis=-1)

    def std_mm(self) -> np.ndarray:
        """Centroid std (D, H, W, 2) in mm."""
        return np.asarray(self._held(self.std_lcd_px) * self.pitch_mm)

    @staticmethod
    def _held(a: np.ndarray | None) -> np.ndarray:
        if a is None:
            raise ValueError("Centroids: the per-depth centroids are not held (a "
                             "LensGeometry's centroids keep only moments and status)")
        return a


def compute_centroids(volume: LtcVolume, rows_per_tile: int | None = None,
                      progress: bool = False, engine: Engine | None = None) -> Centroids:
    """Centroids of all pixels at all depths, one depth of one stored chunk of camera rows
    and columns (default: the store's chunk; ``rows_per_tile`` overrides the rows) per
    task, ``WINDOWS_PER_BATCH`` windows at once, so memory does not grow with the sensor
    and each stored chunk is decoded once. engine : where the tasks run
    (``station.compute.Engine``; default: in this process), bit-identical results
    whatever the engine. ``progress``: a bar over the tasks. (The lens derivation runs
    this pass with its ray fit: ``station.lens.geometry.centroids_and_rays``.)"""

    d = len(volume.depths_mm)
    w, h = volume.camera_size
    chunks = getattr(volume.ltc, "chunks", None)
    rows = rows_per_tile or volume.chunk_rows
    cols = int(chunks[2]) if chunks else w
    f4 = np.float32  # uncertainties and moments: 7 digits are plenty, half the memory
    out = {"xy": np.full((d, h, w, 2), np.nan), "std": np.full((d, h, w, 2), np.nan, f4),
           "mom": np.full((d, h, w, 3), np.nan, f4), "tstd": np.full((d, h, w), np.nan, f4),
           "status": np.full((d, h, w), STATUS_NO_SIGNAL, dtype=np.int8)}
    tasks = [((i, r0, min(h, r0 + rows), c0, min(w, c0 + cols)))
             for r0 in range(0, h, rows) for c0 in range(0, w, cols) for i in range(d)]
    bar = tqdm(total=len(tasks), desc="lens: centroids", unit="block",
               disable=None if progress else True)

    def on_result(key: tuple[int, int, int, int, int], part: dict[str, np.ndarray]) -> None:
        i, r0, r1, c0, c1 = key
        for name, value in part.items():
            out[name][i, r0:r1, c0:c1] = value
        bar.update()

    run_centroid_blocks(volume, tasks, on_result, engine, bar)
    return Centroids(out["xy"], out["std"], out["mom"], out["tstd"], out["status"],
                     volume.depths_mm.copy(), float(volume.pitch_mm))


def run_centroid_blocks(volume: LtcVolume, tasks: list[tuple[int, int, int, int, int]],
                        on_result: Callable[[Any, Any], None], engine: Engine | None,
                        bar: tqdm) -> None:
    """Compute ``centroid_rows`` of every (depth, r0, r1, c0, c1) in ``tasks`` on ``engine``
    (default: in this process), calling ``on_result(task, part)`` as each finishes; closes
    the progress ``bar`` and any engine it started."""
    from station.compute import Engine, run_ordered

    own = engine is None
    engine = engine or Engine(1)
    try:
        run_ordered(engine, ((t, centroid_rows, (volume,) + t) for t in tasks), on_result)
    finally:
        bar.close()
        if own:
            engine.close()


def centroid_rows(volume: LtcVolume, depth: int, r0: int, r1: int, c0: int = 0,
                  c1: int | None = None) -> dict[str, np.ndarray]:
    """Centroid statistics of camera rows ``r0:r1`` (columns ``c0:c1``, default all) at one
    depth: ``xy`` (rows, cols, 2) LCD px, ``std`` (rows, cols, 2), ``mom`` (rows, cols, 3),
    ``tstd`` (rows, cols), ``status`` (rows, cols) int8. A pure function of the store: every
    engine computes blocks with it."""
    c1 = volume.camera_size[0] if c1 is None else c1
    w = c1 - c0
    ltc = np.asarray(volume.ltc[depth, r0:r1, c0:c1])
    origin = np.asarray(volume.origin[depth, r0:r1, c0:c1], dtype=np.int64)
    noise = np.asarray(volume.noise[depth, r0:r1, c0:c1], dtype=np.float64).ravel()
    p = ltc.shape[-1]
    flat = ltc.reshape(-1, p, p)
    parts = []
    for k in range(0, len(flat), WINDOWS_PER_BATCH):
        j = np.arange(k, min(k + WINDOWS_PER_BATCH, len(flat)))
        where = np.stack([np.full(len(j), depth), r0 + j // w, c0 + j % w], axis=1)
        parts.append(window_stats(flat[j].astype(np.float64), noise[j], where=where,
                                  name=volume.name))
    shp = (r1 - r0, w)
    return {
        "xy": np.concatenate([q.centroid for q in parts]).reshape(shp + (2,)) + origin,
        "std": np.concatenate([q.centroid_std for q in parts]).reshape(shp + (2,)),
        "mom": np.concatenate([q.moments for q in parts]).reshape(shp + (3,)),
        "tstd": np.concatenate([q.trace_std for q in parts]).reshape(shp),
        "status": np.concatenate([q.status for q in parts]).reshape(shp),
    }
