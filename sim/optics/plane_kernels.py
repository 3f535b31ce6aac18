"""Compiled ray-plane hits and footprint deposition of ``sim.optics.plane_ltc`` (numba),
kept out of ``plane_ltc.py`` so that importing it does not load numba."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

MAX_HALF_PX = 7.0  # a footprint narrower than 14 plane pixels spans at most 16 of them


@nb.njit(parallel=True, nogil=True, cache=True, error_model="numpy", boundscheck=False)
def deposit_footprints(xy, half, weight, lo, plane_size, out):
    """Add each ray's weight into ``out`` (n, wy, wx), spread over the plane pixels its
    footprint overlaps in proportion to the overlapped area, one pixel per thread. xy :
    (n, r, 2) hits, plane pixels; half : (n, r, 2) the footprints' half-widths along x and
    y, plane pixels, below ``MAX_HALF_PX`` (the caller checks); weight : (n, r) (rays with
    weight <= 0 are skipped); lo : (n, 2) plane pixel of ``out[i, 0, 0]``; plane_size :
    (width, height); cells outside the plane get nothing."""
    pw, ph = plane_size
    for i in nb.prange(xy.shape[0]):
        fx = np.empty(16)
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


@nb.njit(parallel=True, nogil=True, cache=True, error_model="numpy", boundscheck=False)
def plane_hits(origins, directions, weights, R, t, pitch_mm, half_scale, xy, half, w_out,
              box):
    """Intersect each ray with the plane ``z = 0`` of the plane frame, one pixel per thread.
    origins, directions : (n, r, 3) camera frame, mm; weights : (n, r); R (3, 3), t (3,):
    ``X_plane = R X_cam + t``; pitch_mm : plane pixel pitch; half_scale : (2,) footprint
    half-width per mm of camera-frame depth along x and y, plane pixels. Writes xy (n, r, 2)
    hits in plane pixels, half (n, r, 2) footprint half-widths, w_out (n, r) the weight of
    each ray that hits in front of the camera (else 0; hits and half-widths then 0), and box
    (n, 4) int64: the plane pixels ``lo_x, lo_y, hi_x, hi_y`` the pixel's footprints touch
    (all 0 when none hits)."""
    n, r = weights.shape
    for i in nb.prange(n):
        lox, loy, hix, hiy = np.inf, np.inf, -np.inf, -np.inf
        for j in range(r):
            ox, oy, oz = origins[i, j, 0], origins[i, j, 1], origins[i, j, 2]
            dx, dy, dz = directions[i, j, 0], directions[i, j, 1], directions[i, j, 2]
            pz = R[2, 0] * ox + R[2, 1] * oy + R[2, 2] * oz + t[2]
            qz = R[2, 0] * dx + R[2, 1] * dy + R[2, 2] * dz
            tt = -pz / qz
            w = weights[i, j]
            if tt > 0.0 and w > 0.0:
                px = R[0, 0] * ox + R[0, 1] * oy + R[0, 2] * oz + t[0]
                py = R[1, 0] * ox + R[1, 1] * oy + R[1, 2] * oz + t[1]
                qx = R[0, 0] * dx + R[0, 1] * dy + R[0, 2] * dz
                qy = R[1, 0] * dx + R[1, 1] * dy + R[1, 2] * dz
                x = (px + tt * qx) / pitch_mm
                y = (py + tt * qy) / pitch_mm
                depth = oz + tt * dz
                hx, hy = half_scale[0] * depth, half_scale[1] * depth
                xy[i, j, 0], xy[i, j, 1] = x, y
                half[i, j, 0], half[i, j, 1] = hx, hy
                w_out[i, j] = w
                lox = min(lox, math.floor(x - hx + 0.5))
                loy = min(loy, math.floor(y - hy + 0.5))
                hix = max(hix, math.floor(x + hx + 0.5))
                hiy = max(hiy, math.floor(y + hy + 0.5))
            else:
                xy[i, j, 0], xy[i, j, 1] = 0.0, 0.0
                half[i, j, 0], half[i, j, 1] = 0.0, 0.0
                w_out[i, j] = 0.0
        if lox <= hix:
            box[i, 0], box[i, 1], box[i, 2], box[i, 3] = int(lox), int(loy), int(hix), int(hiy)
        else:
            box[i, 0], box[i, 1], box[i, 2], box[i, 3] = 0, 0, 0, 0
