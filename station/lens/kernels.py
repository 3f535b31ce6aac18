"""Compiled (numba) kernels of the lens derivation: the same formulas as the numpy reference
code they replace (``station.lens.centroids.window_stats``, ``station.lens.aperture.resample``),
one window or node at a time so nothing grows with the batch.

``stats_kernel`` computes what ``window_stats`` documents (3 x 3 box smoothing, the
8-connected region above the threshold that holds the smoothed peak, grown by a disk of
radius ``REGION_MARGIN_PX + 0.5``; centroid, moments and their noise); only the order of
floating-point sums differs from the numpy version (tests compare them within 1e-12).
``resample_kernel`` is ``aperture.resample`` (nearest LCD pixel at each sub-cell centre).
``moments_kernel`` is ``aperture.grid_moments``. The sampling and deconvolution kernels are
``station.lens.sample_kernels`` (re-exported here).
"""

from __future__ import annotations

import numba
import numpy as np

from station.lens.sample_kernels import (
    lloyd_kernel,
    richardson_lucy_kernel,
    rings_kernel,
    stable_argsort,
)

__all__ = ["lloyd_kernel", "moments_kernel", "resample_kernel", "resample_zoned_kernel",
           "richardson_lucy_kernel", "rings_kernel", "stable_argsort", "stats_kernel"]


@numba.njit(cache=True, nogil=True)
def stats_kernel(h: np.ndarray, sigma: np.ndarray, signal: np.ndarray, noise_sigmas: float,
                 peak_fraction: float, margin: int, centroid: np.ndarray,
                 centroid_std: np.ndarray, moments: np.ndarray, trace_std: np.ndarray,
                 region_out: np.ndarray, status_out: np.ndarray,
                 zero_outside: bool = False) -> None:
    """Per window n: h (n, P, P) float64 (NaN windows already zeroed), sigma (n,), signal (n,)
    bool; writes centroid (n, 2), centroid_std (n, 2), moments (n, 3), trace_std (n,),
    region_out (n, P, P) bool, status_out (n,) int8 (0 ok, 1 no signal, 2 truncated);
    ``zero_outside``: also set h to 0 outside region_out (the aperture pass's windows)."""
    n, p = h.shape[0], h.shape[1]
    sm = np.empty((p, p))
    tmp = np.empty((p, p))
    above = np.empty((p, p), dtype=np.bool_)
    core = np.empty((p, p), dtype=np.bool_)
    region = np.empty((p, p), dtype=np.bool_)
    stack = np.empty(p * p, dtype=np.int64)
    r2m = (margin + 0.5) ** 2
    for k in range(n):
        hz = h[k]
        sig_k = sigma[k] if signal[k] else 0.0
        # separable 3-tap box, zero outside (uniform_filter mode "constant"): rows then columns
        for i in range(p):
            for j in range(p):
                a = hz[i - 1, j] if i > 0 else 0.0
                c = hz[i + 1, j] if i < p - 1 else 0.0
                tmp[i, j] = (a + hz[i, j] + c) / 3.0
        peak = -np.inf
        ipk = 0
        rawmax = -np.inf
        for i in range(p):
            for j in range(p):
                a = tmp[i, j - 1] if j > 0 else 0.0
                c = tmp[i, j + 1] if j < p - 1 else 0.0
                v = (a + tmp[i, j] + c) / 3.0
                sm[i, j] = v
                if v > peak:
                    peak = v
                    ipk = i * p + j
                if hz[i, j] > rawmax:
                    rawmax = hz[i, j]
        thr = max(noise_sigmas * sig_k / 3.0, peak_fraction * peak)
        for i in range(p):
            for j in range(p):
                above[i, j] = (sm[i, j] > thr) and signal[k] and peak > 0
                core[i, j] = False
        lab = above[ipk // p, ipk % p]
        if lab:  # flood fill (8-connected) from the peak
            top = 0
            stack[0] = ipk
            core[ipk // p, ipk % p] = True
            top = 1
            while top > 0:
                top -= 1
                q = stack[top]
                qi, qj = q // p, q % p
                for di in range(-1, 2):
                    for dj in range(-1, 2):
                        ii, jj = qi + di, qj + dj
                        if 0 <= ii < p and 0 <= jj < p and above[ii, jj] and not core[ii, jj]:
                            core[ii, jj] = True
                            stack[top] = ii * p + jj
                            top += 1
        raw_thr = max(noise_sigmas * sig_k, peak_fraction * rawmax)
        edge = False
        for i in range(p):
            for j in range(p):
                if (i == 0 or i == p - 1 or j == 0 or j == p - 1) and core[i, j] \
                        and hz[i, j] > raw_thr:
                    edge = True
        # region: core dilated by the disk. Only core pixels with a 4-neighbour outside the
        # core (or at the window's edge) paint their disk: a point within the disk of an
        # inner core pixel q is reached from q by unit steps along the axes, each of which
        # shortens the offset left, so it lies within the disk of the last core pixel on
        # that path, which has a 4-neighbour outside the core: the same region, a fraction
        # of the painting (0.7 us less per window).
        for i in range(p):
            for j in range(p):
                region[i, j] = False
        for i in range(p):
            for j in range(p):
                if not core[i, j]:
                    continue
                if 0 < i < p - 1 and 0 < j < p - 1 and core[i - 1, j] and core[i + 1, j] \
                        and core[i, j - 1] and core[i, j + 1]:
                    region[i, j] = True
                    continue
                for di in range(-margin, margin + 1):
                    ii = i + di
                    if ii < 0 or ii >= p:
                        continue
                    for dj in range(-margin, margin + 1):
                        jj = j + dj
                        if 0 <= jj < p and di * di + dj * dj <= r2m:
                            region[ii, jj] = True
        s = 0.0
        sx = 0.0
        sy = 0.0
        npx = 0
        for i in range(p):
            for j in range(p):
                if region[i, j]:
                    v = hz[i, j]
                    s += v
                    sx += v * j
                    sy += v * i
                    npx += 1
        ok = signal[k] and lab and s > noise_sigmas * sigma[k] * np.sqrt(max(npx, 1))
        safe = s if ok else 1.0
        cx = sx / safe
        cy = sy / safe
        mxx = 0.0
        myy = 0.0
        mxy = 0.0
        sdx = 0.0
        sdy = 0.0
        for i in range(p):
            for j in range(p):
                if region[i, j]:
                    v = hz[i, j]
                    dx = j - cx
                    dy = i - cy
                    mxx += v * dx * dx
                    myy += v * dy * dy
                    mxy += v * dx * dy
                    sdx += dx * dx
                    sdy += dy * dy
        mxx /= safe
        myy /= safe
        mxy /= safe
        tr = mxx + myy
        st = 0.0
        for i in range(p):
            for j in range(p):
                if region[i, j]:
                    dx = j - cx
                    dy = i - cy
                    e = dx * dx + dy * dy - tr
                    st += e * e
        sig = (sigma[k] if ok else 0.0) / safe
        if ok:
            centroid[k, 0] = cx
            centroid[k, 1] = cy
            centroid_std[k, 0] = sig * np.sqrt(sdx)
            centroid_std[k, 1] = sig * np.sqrt(sdy)
            moments[k, 0] = mxx
            moments[k, 1] = myy
            moments[k, 2] = mxy
            trace_std[k] = sig * np.sqrt(st)
            status_out[k] = 2 if edge else 0
        else:
            centroid[k, 0] = np.nan
            centroid[k, 1] = np.nan
            centroid_std[k, 0] = np.nan
            centroid_std[k, 1] = np.nan
            moments[k, 0] = np.nan
            moments[k, 1] = np.nan
            moments[k, 2] = np.nan
            trace_std[k] = np.nan
            status_out[k] = 1
        for i in range(p):
            for j in range(p):
                region_out[k, i, j] = region[i, j] and ok
                if zero_outside and not region_out[k, i, j]:
                    hz[i, j] = 0.0


OFFSET_I = 1 << 20  # added before truncating LCD coordinates (|index| << 2^20), exact in float64
OFFSET = float(OFFSET_I)


@numba.njit(cache=True, nogil=True)
def _nonzero_box(hk: np.ndarray) -> tuple[int, int, int, int]:
    """Columns and rows (cmin, cmax, rmin, rmax) spanned by a window's nonzero weights
    (cmax = -1: none)."""
    p = hk.shape[0]
    cmin, cmax, rmin, rmax = p, -1, p, -1
    for r in range(p):
        for c in range(hk.shape[1]):
            if hk[r, c] != 0.0:
                cmin, cmax = min(cmin, c), max(cmax, c)
                rmin, rmax = min(rmin, r), max(rmax, r)
    return cmin, cmax, rmin, rmax


@numba.njit(cache=True, nogil=True)
def resample_kernel(h: np.ndarray, origin: np.ndarray, ray_d: np.ndarray, ray_c: np.ndarray,
                    inv: np.ndarray, box: np.ndarray, ptx: np.ndarray, pty: np.ndarray,
                    pitch_mm: float, g: int, sub: int, cell_area: float, rot: np.ndarray,
                    first: float, pts_cam_step: float, out: np.ndarray) -> None:
    """out[k] (G, G) += masses of window h[k] (P, P) (see ``aperture.resample``): sub-cell
    centres ptx, pty ((G sub)^2,) station-frame mm, ``p_station = R2^T p_cam`` with
    rot = R2; the camera-frame sub-cell centres are ``first + i pts_cam_step`` along each
    axis; inv (n,) = 1 / ratio; box (n,) the LCD pixel's area on the aperture plane."""
    n, p = h.shape[0], h.shape[-1]
    gs = g * sub
    norm = 1.0 / (sub * sub)
    sc = pts_cam_step  # sub-cell pitch, mm
    colb = np.empty(gs)
    rowb = np.empty(gs)
    cell = np.arange(gs) // sub  # output cell of each sub-cell index (no division per point)
    for k in range(n):
        ox, oy = origin[k, 0], origin[k, 1]
        # the window's nonzero weights: only sub-cells that can land on them are visited
        # (the others add 0); their box, mapped back to the aperture, bounds the loop
        cmin, cmax, rmin, rmax = _nonzero_box(h[k])
        if cmax < 0:
            continue
        s_k = 1.0 / inv[k]
        xa = ray_c[k, 0] + ((cmin + ox - 0.5) * pitch_mm - ray_d[k, 0]) * s_k
        xb = ray_c[k, 0] + ((cmax + 1 + ox - 0.5) * pitch_mm - ray_d[k, 0]) * s_k
        ya = ray_c[k, 1] + ((rmin + oy - 0.5) * pitch_mm - ray_d[k, 1]) * s_k
        yb = ray_c[k, 1] + ((rmax + 1 + oy - 0.5) * pitch_mm - ray_d[k, 1]) * s_k
        # station-frame box -> camera frame (p_cam = R2 p_station): bounding box of corners
        umin, umax, vmin, vmax = np.inf, -np.inf, np.inf, -np.inf
        for xs in (xa, xb):
            for ys in (ya, yb):
                u = rot[0, 0] * xs + rot[0, 1] * ys
                v = rot[1, 0] * xs + rot[1, 1] * ys
                umin, umax = min(umin, u), max(umax, u)
                vmin, vmax = min(vmin, v), max(vmax, v)
        b0 = max(0, int(np.floor((umin - first) / sc)) - 2)
        b1 = min(gs, int(np.ceil((umax - first) / sc)) + 3)
        a0 = max(0, int(np.floor((vmin - first) / sc)) - 2)
        a1 = min(gs, int(np.ceil((vmax - first) / sc)) + 3)
        # LCD column and row (+ 0.5) are affine in the camera-frame sub-cell indices (a, b):
        # p_station = R2^T p_cam, so col = ccol + ca a + cb b (likewise row)
        ax, ay = inv[k] / pitch_mm, inv[k] / pitch_mm
        bx = (ray_d[k, 0] - ray_c[k, 0] * inv[k]) / pitch_mm + 0.5
        by = (ray_d[k, 1] - ray_c[k, 1] * inv[k]) / pitch_mm + 0.5
        hb = 1.0 / box[k] * norm
        for b in range(b0, b1):
            xb = first + b * sc
            colb[b] = rot[0, 0] * xb * ax + OFFSET
            rowb[b] = rot[0, 1] * xb * ay + OFFSET
        for a in range(a0, a1):
            ya = first + a * sc
            cya = rot[1, 0] * ya * ax + bx
            rya = rot[1, 1] * ya * ay + by
            oa = out[k, a // sub]
            hk = h[k]
            for b in range(b0, b1):
                # floor by truncation of a positive number (OFFSET >> any LCD index)
                col = np.int64(colb[b] + cya) - OFFSET_I - ox
                row = np.int64(rowb[b] + rya) - OFFSET_I - oy
                if 0 <= col < p and 0 <= row < p:
                    oa[cell[b]] += hk[row, col] * hb
        for a in range(g):
            for b in range(g):
                out[k, a, b] *= cell_area


@numba.njit(cache=True, nogil=True)
def moments_kernel(mass: np.ndarray, centres: np.ndarray, mean: np.ndarray,
                   cov: np.ndarray) -> None:
    """Mean (n, 2) and covariance (n, 2, 2) of grid masses (n, G, G) normalised per node,
    cell centres ``centres`` (G,) mm along both axes (see ``aperture.grid_moments``)."""
    n, g = mass.shape[0], mass.shape[1]
    for k in range(n):
        tot = 0.0
        for a in range(g):
            for b in range(g):
                tot += mass[k, a, b]
        if tot <= 0:
            tot = 1.0
        mx = 0.0
        my = 0.0
        for a in range(g):
            for b in range(g):
                q = mass[k, a, b] / tot
                mx += q * centres[b]
                my += q * centres[a]
        sxx = 0.0
        syy = 0.0
        sxy = 0.0
        for a in range(g):
            dy = centres[a] - my
            for b in range(g):
                q = mass[k, a, b] / tot
                dx = centres[b] - mx
                sxx += q * dx * dx
                syy += q * dy * dy
                sxy += q * dx * dy
        mean[k, 0], mean[k, 1] = mx, my
        cov[k, 0, 0], cov[k, 1, 1] = sxx, syy
        cov[k, 0, 1], cov[k, 1, 0] = sxy, sxy


@numba.njit(cache=True, nogil=True)
def resample_zoned_kernel(h: np.ndarray, origin: np.ndarray, ray_d: np.ndarray,
                          ray_c: np.ndarray, g0: float, g2: float, r2_rim: float,
                          pitch_mm: float, g: int, sub: int, cell_area: float, rot: np.ndarray,
                          first: float, step: float, out: np.ndarray) -> None:
    """out[k] (G, G) += masses of window h[k] (P, P) through the radial map of a lens with a
    focus per pupil zone (``aperture.resample`` with ``g2_per_mm2``): the camera-frame aperture
    point p (radius rho from the optical centre) lands on the LCD at
    ``q = ray_d + R2^T p g(rho) - ray_c g(|ray_c|)``, ``g(rho) = g0 + g2 min(rho^2, r2_rim)``
    (beyond the pupil's rim, where only blur lands, the rim's scale), and carries the LCD
    density times the map's Jacobian ``|g (g + 2 g2 rho^2)| / pitch^2`` (``g^2`` beyond the
    rim). With ``g2 = 0`` it is ``resample_kernel``'s affine map (``g0 = 1 / ratio``).
    ``first`` and ``step``: the camera-frame sub-cell centres along each axis, mm."""
    n, p = h.shape[0], h.shape[-1]
    gs = g * sub
    norm = 1.0 / (sub * sub) / (pitch_mm * pitch_mm)
    # g is monotonic in rho^2, and the caller rules out a fold (a sign change) in the pupil
    gmin = max(min(abs(g0), abs(g0 + g2 * r2_rim)), 1e-9)
    for k in range(n):
        ox, oy = origin[k, 0], origin[k, 1]
        cmin, cmax, rmin, rmax = _nonzero_box(h[k])
        if cmax < 0:
            continue
        rc2 = min(ray_c[k, 0] ** 2 + ray_c[k, 1] ** 2, r2_rim)
        gc = g0 + g2 * rc2
        sx = ray_d[k, 0] - ray_c[k, 0] * gc  # LCD point of the aperture's origin, mm
        sy = ray_d[k, 1] - ray_c[k, 1] * gc
        # the window's nonzero box bounds |p| g(rho): a disk of radius reach on the grid
        dx = max(abs((cmin + ox - 0.5) * pitch_mm - sx), abs((cmax + 1 + ox - 0.5) * pitch_mm - sx))
        dy = max(abs((rmin + oy - 0.5) * pitch_mm - sy), abs((rmax + 1 + oy - 0.5) * pitch_mm - sy))
        reach = min(np.sqrt(dx * dx + dy * dy) / gmin, 2.0 * gs * step)
        i0 = max(0, int(np.floor((-reach - first) / step)) - 1)
        i1 = min(gs, int(np.ceil((reach - first) / step)) + 2)
        hk = h[k]
        for a in range(i0, i1):
            y = first + a * step
            oa = out[k, a // sub]
            for b in range(i0, i1):
                x = first + b * step
                rr = x * x + y * y
                r2 = min(rr, r2_rim)
                gg = g0 + g2 * r2
                qx = sx + (rot[0, 0] * x + rot[1, 0] * y) * gg
                qy = sy + (rot[0, 1] * x + rot[1, 1] * y) * gg
                col = np.int64(qx / pitch_mm + 0.5 + OFFSET) - OFFSET_I - ox
                row = np.int64(qy / pitch_mm + 0.5 + OFFSET) - OFFSET_I - oy
                if 0 <= col < p and 0 <= row < p:
                    jac = gg * gg if rr >= r2_rim else gg * (gg + 2.0 * g2 * r2)
                    oa[b // sub] += hk[row, col] * abs(jac) * norm
        for a in range(g):
            for b in range(g):
                out[k, a, b] *= cell_area
