"""Compiled (numba) kernels that draw and deblur the aperture samples: ``rings_kernel`` and
``lloyd_kernel`` draw K aperture samples (``aperture.ring_samples``; its two sorts by
``stable_argsort``, numpy's stable mergesort's permutation by radix);
``richardson_lucy_kernel`` is ``aperture.deblur``'s deconvolution."""

from __future__ import annotations

import numba
import numpy as np


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
