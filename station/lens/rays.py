"""Principal rays (docs/optics.md section 6), vectorised over pixels; their intersection, the optical
centre, is ``station.lens.centre``.

A pixel's principal ray is the line through its LTC centroids at the depths:
``x(z) = c_x + s_x (z - z_ref)``, ``y(z) = c_y + s_y (z - z_ref)`` (station frame, mm). The
depths are exact (stage readings) and the centroids noisy, so the fit is a weighted linear
regression of x and y on z, weights ``1 / (sigma_centroid^2 + floor^2)``; residuals are the
lateral misfits at each depth. Points whose normalised residual exceeds ``outlier_sigma`` are
dropped one at a time (at most ``max_outliers``), refitting each time.

Flags (bitmask per pixel; a flagged pixel is never used silently):

* ``FLAG_FEW_DEPTHS``: fewer than ``min_depths`` depths with signal; no ray.
* ``FLAG_OUTLIER``: outlier depth(s) removed; the ray uses the rest and stays usable.
* ``FLAG_BAD_FIT``: outliers remain after ``max_outliers`` removals; not used.

"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from station.errors import StationError

FLAG_FEW_DEPTHS = 1
FLAG_OUTLIER = 2
FLAG_BAD_FIT = 4
UNUSABLE = FLAG_FEW_DEPTHS | FLAG_BAD_FIT


class RayFitError(StationError, ValueError):
    """Not enough usable principal rays; the message says how many and why."""


@dataclass(frozen=True)
class PrincipalRays:
    """Per-pixel lines, N pixels, D depths.

    z_ref : (N,) weighted mean depth, mm; xy_ref : (N, 2) line position there, mm;
    slope : (N, 2) dx/dz, dy/dz; var_ref, var_slope : (N,) per-axis variances of those from
    the a-priori weights. residual : (D, N, 2) float32 measured minus fitted, mm (NaN where no
    point; float32: far below the centroid noise), or None in a ``LensGeometry`` (the
    geometry keeps only the lengths: a third of the memory with ``used``);
    used : (D, N) points in the fit; flags : (N,); residual_mm : (D, N) float32 lengths of
    ``residual`` (NaN where the point is not used).
    """

    z_ref: np.ndarray
    xy_ref: np.ndarray
    slope: np.ndarray
    var_ref: np.ndarray
    var_slope: np.ndarray
    residual: np.ndarray | None
    used: np.ndarray
    flags: np.ndarray
    residual_mm: np.ndarray

    @classmethod
    def empty(cls, d: int, n: int) -> PrincipalRays:
        """Rays of n pixels and d depths, to be filled block by block (``put``); without the
        residual vectors (``residual`` None: their lengths only)."""
        return cls(np.empty(n), np.empty((n, 2)), np.empty((n, 2)), np.empty(n), np.empty(n),
                   None, np.empty((d, n), bool), np.empty(n, np.int8),
                   np.empty((d, n), np.float32))

    def put(self, sl: slice | np.ndarray, part: PrincipalRays) -> None:
        """Copy the rays of pixels ``sl`` (a slice or flat indices) from ``part`` (pixel
        axis: 0 of the per-pixel arrays, 1 of the (D, N, ...) ones)."""
        for f in fields(self):
            dst = getattr(self, f.name)
            if dst is None:
                continue
            if f.name in ("residual", "used", "residual_mm"):
                dst[:, sl] = getattr(part, f.name)
            else:
                dst[sl] = getattr(part, f.name)

    @property
    def usable(self) -> np.ndarray:
        """(N,) rays fit for use (not FEW_DEPTHS, not BAD_FIT)."""
        return (self.flags & UNUSABLE) == 0

    def xy_at(self, z_mm: float | np.ndarray) -> np.ndarray:
        """Ray positions (N, 2) mm on the plane(s) ``z = z_mm`` (scalar or (N,))."""
        dz = np.asarray(z_mm, dtype=np.float64) - self.z_ref
        return self.xy_ref + self.slope * np.asarray(dz)[..., None]

    def var_at(self, z_mm: float | np.ndarray) -> np.ndarray:
        """Per-axis variance (N,) of ``xy_at(z_mm)``, mm^2."""
        dz = np.asarray(z_mm, dtype=np.float64) - self.z_ref
        return self.var_ref + dz**2 * self.var_slope

    def directions(self) -> np.ndarray:
        """Unit direction vectors (N, 3), z > 0."""
        d = np.concatenate([self.slope, np.ones((len(self.slope), 1))], axis=1)
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def residual_norm(self) -> np.ndarray:
        """Lateral residual length (D, N), mm, NaN where the point is not used."""
        return np.where(self.used, self.residual_mm, np.nan)


def _line_fit(z: np.ndarray, xy: np.ndarray, w: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Weighted regression of xy (D, N, 2) on z (D, 1) with weights w (D, N), 0 = unused."""
    sw = w.sum(axis=0)
    safe = np.where(sw > 0, sw, 1.0)
    z_ref = (w * z).sum(axis=0) / safe
    dz = z - z_ref
    szz = (w * dz * dz).sum(axis=0)
    xyw = np.where(w[..., None] > 0, xy, 0.0)
    c = (w[..., None] * xyw).sum(axis=0) / safe[:, None]
    szz_safe = np.where(szz > 0, szz, 1.0)
    s = (w[..., None] * dz[..., None] * (xyw - c)).sum(axis=0) / szz_safe[:, None]
    return z_ref, c, s, 1.0 / safe, 1.0 / szz_safe


def fit_principal_rays(
    points_mm: np.ndarray,
    std_mm: np.ndarray,
    valid: np.ndarray,
    *,
    min_depths: int = 3,
    outlier_sigma: float = 6.0,
    max_outliers: int = 1,
    floor_mm: float = 0.005,
) -> PrincipalRays:
    """Fit a principal ray per pixel.

    points_mm : (D, N, 3) centroids ``(x, y, z)``; std_mm : (D, N, 2) or (D, N) their std;
    valid : (D, N) bool, depth has signal. floor_mm : std added in quadrature (model error:
    LCD pixelation of the LTC), which also keeps noise-free data finite.
    """
    pts = np.asarray(points_mm, dtype=np.float64)
    d, n = pts.shape[:2]
    if d < 2:
        raise RayFitError(f"principal rays need points at >= 2 depths, got {d}")
    if min_depths < 2:
        raise RayFitError(f"min_depths must be >= 2 (a line needs two points), got {min_depths}")
    std = np.asarray(std_mm, dtype=np.float64)
    var = np.sum(std**2, axis=-1) / 2.0 if std.ndim == 3 else std**2
    valid = np.asarray(valid, dtype=bool) & np.isfinite(pts).all(axis=-1) & np.isfinite(var)
    w0 = np.where(valid, 1.0 / (np.where(valid, var, 0.0) + floor_mm**2), 0.0)
    z = pts[..., 2]
    xy = pts[..., :2]
    used = valid.copy()
    flags = np.where(valid.sum(axis=0) < min_depths, FLAG_FEW_DEPTHS, 0)
    for attempt in range(max_outliers + 1):
        w = np.where(used, w0, 0.0)
        z_ref, c, s, vr, vs = _line_fit(z, xy, w)
        res = xy - (c + s * (z - z_ref)[..., None])
        # normalised residual; a point's own leverage is removed so that an outlier with a
        # large weight does not hide by pulling the line onto itself
        lev = w * (1.0 / np.where(w.sum(0) > 0, w.sum(0), 1.0)
                   + (z - z_ref) ** 2 * vs)
        score = np.where(used, np.linalg.norm(res, axis=-1)
                         * np.sqrt(w0 / np.maximum(1.0 - lev, 1e-9) / 2.0), 0.0)
        worst = score.argmax(axis=0)
        bad = (score[worst, np.arange(n)] > outlier_sigma) & ((flags & FLAG_FEW_DEPTHS) == 0)
        if not bad.any():
            break
        can = bad & (used.sum(axis=0) > min_depths) & (attempt < max_outliers)
        flags = np.where(bad & ~can, flags | FLAG_BAD_FIT, flags)
        used[worst[can], np.flatnonzero(can)] = False
        flags = np.where(can, flags | FLAG_OUTLIER, flags)
        if not can.any():
            break
    res = np.where(used[..., None], res, np.nan).astype(np.float32)
    return PrincipalRays(z_ref, c, s, vr, vs, res, used, flags.astype(np.int8),
                         np.linalg.norm(res, axis=-1))
