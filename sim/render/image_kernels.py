"""Compiled loops of ``sim.render.images`` (numba): the bilinear gather of projected patterns through a
light transport, and the camera's digitisation, both written in place.

The gather reads each pattern in its ``sim.render.pattern_stack`` form (a row or column profile, or
the full image) and writes its radiance into the pattern's image row ((n, H W)), so the cost of
a pattern is one pass over the transport's rays, with the taps of a block of rays computed once
for every pattern. The loops release the GIL (``nogil``); ``sim.render.images`` runs them on every core.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from sim.render.pattern_stack import ALONG_U, ALONG_V

_JIT = {"nogil": True, "cache": True, "error_model": "numpy"}
BLOCK_RAYS = 2048  # rays whose taps are computed once per block, for every pattern


@nb.njit(**_JIT)
def response(x, scale, low_e, high_e, dn_per_e, black_dn, max_dn):
    """DN of radiance ``x`` before rounding, float32:
    ``clip(clip(scale x, low_e, high_e) dn_per_e + black_dn, 0, max_dn)`` (``scale`` turns
    radiance into electrons, or is 1). ``IDENTITY`` keeps any ``x >= 0``."""
    e = x * scale
    e = e if e > low_e else low_e  # selects rather than min/max: they vectorise
    e = e if e < high_e else high_e
    dn = e * dn_per_e + black_dn
    dn = dn if dn > np.float32(0.0) else np.float32(0.0)
    return dn if dn < max_dn else max_dn


_INF = np.float32(np.inf)
IDENTITY = (np.float32(1.0), -_INF, _INF, np.float32(1.0), np.float32(0.0), _INF)


@nb.njit(**_JIT)
def write(row, start, index, values, m, resp, quantize):
    """``row[start + q] = response(values[q], *resp)`` for ``q < m`` (``row[index[q]]``, and
    ``start`` unused, when ``index`` is an array rather than None), rounded half to even when
    ``quantize`` (``row`` then an integer array)."""
    scale, low_e, high_e, dn_per_e, black_dn, max_dn = resp
    if index is not None:
        for q in range(m):
            dn = response(values[q], scale, low_e, high_e, dn_per_e, black_dn, max_dn)
            row[index[q]] = np.rint(dn) if quantize else dn
        return
    dst = row[start:start + m]  # indices from range(m): no negative-index checks, so the
    if quantize:                # loops vectorise
        for q in range(m):
            dn = response(values[q], scale, low_e, high_e, dn_per_e, black_dn, max_dn)
            dst[q] = np.rint(dn)
    else:
        for q in range(m):
            dst[q] = response(values[q], scale, low_e, high_e, dn_per_e, black_dn, max_dn)


@nb.njit(**_JIT)
def gather_rows(pixels, proj_uv, weight, form, slot, full, rows, cols, resp, quantize, out,
                first, last):
    """``response(radiance, *resp)`` (rounded when ``quantize``) of transport rows
    ``first:last`` into ``out[p, pixels[i]]`` for every pattern ``p`` of a
    ``sim.render.pattern_stack.PatternStack`` (``form``, ``slot``, ``full``, ``rows``, ``cols``).
    Radiance is the sum over the row's rays of weight times the pattern sampled bilinearly at
    the ray's projector coordinate (pixel centres at integers, taps clamped to the edge pixels);
    a row or column profile is sampled linearly along its axis, which is the same value. Rays of
    weight <= 0 add nothing."""
    n_pat = len(form)
    n_full, hp, wp = full.shape
    flat = full.reshape(n_full, hp * wp)
    k = weight.shape[1]
    ray_w, ray_uv = weight.reshape(-1), proj_uv.reshape(-1, 2)  # ray r = row r // k, ray r % k
    rows_per_block = max(1, BLOCK_RAYS // k)
    m_max = rows_per_block * k
    iu0, iu1 = np.empty(m_max, np.uint32), np.empty(m_max, np.uint32)  # unsigned: no wraparound
    iv0, iv1 = np.empty(m_max, np.uint32), np.empty(m_max, np.uint32)  # checks on the loads
    cu0, cu1 = np.empty(m_max, np.float32), np.empty(m_max, np.float32)  # weight times the
    cv0, cv1 = np.empty(m_max, np.float32), np.empty(m_max, np.float32)  # linear weights
    frac_v = np.empty(m_max, np.float32)
    m_full = m_max if n_full else 0  # bilinear taps and weights, only for full images
    t00, t01 = np.empty(m_full, np.uint32), np.empty(m_full, np.uint32)
    t10, t11 = np.empty(m_full, np.uint32), np.empty(m_full, np.uint32)
    c00, c01 = np.empty(m_full, np.float32), np.empty(m_full, np.float32)
    c10, c11 = np.empty(m_full, np.float32), np.empty(m_full, np.float32)
    acc, sums = np.empty(m_max, np.float32), np.empty(rows_per_block, np.float32)  # per ray, pixel
    ends = np.empty(rows_per_block, np.int64)
    zero, one = np.float32(0.0), np.float32(1.0)
    u_max, v_max = np.float32(wp - 1), np.float32(hp - 1)
    for b0 in range(first, last, rows_per_block):
        b1 = min(b0 + rows_per_block, last)
        m = (b1 - b0) * k
        bw, buv = ray_w[b0 * k:b0 * k + m], ray_uv[b0 * k:b0 * k + m]
        for q in range(m):  # float clamps and selects, no negative-index checks: it vectorises
            w, u, v = bw[q], buv[q, 0], buv[q, 1]
            hit = w > zero
            w, u, v = (w if hit else zero), (u if hit else zero), (v if hit else zero)
            fu, fv = np.floor(u), np.floor(v)
            au, av = u - fu, v - fv
            iu0[q] = np.uint32(min(max(fu, zero), u_max))
            iu1[q] = np.uint32(min(max(fu + one, zero), u_max))
            iv0[q] = np.uint32(min(max(fv, zero), v_max))
            iv1[q] = np.uint32(min(max(fv + one, zero), v_max))
            cu0[q], cu1[q] = w * (one - au), w * au
            cv0[q], cv1[q] = w * (one - av), w * av
            frac_v[q] = av
        n_pix = b1 - b0
        if k > 1:  # keep the rays that hit, in order; ends[i]: end of pixel i's rays
            m = 0
            for i in range(n_pix):
                for q in range(i * k, i * k + k):
                    if bw[q] > zero:
                        iu0[m], iu1[m], iv0[m], iv1[m] = iu0[q], iu1[q], iv0[q], iv1[q]
                        cu0[m], cu1[m], cv0[m], cv1[m] = cu0[q], cu1[q], cv0[q], cv1[q]
                        frac_v[m] = frac_v[q]
                        m += 1
                ends[i] = m
        for q in range(min(m, m_full)):
            r0, r1 = iv0[q] * wp, iv1[q] * wp
            t00[q], t01[q], t10[q], t11[q] = r0 + iu0[q], r0 + iu1[q], r1 + iu0[q], r1 + iu1[q]
            c00[q], c01[q] = cu0[q] * (one - frac_v[q]), cu1[q] * (one - frac_v[q])
            c10[q], c11[q] = cu0[q] * frac_v[q], cu1[q] * frac_v[q]
        p0 = pixels[b0]
        contiguous = True
        for i in range(b0 + 1, b1):
            contiguous = contiguous and pixels[i] == p0 + (i - b0)
        for p in range(n_pat):
            s, f = slot[p], form[p]
            if f == ALONG_U:  # one pass over the block's rays that vectorises
                prof = rows[s]
                for q in range(m):
                    acc[q] = cu0[q] * prof[iu0[q]] + cu1[q] * prof[iu1[q]]
            elif f == ALONG_V:
                prof = cols[s]
                for q in range(m):
                    acc[q] = cv0[q] * prof[iv0[q]] + cv1[q] * prof[iv1[q]]
            else:
                img = flat[s]
                for q in range(m):
                    acc[q] = (c00[q] * img[t00[q]] + c01[q] * img[t01[q]]
                              + c10[q] * img[t10[q]] + c11[q] * img[t11[q]])
            values = acc
            if k > 1:  # each pixel's rays, summed in order
                r = 0
                for i in range(n_pix):
                    t = zero
                    for q in range(r, ends[i]):
                        t += acc[q]
                    sums[i] = t
                    r = ends[i]
                values = sums
            write(out[p], p0, None if contiguous else pixels[b0:b1], values, n_pix, resp, quantize)


@nb.njit(**_JIT)
def digitise(x, resp, quantize, out, first, last):
    """``out[i] = response(x[i], *resp)`` for flat indices ``first:last``, rounded when
    ``quantize`` (``out`` then an integer array; otherwise it may be ``x`` itself)."""
    write(out, first, None, x[first:last], last - first, resp, quantize)
