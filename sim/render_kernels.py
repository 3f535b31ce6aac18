"""Compiled loops of ``sim.render`` (numba): the bilinear gather of projected patterns through a
light transport, and the camera's digitisation, both written in place.

The gather reads the pattern images where they lie ((n, Hp, Wp), no transposed copy) and writes
each pattern's radiance straight into its image row ((n, H W)), so the cost of a pattern is one
pass over the transport's rays, with the bilinear weights of a block of rays computed once for
every pattern. The loops release the GIL (``nogil``); ``sim.render`` runs them on every core.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

_JIT = {"nogil": True, "cache": True, "error_model": "numpy"}
BLOCK_RAYS = 4096  # rays whose bilinear taps are computed once per block, for every pattern


@nb.njit(**_JIT)
def gather_rows(pixels, proj_uv, weight, patterns, out, first, last):
    """Radiance of transport rows ``first:last`` into ``out[p, pixels[i]]`` (float32) for every
    projected pattern ``p`` of ``patterns`` (n, Hp, Wp) float32: the sum over the row's rays of
    weight times the pattern sampled bilinearly at the ray's projector coordinate (pixel centres
    at integers, taps clamped to the edge pixels). Rays of weight <= 0 are skipped."""
    n_pat, hp, wp = patterns.shape
    k = weight.shape[1]
    flat = patterns.reshape(n_pat, hp * wp)
    rows_per_block = max(1, BLOCK_RAYS // k)
    taps = np.empty((rows_per_block * k, 4), np.uint32)  # unsigned: loads skip the wraparound check
    coef = np.empty((rows_per_block * k, 4), np.float32)
    ends = np.empty(rows_per_block, np.int64)
    for b0 in range(first, last, rows_per_block):
        b1 = min(b0 + rows_per_block, last)
        m = 0
        for i in range(b0, b1):
            for j in range(k):
                w = weight[i, j]
                if not w > 0:
                    continue
                u, v = proj_uv[i, j, 0], proj_uv[i, j, 1]
                fu, fv = math.floor(u), math.floor(v)
                au, av = u - fu, v - fv
                iu, iv = int(fu), int(fv)
                ia, ib = min(max(iu, 0), wp - 1), min(max(iu + 1, 0), wp - 1)
                ja, jb = min(max(iv, 0), hp - 1) * wp, min(max(iv + 1, 0), hp - 1) * wp
                taps[m, 0], taps[m, 1], taps[m, 2], taps[m, 3] = ja + ia, ja + ib, jb + ia, jb + ib
                a, c = w * (1 - au), w * au
                coef[m, 0], coef[m, 1] = a * (1 - av), c * (1 - av)
                coef[m, 2], coef[m, 3] = a * av, c * av
                m += 1
            ends[i - b0] = m
        for p in range(n_pat):
            img, row = flat[p], out[p]
            r = 0
            for i in range(b0, b1):
                e = ends[i - b0]
                s = np.float32(0.0)
                for q in range(r, e):
                    s += (coef[q, 0] * img[taps[q, 0]] + coef[q, 1] * img[taps[q, 1]]
                          + coef[q, 2] * img[taps[q, 2]] + coef[q, 3] * img[taps[q, 3]])
                row[pixels[i]] = s
                r = e


@nb.njit(**_JIT)
def digitise(x, scale, low_e, high_e, dn_per_e, black_dn, max_dn, quantize, out, first, last):
    """``out[i] = clip(clip(scale x[i], low_e, high_e) dn_per_e + black_dn, 0, max_dn)`` for flat
    indices ``first:last``, rounded half to even when ``quantize`` (then ``out`` is an integer
    array): electrons to DN (``scale`` turns radiance into electrons, or is 1)."""
    for i in range(first, last):
        e = min(max(x[i] * scale, low_e), high_e)
        dn = min(max(e * dn_per_e + black_dn, 0.0), max_dn)
        out[i] = np.rint(dn) if quantize else dn
