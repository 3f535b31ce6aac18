"""Compiled footprint deposition of ``sim.optics.plane_ltc`` (numba), kept out of
``plane_ltc.py`` so that importing it does not load numba."""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
def deposit_footprints(xy, half, weight, lo, plane_size, out):
    """Add each ray's weight into ``out`` (n, wy, wx), spread over the plane pixels its
    footprint overlaps in proportion to the overlapped area. xy : (n, r, 2) hits, plane
    pixels; half : (n, r, 2) the footprints' half-widths along x and y, plane pixels;
    weight : (n, r) (rays with weight <= 0 are skipped); lo : (n, 2) plane pixel of
    ``out[i, 0, 0]``; plane_size : (width, height); cells outside the plane get nothing."""
    pw, ph = plane_size
    wy, wx = out.shape[1], out.shape[2]
    fx = np.empty(16)
    for i in range(xy.shape[0]):
        lx, ly = lo[i, 0], lo[i, 1]
        for j in range(xy.shape[1]):
            w = weight[i, j]
            if not w > 0.0:
                continue
            x, y = xy[i, j, 0], xy[i, j, 1]
            hx, hy = half[i, j, 0], half[i, j, 1]
            x0 = int(math.floor(x - hx + 0.5))
            x1 = int(math.floor(x + hx + 0.5))
            y0 = int(math.floor(y - hy + 0.5))
            y1 = int(math.floor(y + hy + 0.5))
            nx = x1 - x0 + 1
            if nx > fx.shape[0]:
                raise ValueError("plane_ltc: a subpixel's footprint spans more than 16 plane "
                                 "pixels; use more subpixels")
            for a in range(nx):
                c = x0 + a
                over = min(x + hx, c + 0.5) - max(x - hx, c - 0.5)
                fx[a] = over / (2.0 * hx) if (over > 0.0 and 0 <= c < pw) else 0.0
            for r in range(y0, y1 + 1):
                if r < 0 or r >= ph:
                    continue
                over = min(y + hy, r + 0.5) - max(y - hy, r - 0.5)
                if over <= 0.0:
                    continue
                wr = w * over / (2.0 * hy)
                for a in range(nx):
                    if fx[a] > 0.0:
                        out[i, r - ly, x0 + a - lx] += wr * fx[a]
