"""Compiled ray geometry of ``sim.optics.lens`` bundles (numba), kept out of ``lens.py`` so that
importing the lens models does not load numba (``lens`` imports this module on first use)."""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
def aimed_directions(xy_n, pupil, z_aim, coma, out):
    """Unit directions (n, K, 3) into ``out`` of rays from the aperture points ``pupil`` (K, 2)
    mm (z = 0) through the aim points ``(x z_k + c_k x, y z_k + c_k y, z_k)`` of pixels with
    normalised coordinates ``xy_n`` (n, 2), for per-sample aim depths ``z_aim`` and lateral
    factors ``coma`` (K,): the ray geometry of ``sim.optics.lens`` bundles. The loop over samples
    is vectorised (contiguous arrays), then interleaved into ``out``."""
    k = pupil.shape[0]
    px, py = pupil[:, 0].copy(), pupil[:, 1].copy()
    ax, ay, az = np.empty(k), np.empty(k), np.empty(k)
    for i in range(xy_n.shape[0]):
        x, y = xy_n[i, 0], xy_n[i, 1]
        for j in range(k):
            z = z_aim[j]
            dx = x * z + coma[j] * x - px[j]
            dy = y * z + coma[j] * y - py[j]
            inv = 1.0 / math.sqrt(dx * dx + dy * dy + z * z)
            ax[j] = dx * inv
            ay[j] = dy * inv
            az[j] = z * inv
        for j in range(k):
            out[i, j, 0], out[i, j, 1], out[i, j, 2] = ax[j], ay[j], az[j]
