"""Compiled per-pixel loops of ``sim.dataset.generate`` (numba; they release the GIL).

Each replaces a chain of numpy passes over a camera's frames with one pass, and computes the
same float32 values bit for bit: the same operations in the same order, no fused multiply-add
(numba does not contract without ``fastmath``). Transcendentals (``arctan2``, ``hypot``) stay
with numpy, whose float32 loops the loops here cannot be sure to match.
"""

from __future__ import annotations

import numba as nb
import numpy as np

_JIT = {"nogil": True, "cache": True, "error_model": "numpy"}


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
    for i in range(rad.size):
        e = rad[i] * exposure
        if e < zero:
            e = zero
        if shot and e > zero and e < threshold:
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
def _diff(g, o, a, b, axis):  # pragma: no cover - compiled
    """Neighbour difference of points ``g`` (H, W, 3) along ``axis`` at pixel (a, b): central
    where both same-object neighbours are, else one-sided, NaN where none (per component)."""
    h, w = o.shape
    nan = np.float32(np.nan)
    if axis == 1:
        fwd_ok = b + 1 < w and o[a, b + 1] == o[a, b] and o[a, b + 1] >= 0
        bwd_ok = b >= 1 and o[a, b] == o[a, b - 1] and o[a, b] >= 0
        a1, b1, a0, b0 = a, b + 1, a, b - 1
    else:
        fwd_ok = a + 1 < h and o[a + 1, b] == o[a, b] and o[a + 1, b] >= 0
        bwd_ok = a >= 1 and o[a, b] == o[a - 1, b] and o[a, b] >= 0
        a1, b1, a0, b0 = a + 1, b, a - 1, b
    return (_central(g, a, b, a1, b1, a0, b0, 0, fwd_ok, bwd_ok, nan),
            _central(g, a, b, a1, b1, a0, b0, 1, fwd_ok, bwd_ok, nan),
            _central(g, a, b, a1, b1, a0, b0, 2, fwd_ok, bwd_ok, nan))


@nb.njit(**_JIT)
def _central(g, a, b, a1, b1, a0, b0, k, fwd_ok, bwd_ok, nan):  # pragma: no cover - compiled
    f = g[a1, b1, k] - g[a, b, k] if fwd_ok else nan
    r = g[a, b, k] - g[a0, b0, k] if bwd_ok else nan
    c = np.float32(0.5) * (f + r)
    if np.isnan(c):
        c = f
    if np.isnan(c):
        c = r
    return c


@nb.njit(**_JIT)
def normals(g, o, out):  # pragma: no cover - compiled
    """Unit normals ``out`` (H, W, 3) float32 of camera-frame points ``g`` (H, W, 3) float32
    with object ids ``o`` (H, W): the cross product of the neighbour differences along u and
    along v, normalised and turned to face the camera at the origin."""
    h, w = o.shape
    for a in range(h):
        for b in range(w):
            u = _diff(g, o, a, b, 1)
            v = _diff(g, o, a, b, 0)
            n0 = u[1] * v[2] - u[2] * v[1]
            n1 = u[2] * v[0] - u[0] * v[2]
            n2 = u[0] * v[1] - u[1] * v[0]
            norm = np.sqrt((n0 * n0 + n1 * n1) + n2 * n2)
            n0, n1, n2 = n0 / norm, n1 / norm, n2 / norm
            d = (n0 * g[a, b, 0] + n1 * g[a, b, 1]) + n2 * g[a, b, 2]
            if d > np.float32(0.0):
                n0, n1, n2 = -n0, -n1, -n2
            out[a, b, 0], out[a, b, 1], out[a, b, 2] = n0, n1, n2
