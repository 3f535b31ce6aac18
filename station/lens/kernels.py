"""Compiled (numba) kernels of the lens derivation: the same formulas as the numpy reference
code they replace (``station.lens.centroids.window_stats``, ``station.lens.aperture.resample``),
one window or node at a time so nothing grows with the batch.

``stats_kernel`` computes what ``window_stats`` documents (3 x 3 box smoothing, the
8-connected region above the threshold that holds the smoothed peak, grown by a disk of
radius ``REGION_MARGIN_PX + 0.5``; centroid, moments and their noise); only the order of
floating-point sums differs from the numpy version (tests compare them within 1e-12).
``resample_kernel`` is ``aperture.resample`` (nearest LCD pixel at each sub-cell centre).
``rings_kernel`` and ``lloyd_kernel`` draw K aperture samples (``aperture.ring_samples``;
its two sorts by ``stable_argsort``, numpy's stable mergesort's permutation by radix);
``moments_kernel`` is ``aperture.grid_moments``.
"""

from __future__ import annotations

import numba
import numpy as np


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
def stable_argsort(keys: np.ndarray, n: int, work_f: np.ndarray, u: np.ndarray, u2: np.ndarray,
                   order: np.ndarray, order2: np.ndarray,
                   count: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """The indices of ``keys[:n]`` (float64, no NaN) in ascending order, equal keys in index
    order: ``np.argsort(keys[:n], kind="mergesort")``, by a least-significant-digit radix sort
    of the keys' bits (8 bits a pass; a pass where every key has the same digit is skipped):
    with it the ring strata of ~900 cells took 48 instead of 98 us. -0.0 counts as +0.0 (as in
    a comparison). Scratch: work_f float64, u and u2 uint64, order and order2 int64, each at
    least n long, count int64 (256,); returns a view of ``order`` or ``order2``."""
    top = np.uint64(1) << np.uint64(63)
    for i in range(n):
        work_f[i] = keys[i] + 0.0  # -0.0 -> +0.0
    bits = work_f.view(np.uint64)
    for i in range(n):
        b = bits[i]
        u[i] = ~b if b & top else b | top  # the float order as unsigned integers
        order[i] = i
    mask = np.uint64(255)
    for shift in range(0, 64, 8):
        sh = np.uint64(shift)
        for d in range(256):
            count[d] = 0
        for i in range(n):
            count[(u[i] >> sh) & mask] += 1
        if n == 0 or count[(u[0] >> sh) & mask] == n:
            continue
        total = 0
        for d in range(256):
            c = count[d]
            count[d] = total
            total += c
        for i in range(n):
            d = (u[i] >> sh) & mask
            j = count[d]
            count[d] = j + 1
            u2[j] = u[i]
            order2[j] = order[i]
        u, u2 = u2, u
        order, order2 = order2, order
    return order[:n]


@numba.njit(cache=True, nogil=True)
def rings_kernel(mass: np.ndarray, centres: np.ndarray, mean: np.ndarray, white: np.ndarray,
                 counts: np.ndarray, offsets: np.ndarray, out_xy: np.ndarray,
                 out_w: np.ndarray) -> None:
    """Equal-mass polar strata of grid masses (n, G, G) (normalised, >= 0) about their mean
    (n, 2) in whitened coordinates (``white`` (n, 2, 2) = cov^-1/2): rings of mass
    counts[i] / K (cells sorted by whitened radius), each cut into counts[i] sectors of equal
    mass by whitened angle from ``offsets[i]`` (radians). A cell's mass is split where a
    boundary falls inside it. Writes each stratum's centroid (cell centres ``centres`` (G,)
    mm) to out_xy (n, K, 2) and its mass to out_w (n, K), ring by ring, sector by sector."""
    n, g = mass.shape[0], mass.shape[1]
    nr = len(counts)
    k = out_w.shape[1]
    ncell = g * g
    px = np.empty(ncell)
    py = np.empty(ncell)
    rad = np.empty(ncell)
    ang = np.empty(ncell)
    mm = np.empty(ncell)
    piece_cell = np.empty(ncell + nr, dtype=np.int64)
    piece_mass = np.empty(ncell + nr)
    piece_ring = np.empty(ncell + nr, dtype=np.int64)
    sort_f = np.empty(ncell + nr)  # the stable sort's scratch
    sort_u, sort_u2 = np.empty(ncell + nr, np.uint64), np.empty(ncell + nr, np.uint64)
    sort_o, sort_o2 = np.empty(ncell + nr, np.int64), np.empty(ncell + nr, np.int64)
    sort_count = np.empty(256, np.int64)
    ks = np.empty(ncell + nr)
    for m in range(n):
        na = 0
        for a in range(g):
            for b in range(g):
                v = mass[m, a, b]
                if v > 0:
                    x, y = centres[b], centres[a]
                    dx, dy = x - mean[m, 0], y - mean[m, 1]
                    zx = white[m, 0, 0] * dx + white[m, 0, 1] * dy
                    zy = white[m, 1, 0] * dx + white[m, 1, 1] * dy
                    px[na], py[na], mm[na] = x, y, v
                    rad[na] = zx * zx + zy * zy
                    ang[na] = np.arctan2(zy, zx)
                    na += 1
        order = stable_argsort(rad, na, sort_f, sort_u, sort_u2, sort_o, sort_o2, sort_count)
        # rings: walk the cells outwards, cutting at cumulative masses sum(counts[:i+1]) / K
        np_ = 0
        ring = 0
        cum_count = counts[0]
        target = cum_count / k
        acc = 0.0
        for t in range(na):
            c = order[t]
            left = mm[c]
            while left > 0:
                room = target - acc if ring < nr - 1 else left
                take = min(left, room)
                if take > 0:
                    piece_cell[np_], piece_mass[np_], piece_ring[np_] = c, take, ring
                    np_ += 1
                    acc += take
                    left -= take
                if left > 0 and ring < nr - 1:
                    ring += 1
                    cum_count += counts[ring]
                    target = cum_count / k
        # sectors: within each ring (its pieces are contiguous: the walk went outwards), by
        # angle from the ring's offset
        first = 0
        q0 = 0
        for r in range(nr):
            q1 = q0
            while q1 < np_ and piece_ring[q1] == r:
                q1 += 1
            ns = q1 - q0
            tot = 0.0
            for t in range(ns):
                q = q0 + t
                a2 = ang[piece_cell[q]] - offsets[r]
                ks[t] = a2 - 2 * np.pi * np.floor(a2 / (2 * np.pi))
                tot += piece_mass[q]
            cnt = counts[r]
            for j in range(cnt):
                out_w[m, first + j] = 0.0
                out_xy[m, first + j, 0] = mean[m, 0]
                out_xy[m, first + j, 1] = mean[m, 1]
            if ns == 0:
                first += cnt
                q0 = q1
                continue
            so = stable_argsort(ks, ns, sort_f, sort_u, sort_u2, sort_o, sort_o2, sort_count)
            sec = 0
            sec_target = tot / cnt
            acc = 0.0
            sx = 0.0
            sy = 0.0
            for t in range(ns):
                q = q0 + so[t]
                c = piece_cell[q]
                left = piece_mass[q]
                while left > 0:
                    room = sec_target - acc if sec < cnt - 1 else left
                    take = min(left, room)
                    if take > 0:
                        acc += take
                        sx += take * px[c]
                        sy += take * py[c]
                        out_w[m, first + sec] += take
                        left -= take
                    if left > 0 and sec < cnt - 1:
                        w = out_w[m, first + sec]
                        if w > 0:
                            out_xy[m, first + sec, 0] = sx / w
                            out_xy[m, first + sec, 1] = sy / w
                        sec += 1
                        sec_target = tot * (sec + 1) / cnt
                        sx = 0.0
                        sy = 0.0
            w = out_w[m, first + sec]
            if w > 0:
                out_xy[m, first + sec, 0] = sx / w
                out_xy[m, first + sec, 1] = sy / w
            first += cnt
            q0 = q1


@numba.njit(cache=True, nogil=True)
def lloyd_kernel(mass: np.ndarray, centres: np.ndarray, x: np.ndarray, w: np.ndarray,
                 iterations: int) -> None:
    """Weighted Lloyd (k-means) iterations from the samples x (n, K, 2) mm over the cells of
    grid masses (n, G, G) (normalised, >= 0; cell centres ``centres`` (G,) mm): each cell
    goes to its nearest sample, each sample moves to its cells' centroid (one without cells
    stays, weight 0); stops early when no cell changes sample. Writes x and the samples'
    masses w (n, K). Sample j stays sample j (its stratum moves, it is not renumbered)."""
    n, g = mass.shape[0], mass.shape[1]
    k = x.shape[1]
    ncell = g * g
    cx = np.empty(ncell)
    cy = np.empty(ncell)
    cm = np.empty(ncell)
    lab = np.empty(ncell, dtype=np.int64)
    nl = np.empty(ncell, dtype=np.int64)
    bd = np.empty(ncell)
    sx = np.empty(k)
    sy = np.empty(k)
    sw = np.empty(k)
    for m in range(n):
        na = 0
        for a in range(g):
            for b in range(g):
                v = mass[m, a, b]
                if v > 0:
                    cx[na], cy[na], cm[na] = centres[b], centres[a], v
                    lab[na] = -1
                    na += 1
        for it in range(iterations):
            # nearest sample of every cell, sample by sample over all cells (a loop the
            # compiler vectorises); strict < keeps the first nearest, as a per-cell scan does
            for c in range(na):
                bd[c] = np.inf
            for j in range(k):
                xj, yj = x[m, j, 0], x[m, j, 1]
                for c in range(na):
                    dx = cx[c] - xj
                    dy = cy[c] - yj
                    d = dx * dx + dy * dy
                    closer = d < bd[c]
                    bd[c] = d if closer else bd[c]
                    nl[c] = j if closer else nl[c]
            changed = False
            for j in range(k):
                sx[j] = 0.0
                sy[j] = 0.0
                sw[j] = 0.0
            for c in range(na):
                best = nl[c]
                if best != lab[c]:
                    changed = True
                    lab[c] = best
                sx[best] += cm[c] * cx[c]
                sy[best] += cm[c] * cy[c]
                sw[best] += cm[c]
            for j in range(k):
                w[m, j] = sw[j]
                if sw[j] > 0:
                    x[m, j, 0] = sx[j] / sw[j]
                    x[m, j, 1] = sy[j] / sw[j]
            if not changed:
                break


@numba.njit(cache=True, nogil=True)
def _mixed_blur(src: np.ndarray, w: np.ndarray, rows: np.ndarray, y0: int, y1: int, x0: int,
                x1: int, tmp: np.ndarray, out: np.ndarray) -> None:
    """out[y0:y1, x0:x1] = sum_i w[i] (rows[i] (x) rows[i]) * src over that box (src is 0
    outside it); rows (D, 2L+1) symmetric, zero taps and depths skipped."""
    half = rows.shape[1] // 2
    for y in range(y0, y1):
        for x in range(x0, x1):
            out[y, x] = 0.0
    for i in range(rows.shape[0]):
        if w[i] <= 0.0:
            continue
        for y in range(y0, y1):
            for x in range(x0, x1):
                a = 0.0
                for t in range(-half, half + 1):
                    c = rows[i, t + half]
                    if c != 0.0 and x0 <= x - t < x1:
                        a += c * src[y, x - t]
                tmp[y, x] = a
        for y in range(y0, y1):
            for x in range(x0, x1):
                a = 0.0
                for t in range(-half, half + 1):
                    c = rows[i, t + half]
                    if c != 0.0 and y0 <= y - t < y1:
                        a += c * tmp[y - t, x]
                out[y, x] += w[i] * a


@numba.njit(cache=True, nogil=True)
def richardson_lucy_kernel(d: np.ndarray, w: np.ndarray, rows: np.ndarray,
                           norm_rows: np.ndarray, iterations: int, x: np.ndarray) -> None:
    """``aperture.deblur``'s Richardson-Lucy steps, node by node: d (n, G, G) normalised
    non-negative data, w (n, D) weights, rows (D, 2L+1) the depths' 1-D blurs, norm_rows
    (D, G) each blur's mass falling on the grid; writes x (n, G, G). Only the bounding box of
    a node's data is computed (the estimate stays inside the data's support)."""
    n, g = d.shape[0], d.shape[1]
    model = np.zeros((g, g))
    tmp = np.zeros((g, g))
    acc = np.zeros((g, g))
    ratio = np.zeros((g, g))
    norm = np.zeros((g, g))
    for k in range(n):
        x[k] = d[k]
        y0, y1, x0, x1 = g, 0, g, 0
        for y in range(g):
            for c in range(g):
                if d[k, y, c] > 0.0:
                    y0, y1 = min(y0, y), max(y1, y + 1)
                    x0, x1 = min(x0, c), max(x1, c + 1)
        if y1 <= y0:
            continue
        for y in range(y0, y1):
            for c in range(x0, x1):
                a = 0.0
                for i in range(rows.shape[0]):
                    a += w[k, i] * norm_rows[i, y] * norm_rows[i, c]
                norm[y, c] = a if a > 1e-12 else 1.0
        for _ in range(iterations):
            _mixed_blur(x[k], w[k], rows, y0, y1, x0, x1, tmp, model)
            for y in range(y0, y1):
                for c in range(x0, x1):
                    m = model[y, c]
                    ratio[y, c] = d[k, y, c] / m if m > 1e-15 else 0.0
            _mixed_blur(ratio, w[k], rows, y0, y1, x0, x1, tmp, acc)
            for y in range(y0, y1):
                for c in range(x0, x1):
                    x[k, y, c] *= max(acc[y, c], 0.0) / norm[y, c]


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
