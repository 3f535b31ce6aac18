"""Focus distance per aperture zone (spherical aberration, docs/optics.md section 9) from the LTCs
of the pixels at the optical centre.

At the optical centre the pupil is unvignetted and rotationally symmetric. A ray through
pupil radius ``rho`` aimed at that zone's focus ``z(rho)`` lands on an LCD at distance ``z_i``
from the optical centre ``p (1 - z_i / z(rho))`` from the principal ray, so the LTC's radial
profile shrinks towards each zone's own focus: on the near side of focus the rim (focusing
farther away for positive spherical aberration) spreads relatively more than on the far side.
The pupil's second moments alone cannot see this (they give one RMS-best focus, the lens
file's ``focus_distance_mm``), so the model ``1 / z(rho) = c0 + c1 rho^2`` with a uniform
disk of radius ``R`` is fitted to the LTC windows themselves by least squares: each
model ray is spread over the camera pixel's footprint on the LCD (``z_i / f`` mm: a box, or
``pixel_samples`` x ``pixel_samples`` points for a simulated camera rendered that way) and
binned into the LCD's pixels, centred on each window's measured centroid.

On the experiment's fake benches (docs/decisions 0017) it recovers the true lenses'
``z(rho)`` within ~1.5 mm over the whole pupil (760 -> 775 and 760 -> 768 mm) and their
pupil radius within 0.01 mm.
"""

from __future__ import annotations

from typing import cast

import numpy as np
from scipy.optimize import least_squares

from station.lens.centroids import window_stats
from station.ltc.store import LtcVolume

ZONE_POINTS = 4000  # model rays over the unit disk (sunflower)
ZONES = 9  # rows of the stored table: pupil radius 0 .. R


def _sunflower(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    k = np.arange(n) + 0.5
    r = np.sqrt(k / n)
    t = k * np.pi * (3.0 - np.sqrt(5.0))
    return r, r * np.cos(t), r * np.sin(t)


def _overlap(x: np.ndarray, width: float, cells: np.ndarray) -> np.ndarray:
    """Fraction (m, P) of each box ``[x - width/2, x + width/2]`` (m,) inside the unit cells
    centred on ``cells`` (P,); all in LCD pixels."""
    lo = np.maximum(x[:, None] - width / 2, cells[None] - 0.5)
    hi = np.minimum(x[:, None] + width / 2, cells[None] + 0.5)
    return np.clip(hi - lo, 0.0, None) / width


def centre_windows(volume: LtcVolume, centre_uv: np.ndarray,
                   half_px: int) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """The normalised LTC windows (depth index, (P, P) window, centroid (x, y) in window
    pixels) of the pixels within ``half_px`` of the optical centre's pixel ``centre_uv``,
    each cut to its signal region (``window_stats``)."""
    w, h = volume.camera_size
    u0 = max(int(np.floor(centre_uv[0])) - half_px + 1, 0)
    u1 = min(int(np.ceil(centre_uv[0])) + half_px, w)
    v0 = max(int(np.floor(centre_uv[1])) - half_px + 1, 0)
    v1 = min(int(np.ceil(centre_uv[1])) + half_px, h)
    out = []
    for v in range(v0, v1):
        ltc = np.asarray(volume.ltc[:, v, u0:u1], dtype=np.float64)
        noise = np.asarray(volume.noise[:, v, u0:u1], dtype=np.float64)
        for i in range(len(volume.depths_mm)):
            st = window_stats(ltc[i], noise[i])
            for j in range(u1 - u0):
                hh = np.where(st.region[j], ltc[i, j], 0.0)
                if np.isfinite(hh).all() and hh.sum() > 0 and np.isfinite(st.centroid[j]).all():
                    out.append((i, hh / hh.sum(), st.centroid[j]))
    return out


def fit_focus_zones(volume: LtcVolume, centre_z_mm: float, K: np.ndarray,
                    focus_distance_mm: float, pupil_radius_mm: float, half_px: int = 2,
                    pixel_samples: int = 0) -> tuple[np.ndarray, dict] | None:
    """The focus distance per pupil zone: a table (ZONES, 2) of pupil radius mm (0 .. the
    fitted radius R) and focus distance mm from the optical centre, with a dict of the fit
    (``c0`` 1/mm, ``c1`` 1/mm^3, ``radius_mm``, ``cost``, ``cost_single_focus``, ``windows``);
    None where the centre's windows do not support a fit. ``focus_distance_mm`` and
    ``pupil_radius_mm`` start the fit; ``pixel_samples``: 0 for a camera pixel integrating
    a box, n for n x n point samples."""
    uv = np.asarray(K[:2, 2], dtype=np.float64)
    data = centre_windows(volume, uv, half_px)
    if len(data) < 3 * len(volume.depths_mm):
        return None
    z = np.asarray(volume.depths_mm, dtype=np.float64) - centre_z_mm
    pitch = float(volume.pitch_mm)
    fp_px = np.abs(z) / float(np.sqrt(K[0, 0] * K[1, 1])) / pitch
    r_u, ux, uy = _sunflower(ZONE_POINTS)
    cells = np.arange(data[0][1].shape[0], dtype=np.float64)

    def predict(c0: float, c1: float, radius: float, i: int, cen: np.ndarray) -> np.ndarray:
        f = 1.0 - z[i] * (c0 + c1 * (radius * r_u) ** 2)
        x = radius * ux * f / pitch + cen[0]
        y = radius * uy * f / pitch + cen[1]
        if pixel_samples == 0:
            return _overlap(y, fp_px[i], cells).T @ _overlap(x, fp_px[i], cells) / len(x)
        offs = ((np.arange(pixel_samples) + 0.5) / pixel_samples - 0.5) * fp_px[i]
        # each model ray's own share of the pupil, so the binning is continuous
        spread = max(radius * np.sqrt(np.pi / len(x)) * abs(1 - z[i] * c0) / pitch, 1e-3)
        ox = cast(np.ndarray, sum(_overlap(x + o, spread, cells) for o in offs))
        oy = cast(np.ndarray, sum(_overlap(y + o, spread, cells) for o in offs))
        return oy.T @ ox / (len(x) * pixel_samples**2)

    def resid(p: np.ndarray, single: bool = False) -> np.ndarray:
        c0, c1, radius = p[0] * 1e-3, (0.0 if single else p[1] * 1e-7), p[-1]
        return np.concatenate([(predict(c0, c1, radius, i, c) - hh).ravel()
                               for i, hh, c in data])

    x0 = np.array([1e3 / focus_distance_mm, 0.0, pupil_radius_mm])
    scale = np.array([1e-3 * x0[0], 1.0, 0.01 * pupil_radius_mm])
    try:
        fit = least_squares(resid, x0, x_scale=scale)
        single = least_squares(lambda p: resid(p, True), x0[[0, 2]], x_scale=scale[[0, 2]])
    except (ValueError, np.linalg.LinAlgError):
        return None
    c0, c1, radius = fit.x[0] * 1e-3, fit.x[1] * 1e-7, float(fit.x[2])
    rho = np.linspace(0.0, radius, ZONES)
    inv = c0 + c1 * rho**2
    if not (fit.success and radius > 0 and np.all(np.isfinite(inv)) and np.all(inv > 0)):
        return None
    table = np.stack([rho, 1.0 / inv], axis=1)
    return table, {"c0_per_mm": c0, "c1_per_mm3": c1, "radius_mm": radius,
                   "cost": float(fit.cost), "cost_single_focus": float(single.cost),
                   "single_focus_mm": float(1e3 / single.x[0]), "windows": len(data),
                   "pixel_samples": pixel_samples}

