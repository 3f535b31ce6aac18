"""Compiled per-pixel loops of ``sim.dataset.generate`` (numba; they release the GIL).

Each replaces a chain of numpy passes over a camera's frames with one pass, and computes the
same float32 values bit for bit: the same operations in the same order, no fused multiply-add
(numba does not contract without ``fastmath``). Transcendentals (``arctan2``, ``hypot``) stay
with numpy, whose float32 loops the loops here cannot be sure to match.
"""

from __future__ import annotations

from typing import Any

import numba as nb
import numpy as np

_JIT: dict[str, Any] = {"nogil": True, "cache": True, "error_model": "numpy"}


@nb.njit(**_JIT)
def expose(rad, z, exposure, r2, shot, threshold, full_well, dn_per_e, black, max_dn, quantize,
           out, low):  # pragma: no cover - compiled
    """One pass over flat radiance ``rad`` and normal deviates ``z`` (float32): a pixel's DN
    (shot and read noise as one normal deviate, full-well clip, gain, black level, clip to
    ``[0, max_dn]``, rounded half to even when ``quantize``) into ``out`` (float32, or the
    integer type of the images). Pixels whose electrons lie in (0, threshold) with shot noise
    on are left out and their indices listed in ``low``. Returns how many were listed."""
    n_low = 0
    zero = np.float32(0.0)
    read_sd = np.sqrt(r2)
    for i in range(rad.size):
        e = rad[i] * exposure
        if e <= zero:  # dark (most pixels miss): the read noise alone, sqrt(r2) hoisted
            e = zero + read_sd * z[i]
            if e > full_well:
                e = full_well
            dn = e * dn_per_e + black
            dn = zero if dn < zero else (max_dn if dn > max_dn else dn)
            out[i] = np.rint(dn) if quantize else dn
            continue
        if shot and e < threshold:
            low[n_low] = i
            n_low += 1
            continue
        var = r2 + (e if shot else zero)
        e = e + np.sqrt(var) * z[i]
        if e > full_well:
            e = full_well
        dn = e * dn_per_e + black
        dn = zero if dn < zero else (max_dn if dn > max_dn else dn)
        out[i] = np.rint(dn) if quantize else dn
    return n_low


@nb.njit(**_JIT)
def noise_free_dn(rad, idx, exposure, full_well, dn_per_e, black, out):  # pragma: no cover
    """``out[j] = min(rad[idx[j]] exposure, full_well) dn_per_e + black`` (float32): the
    noise-free, unquantised images of the phase-shift patterns ``idx``, ``rad`` (n, P)."""
    for j in range(idx.size):
        r, o = rad[idx[j]], out[j]
        for p in range(r.size):
            e = r[p] * exposure
            if e > full_well:
                e = full_well
            o[p] = e * dn_per_e + black


@nb.njit(**_JIT)
def mean(dn, n_f32, out):  # pragma: no cover - compiled
    """``out = (sum_k I_k) / N`` of ``N`` images ``dn`` (N, P) float32, summed in k order
    (numpy's ``mean(axis=0)``); ``n_f32`` = N as float32."""
    for p in range(dn.shape[1]):
        s = dn[0, p]
        for k in range(1, dn.shape[0]):
            s = s + dn[k, p]
        out[p] = s / n_f32


@nb.njit(**_JIT)
def wrap_phase(ph, two_pi):  # pragma: no cover - compiled
    """``ph`` (from ``arctan2``, in [-pi, pi]) taken into [0, 2 pi) in place, as
    ``mod(ph, two_pi)`` then 0 where that reaches ``two_pi`` does (float32): negatives gain
    ``two_pi``, zeros of either sign become +0, NaN stays."""
    zero = np.float32(0.0)
    for p in range(ph.size):
        x = ph[p]
        if x < zero:
            x = x + two_pi
        elif x == zero:
            x = zero
        ph[p] = zero if x >= two_pi else x


@nb.njit(**_JIT)
def normals(g, o, out):  # pragma: no cover - compiled
    """Unit normals ``out`` (H, W, 3) float32 of camera-frame points ``g`` (H, W, 3) float32
    with object ids ``o`` (H, W): the cross product of the neighbour differences along u and
    along v (central where both same-object neighbours are, else one-sided, NaN where none;
    per component), normalised and turned to face the camera at the origin; NaN where nothing
    was hit."""
    h, w = o.shape
    nan = np.float32(np.nan)
    half = np.float32(0.5)
    zero = np.float32(0.0)
    du = np.empty(3, np.float32)
    dv = np.empty(3, np.float32)
    for a in range(h):
        for b in range(w):
            ob = o[a, b]
            if ob < 0:
                out[a, b, 0], out[a, b, 1], out[a, b, 2] = nan, nan, nan
                continue
            # same-object neighbours (along u: fu forward, bu backward; along v: fv, bv)
            fu = b + 1 < w and o[a, b + 1] == ob
            bu = b >= 1 and o[a, b - 1] == ob
            fv = a + 1 < h and o[a + 1, b] == ob
            bv = a >= 1 and o[a - 1, b] == ob
            for k in range(3):  # central differences, else one-sided, else NaN
                gk = g[a, b, k]
                f = g[a, b + 1, k] - gk if fu else nan
                r = gk - g[a, b - 1, k] if bu else nan
                c = half * (f + r)
                if np.isnan(c):
                    c = f
                if np.isnan(c):
                    c = r
                du[k] = c
                f = g[a + 1, b, k] - gk if fv else nan
                r = gk - g[a - 1, b, k] if bv else nan
                c = half * (f + r)
                if np.isnan(c):
                    c = f
                if np.isnan(c):
                    c = r
                dv[k] = c
            n0 = du[1] * dv[2] - du[2] * dv[1]
            n1 = du[2] * dv[0] - du[0] * dv[2]
            n2 = du[0] * dv[1] - du[1] * dv[0]
            norm = np.sqrt((n0 * n0 + n1 * n1) + n2 * n2)
            n0, n1, n2 = n0 / norm, n1 / norm, n2 / norm
            d = (n0 * g[a, b, 0] + n1 * g[a, b, 1]) + n2 * g[a, b, 2]
            if d > zero:
                n0, n1, n2 = -n0, -n1, -n2
            out[a, b, 0], out[a, b, 1], out[a, b, 2] = n0, n1, n2


@nb.njit(**_JIT)
def truth(pmap, depth, obj, lit, xy, period_px, two_pi, absph, order, uv, z32, points,
          mask):  # pragma: no cover - compiled
    """The chief rays' truth maps of flat pixels: ``absph = float32(2 pi u_p / period_px)``,
    ``order = floor(2 pi u_p / period_px / 2 pi)`` (-1 where not finite), ``uv`` and ``z32``
    the projector map and depth as float32, the camera-frame ``points`` (x z, y z, z) in
    float32 and the ``mask`` (0 nothing hit, 1 lit, 2 shadowed, 3 outside the projector)."""
    for p in range(obj.size):
        a = two_pi * pmap[p, 0] / period_px
        absph[p] = np.float32(a)
        order[p] = np.int32(np.floor(a / two_pi)) if np.isfinite(a) else np.int32(-1)
        uv[p, 0], uv[p, 1] = np.float32(pmap[p, 0]), np.float32(pmap[p, 1])
        z = np.float32(depth[p])
        z32[p] = z
        points[p, 0] = np.float32(xy[p, 0]) * z
        points[p, 1] = np.float32(xy[p, 1]) * z
        points[p, 2] = z
        if obj[p] < 0:
            mask[p] = 0
        elif lit[p]:
            mask[p] = 1
        elif np.isfinite(pmap[p, 0]):
            mask[p] = 2
        else:
            mask[p] = 3
