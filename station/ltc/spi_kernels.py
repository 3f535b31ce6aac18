"""The compiled loops of the Fourier single-pixel reconstruction (:mod:`station.ltc.spi`):
demodulation, the level-correction inverse, the per-pixel scalars (gain, noise, centre,
window origin), the half spectrum for the batched inverse DFT and the window cut. Each runs
the operations of the numpy reference functions of ``spi`` in their order, so the results
are the same to the bit whatever calls them.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def _demodulate_kernel(d, j0, reg_idx, sc_idx, e_re, e_im, here, mirror, sc_flat, rest, pp,
                       f_reg, f_sc, planes, sigma):  # pragma: no cover - compiled
    """See :func:`_demodulate`; d (patterns, N) C-contiguous, pixels ``j0 : j0 + n``;
    fills planes (2 P^2, n) (re rows, then im rows: every row written, no zeroing pass)
    and sigma (n,) (the operations of :func:`_noise_from_means` in numpy's order);
    pattern-major loops (rows contiguous)."""
    n = planes.shape[1]
    m, steps = reg_idx.shape
    means = np.empty((m, n))
    acc_r, acc_i, acc_s = np.empty(n), np.empty(n), np.empty(n)
    for fi in range(m):
        # the first step initialises the sums (0.0 + x, as a zeroed sum would give: -0.0
        # becomes 0.0); each row a contiguous slice: these loops are vectorised (4x faster
        # than indexing the frame row at j0 + j)
        row = d[reg_idx[fi, 0], j0 : j0 + n]
        er, ei = e_re[0], e_im[0]
        for j in range(n):
            v = np.float64(row[j])
            acc_r[j] = 0.0 + v * er
            acc_i[j] = 0.0 + v * ei
            acc_s[j] = 0.0 + v
        for st in range(1, steps):
            row = d[reg_idx[fi, st], j0 : j0 + n]
            er, ei = e_re[st], e_im[st]
            for j in range(n):
                v = np.float64(row[j])
                acc_r[j] += v * er
                acc_i[j] += v * ei
                acc_s[j] += v
        h, mi = here[fi], mirror[fi]
        for j in range(n):
            gr, gi = f_reg * acc_r[j], f_reg * acc_i[j]
            planes[h, j] = gr
            planes[pp + h, j] = gi
            planes[mi, j] = gr
            planes[pp + mi, j] = -gi
            means[fi, j] = acc_s[j] / steps
    for si in range(sc_idx.shape[0]):
        plus, minus = d[sc_idx[si, 0], j0 : j0 + n], d[sc_idx[si, 1], j0 : j0 + n]
        q = sc_flat[si]
        for j in range(n):
            planes[q, j] = (np.float64(plus[j]) - np.float64(minus[j])) * f_sc
            planes[pp + q, j] = 0.0
    for q in rest:
        for j in range(n):
            planes[q, j] = 0.0
            planes[pp + q, j] = 0.0
    mu, ss = np.zeros(n), np.zeros(n)
    for fi in range(m):
        for j in range(n):
            mu[j] += means[fi, j]
    for j in range(n):
        mu[j] = mu[j] / m
    for fi in range(m):
        for j in range(n):
            dv = means[fi, j] - mu[j]
            ss[j] += dv * dv
    for j in range(n):
        sigma[j] = np.sqrt(steps * (ss[j] / (m - 1)))


@numba.njit(cache=True, nogil=True)
def _apply_level_inverse(planes, start, source, weight, here,
                         mirror):  # pragma: no cover - compiled
    """In place on planes (2 P^2, n) (re rows, then im rows): the regular rows ``here``
    (and their conjugates at ``mirror``) replaced by the sparse map of
    :class:`_LevelInverse` of the planes (its sources index the planes' rows directly)."""
    pp2, n = planes.shape
    pp = pp2 // 2
    m = here.shape[0]
    out = np.zeros((2 * m, n))
    for r in range(2 * m):
        o = out[r]
        for q in range(start[r], start[r + 1]):
            w = weight[q]
            x = planes[source[q]]
            for j in range(n):
                o[j] += w * x[j]
    for i in range(m):
        h, mi = here[i], mirror[i]
        for j in range(n):
            planes[h, j] = out[i, j]
            planes[pp + h, j] = out[m + i, j]
            planes[mi, j] = out[i, j]
            planes[pp + mi, j] = -out[m + i, j]


@numba.njit(cache=True, nogil=True)
def _window(folded, origin, gain, valid, ltc):  # pragma: no cover - compiled
    """:func:`unfold` divided by the gain (times its reciprocal) into ``ltc`` (n, P, P),
    float64 or float32 (each value computed in float64, then rounded), NaN where not
    ``valid``; returns the windows' outer-ring masses (n,) float64: folded (P, P, n)
    pixel-minor (as the batched inverse DFT leaves it), origin (n, 2) int (x, y), gain (n,),
    valid (n,) bool. Pixel after pixel: the P^2 cache lines of ``folded`` a pixel reads hold
    the next pixels' values too and stay in the L1 cache (36 kB at P = 24, double); each
    window row is two contiguous runs (no modulo per weight); a multiply per weight, not a
    divide (0.7 against 2.1 us per pixel)."""
    p, n = folded.shape[0], folded.shape[2]
    ring = np.empty(n)
    for j in range(n):
        if not valid[j]:
            ltc[j] = np.nan
            ring[j] = np.nan
            continue
        ox, oy = origin[j, 0] % p, origin[j, 1] % p
        inv = 1.0 / gain[j]
        for r in range(p):
            yy = (oy + r) % p
            for c in range(p - ox):
                ltc[j, r, c] = folded[yy, ox + c, j] * inv
            for c in range(p - ox, p):
                ltc[j, r, c] = folded[yy, c - (p - ox), j] * inv
        edge = 0.0  # the outer ring, in the order of a full r-major, c-minor pass
        for r in range(p):
            yy = (oy + r) % p
            if r == 0 or r == p - 1:
                for c in range(p):
                    edge += folded[yy, (ox + c) % p, j] * inv
            else:
                edge += folded[yy, ox, j] * inv
                edge += folded[yy, (ox + p - 1) % p, j] * inv
        ring[j] = edge
    return ring


@numba.njit(cache=True, nogil=True)
def _block_scalars(planes, sigma_d, lcd_xy, p, amplitude, noise_factor, min_snr,
                   min_harmonic, gain, noise, centre, valid,
                   origin):  # pragma: no cover - compiled
    """Per pixel of planes (2 P^2, n), frame noise sigma_d (n,) and coarse centres lcd_xy
    (n, 2): the gain ``G(0, 0)``, the LTC weight noise (:func:`ltc_noise`), the refined
    centre (:func:`_refine`), validity and window origin (:func:`centred_origins`), each
    with the numpy functions' operations in their order, into the given arrays."""
    pp = p * p
    n = planes.shape[1]
    snr_den = np.sqrt(2.0) * amplitude
    half = p // 2
    for j in range(n):
        g0 = planes[0, j]
        gain[j] = g0
        sigma = sigma_d[j]
        noise[j] = noise_factor * sigma / g0 if g0 > 0 else np.nan
        ok = True
        for axis in range(2):
            row = 1 if axis == 0 else p
            gr, gi = planes[row, j], planes[pp + row, j]
            c = lcd_xy[j, axis]
            xp = (-np.arctan2(gi, gr) * p / (2 * np.pi)) % p
            fine = xp + p * np.round((c - xp) / p)
            v = c
            if np.hypot(gr, gi) >= min_harmonic * g0 and np.isfinite(c):
                v = fine
            centre[j, axis] = v
            ok = ok and np.isfinite(v)
        ok = ok and g0 > 0 and g0 > min_snr * sigma / snr_den
        valid[j] = ok
        for axis in range(2):
            origin[j, axis] = np.int32(np.floor(centre[j, axis] + 0.5) - half) if ok else 0


@numba.njit(cache=True, nogil=True)
def _half_spectrum(planes, p, half):  # pragma: no cover - compiled
    """The non-negative-k half (P, P // 2 + 1, n) complex of the spectrum in planes
    (2 P^2, n), frequency-major (what the batched real inverse DFT reads)."""
    pp, q, n = p * p, half.shape[1], planes.shape[1]
    for l in range(p):
        for k in range(q):
            re, im, out = planes[l * p + k], planes[pp + l * p + k], half[l, k]
            for j in range(n):
                out[j] = complex(re[j], im[j])
