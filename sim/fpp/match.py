"""Stereo matching by equal projector coordinate along rectified rows: the coarse row search
(``match_row``), the local phase model of each pixel's 3 x 3 stencil (``local_phase_model``)
and the sub-pixel Newton search on it, left-right consistency, and the per-pixel phase noise
(``phase_noise_px``). The method is described in :mod:`sim.fpp.stereo`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from sim.fpp.rectify import (
    _cubic_weights,
    _rectified_to_pixel,
    _to_rectified,
    rectify_map,
    sample_image,
)
from sim.optics.rig import DeviceCalibration
from sim.tolerances import MODEL_RESIDUAL_FLOOR_PX, STEREO_STEP


def _refine_cubic(key: np.ndarray, k: np.ndarray, t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Newton refinement of the crossing ``t`` in [0, 1] of interval ``k`` of the monotone
    values ``key`` on the cubic through ``key[k-1 .. k+2]`` (linear ``t`` where it is absent)."""
    has = (k >= 1) & (k + 2 <= len(key) - 1)
    kk = np.clip(k, 1, max(len(key) - 3, 1))
    if len(key) < 4 or not has.any():
        return t
    nodes = np.stack([key[kk - 1], key[kk], key[kk + 1], key[kk + 2]], axis=1)
    tt = t.copy()
    for _ in range(4):
        f = np.sum(_cubic_weights(tt) * nodes, axis=1) - q
        eps = STEREO_STEP
        df = (np.sum(_cubic_weights(tt + eps) * nodes, axis=1) - q - f) / eps
        tt = np.clip(tt - f / np.where(df > 0, df, np.inf), 0.0, 1.0)
    return np.where(has, tt, t)


def match_row(
    left: np.ndarray, right: np.ndarray, order: int = 3
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Sub-pixel positions in ``right`` (W_r,) where it takes each value of ``left`` (W_l,).

    The right row is split into monotone runs of finite values; inside a run the crossing is
    found by binary search and refined by linear (``order=1``) or cubic Lagrange (``order=3``,
    over the 4 values around the crossing) interpolation. Returns one ``(j_left, x_right)``
    pair of arrays per run (``x_right`` in right-row index units).
    """
    out: list[tuple[np.ndarray, np.ndarray]] = []
    jl = np.flatnonzero(np.isfinite(left))
    if len(jl) == 0:
        return out
    q = left[jl]
    step = np.diff(right)
    slope = np.sign(step)
    usable = np.flatnonzero(np.isfinite(step) & (slope != 0))
    if len(usable) == 0:
        return out
    cut = np.flatnonzero((np.diff(usable) != 1) | (np.diff(slope[usable]) != 0)) + 1
    for run in np.split(usable, cut):
        s, e = int(run[0]), int(run[-1]) + 1  # monotone values right[s..e]
        vals = right[s : e + 1]
        sign = slope[s]
        key = vals if sign > 0 else -vals  # ascending either way
        qq = q if sign > 0 else -q
        k = np.searchsorted(key, qq, side="right") - 1
        k = np.where(qq == key[-1], len(key) - 2, k)
        ok = (k >= 0) & (k <= len(key) - 2)
        k = k[ok]
        t = (qq[ok] - key[k]) / (key[k + 1] - key[k])
        if order == 3:
            t = _refine_cubic(key, k, t, qq[ok])
        out.append((jl[ok], s + k + t))
    return out


MODEL_RADIUS = 1
"""Half-width (px) of the stencil of the local phase model: (2 r + 1)^2 pixels."""
MODEL_DEGREE = 2
"""Total degree of the local phase model's 2-D polynomial."""
_POWERS = np.array([(i, d - i) for d in range(MODEL_DEGREE + 1) for i in range(d, -1, -1)])
_OFFSETS = np.array([(dx, dy) for dy in range(-MODEL_RADIUS, MODEL_RADIUS + 1)
                     for dx in range(-MODEL_RADIUS, MODEL_RADIUS + 1)], dtype=np.float64)


def _basis(dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Monomials ``dx^i dy^j`` (..., m), ``i + j <= MODEL_DEGREE``, of the local phase model."""
    dx, dy = np.asarray(dx, dtype=np.float64), np.asarray(dy, dtype=np.float64)
    return np.stack([dx**i * dy**j for i, j in _POWERS], axis=-1)


def _basis_grad(dx: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Derivatives (..., m) of ``_basis`` along dx and dy."""
    gx = np.stack([i * dx ** max(i - 1, 0) * dy**j for i, j in _POWERS], axis=-1)
    gy = np.stack([j * dx**i * dy ** max(j - 1, 0) for i, j in _POWERS], axis=-1)
    return gx, gy


MEDIAN_CHI_RATIO = {d: float(np.sqrt(chi2.median(d) / d)) for d in range(1, 64)}
"""Median over mean of a chi distribution with d degrees of freedom, as RMS ratio."""
_PINV = np.linalg.pinv(_basis(_OFFSETS[:, 0], _OFFSETS[:, 1]))  # (m, stencil)


def local_phase_model(coord: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares polynomial (``MODEL_DEGREE``) of ``coord`` (H, W) over the stencil of
    ``(2 MODEL_RADIUS + 1)^2`` pixels centred on every pixel: coefficients (H, W, m) of
    ``_basis`` in pixel offsets from that pixel, and the fit's RMS residual (H, W), both NaN
    where a stencil pixel is NaN or outside the image."""
    c = np.asarray(coord, dtype=np.float64)
    h, w = c.shape
    r = MODEL_RADIUS
    pad = np.pad(c, r, constant_values=np.nan)
    vals = np.stack([pad[r + dy : r + dy + h, r + dx : r + dx + w] for dx, dy in
                     _OFFSETS.astype(int)], axis=-1)  # (H, W, stencil)
    coef = vals @ _PINV.T
    fit = coef @ _basis(_OFFSETS[:, 0], _OFFSETS[:, 1]).T
    return coef, np.sqrt(np.mean((vals - fit) ** 2, axis=-1))


@dataclass(frozen=True)
class _Side:
    """One camera of the pair in the rectified frame: map, rectification, local phase model."""

    coord: np.ndarray
    cam: DeviceCalibration
    r: np.ndarray
    p: np.ndarray
    cols: tuple[int, int]
    coef: np.ndarray
    residual: np.ndarray


def _model_at(side: _Side, uv: np.ndarray, node: np.ndarray, duv: np.ndarray, q: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The local phase model of the pixels ``node`` (n, 2) of ``side`` at the original pixel
    positions ``uv`` (n, 2), minus ``q`` (n,); its slope along the row (n,) (projector px per
    rectified px, the row running ``duv`` (n, 2) original px per rectified px); whether the
    node is inside the image (n,)."""
    h, w = side.coord.shape
    inside = (node[:, 0] >= 0) & (node[:, 0] < w) & (node[:, 1] >= 0) & (node[:, 1] < h)
    nu = np.clip(node[:, 0], 0, w - 1).astype(np.int64)
    nv = np.clip(node[:, 1], 0, h - 1).astype(np.int64)
    c = side.coef[nv, nu]
    d = uv - node
    f = np.sum(c * _basis(d[:, 0], d[:, 1]), axis=1) - q
    gx, gy = _basis_grad(d[:, 0], d[:, 1])
    df = np.sum(c * gx, axis=1) * duv[:, 0] + np.sum(c * gy, axis=1) * duv[:, 1]
    return f, df, inside


def _refine(side: _Side, x: np.ndarray, y: np.ndarray, q: np.ndarray, iterations: int = 5
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Newton search along the rectified rows ``y`` (n,) of ``side`` for the rectified column
    where its local phase model equals ``q`` (n,), from ``x`` (n,): the column, the original
    pixel there (n, 2), whether it converged inside the stencil of a valid model with a
    non-zero slope along the row, and that slope (n,) (projector px per rectified px).

    Each step uses the model of the pixel nearest the current position. Neighbouring pixels'
    models differ at their common cell edge by what a quadratic cannot follow, so the
    piecewise model can step over ``q`` there: Newton then alternates between the two pixels
    with no root in either cell, and the match is the cell edge (``_cell_edge_root``)."""
    ok = np.ones(len(x), dtype=bool)
    step = 1e-3  # rectified px, finite difference of the row's mapping into the image
    uv = _rectified_to_pixel(np.stack([x, y], axis=1), side.cam, side.r, side.p)
    duv = (_rectified_to_pixel(np.stack([x + step, y], axis=1), side.cam, side.r, side.p) - uv) / step
    x_prev, node_prev = x, np.round(uv)
    for it in range(iterations + 1):
        if it:
            uv = _rectified_to_pixel(np.stack([x, y], axis=1), side.cam, side.r, side.p)
        node = np.round(uv)
        f, df, inside = _model_at(side, uv, node, duv, q)
        ok &= inside & np.isfinite(f) & np.isfinite(df) & (df != 0)
        if it == iterations:
            break
        x_prev, node_prev = x, node
        x = np.where(ok, x - np.clip(f / np.where(ok, df, 1.0), -1.0, 1.0), x)
    # converged: the phase matches to a millionth of a pixel's worth of slope
    converged = np.abs(f) <= 1e-6 * np.abs(df) + 1e-12 * np.maximum(1.0, np.abs(q))
    edge = ok & ~converged & np.any(node != node_prev, axis=1)
    if edge.any():
        xe, uve, oke, dfe = _cell_edge_root(side, x_prev[edge], node_prev[edge], x[edge],
                                            node[edge], y[edge], duv[edge], q[edge])
        sel = np.flatnonzero(edge)[oke]
        x, uv, df = x.copy(), uv.copy(), df.copy()
        x[sel], uv[sel], df[sel] = xe[oke], uve[oke], dfe[oke]
        converged[sel] = True
    return x, uv, ok & converged, df


def _cell_edge_root(side: _Side, xa: np.ndarray, node_a: np.ndarray, xb: np.ndarray,
                    node_b: np.ndarray, y: np.ndarray, duv: np.ndarray, q: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where the rectified rows ``y`` (n,) leave the cell of pixels ``node_a`` (n, 2) (column
    ``xa``) for the neighbouring cell of ``node_b`` (column ``xb``), found by bisection: the
    column (n,), the original pixel there (n, 2), whether the two pixels' models there lie on
    either side of ``q`` with slopes of one sign (the piecewise model crosses ``q`` at the
    edge), and their mean slope (n,)."""
    lo, hi = xa.copy(), xb.copy()
    for _ in range(48):  # to below 1e-12 of the (at most 1 px) step
        mid = (lo + hi) / 2
        uv = _rectified_to_pixel(np.stack([mid, y], axis=1), side.cam, side.r, side.p)
        in_a = np.all(np.round(uv) == node_a, axis=1)
        lo, hi = np.where(in_a, mid, lo), np.where(in_a, hi, mid)
    uv = _rectified_to_pixel(np.stack([hi, y], axis=1), side.cam, side.r, side.p)
    fa, dfa, _ = _model_at(side, uv, node_a, duv, q)
    fb, dfb, _ = _model_at(side, uv, node_b, duv, q)
    ok = (np.all(np.round(uv) == node_b, axis=1) & (fa * fb <= 0) & (dfa * dfb > 0)
          & np.isfinite(fa * fb))
    return hi, uv, ok, (dfa + dfb) / 2


def _match_direction(ref: _Side, srch: _Side, rows: tuple[int, int], order: int,
                     ref_ok: np.ndarray) -> tuple[np.ndarray, ...]:
    """Every candidate match of the reference camera's pixels ``ref_ok`` (H, W) bool in the
    search camera: reference pixel indices (n,) (flat), rectified ``xy_ref`` (n, 2),
    rectified search column (n,), search pixel (n, 2), and the slope of the search camera's
    phase along the row there (n,) (projector px per rectified px)."""
    vv, uu = np.nonzero(ref_ok)
    q = ref.coord[vv, uu]
    xy = _to_rectified(np.stack([uu, vv], axis=1).astype(np.float64), ref.cam, ref.r, ref.p)
    row = np.round(xy[:, 1]).astype(np.int64) - rows[0]
    keep = (row >= 0) & (row <= rows[1] - rows[0])
    mu, mv = rectify_map(srch.cam, srch.r, srch.p, srch.cols, rows)
    grid = sample_image(srch.coord, mu, mv, order)  # coarse search only
    idx_all, x_all = [], []
    sel = np.flatnonzero(keep)
    order_rows = sel[np.argsort(row[sel], kind="stable")]
    bounds = np.searchsorted(row[order_rows], np.arange(grid.shape[0] + 1))
    for i in range(grid.shape[0]):
        mine = order_rows[bounds[i] : bounds[i + 1]]
        if len(mine) == 0:
            continue
        for j, xr in match_row(q[mine], grid[i], 1):
            idx_all.append(mine[j])
            x_all.append(srch.cols[0] + xr)
    if not idx_all:
        return (np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0), np.zeros((0, 2)), np.zeros(0))
    k = np.concatenate(idx_all)
    x0 = np.concatenate(x_all)
    x, uv, ok, slope = _refine(srch, x0, xy[k, 1], q[k])
    k, x, uv, slope = k[ok], x[ok], uv[ok], slope[ok]
    flat = vv[k] * ref.coord.shape[1] + uu[k]
    return flat, xy[k], x, uv, slope


def _lr_consistent(uv_match: np.ndarray, ref_pix: np.ndarray, back: np.ndarray, tol_px: float
                   ) -> np.ndarray:
    """Left-right check: the other direction's matches ``back`` (H_s, W_s, 2) (NaN where none),
    interpolated at ``uv_match`` (n, 2), must land within ``tol_px`` of ``ref_pix``.

    Bilinear over the 4 pixels around the match where all have a match; where some lack one
    (the edge of what the other direction matched), the affine least-squares fit to the
    matches among the 4 x 4 pixels around it, if at least one of the 4 and three not on one
    line have one (docs/decisions/0056-stereo-matcher-keeps-edges.md)."""
    h, w = back.shape[:2]
    u0, v0 = np.floor(uv_match[:, 0]), np.floor(uv_match[:, 1])
    inside = (u0 >= 0) & (v0 >= 0) & (u0 + 1 <= w - 1) & (v0 + 1 <= h - 1)
    iu = np.where(inside, u0, 0).astype(np.int64)
    iv = np.where(inside, v0, 0).astype(np.int64)
    fu, fv = (uv_match[:, 0] - u0)[:, None], (uv_match[:, 1] - v0)[:, None]
    pred = ((1 - fv) * ((1 - fu) * back[iv, iu] + fu * back[iv, iu + 1])
            + fv * ((1 - fu) * back[iv + 1, iu] + fu * back[iv + 1, iu + 1]))
    near = np.isfinite(back[..., 0])
    some = (near[iv, iu] | near[iv, iu + 1] | near[iv + 1, iu] | near[iv + 1, iu + 1]) & inside
    partial = some & ~np.isfinite(pred[:, 0])
    if partial.any():
        pred[partial] = _affine_at(back, uv_match[partial], iu[partial], iv[partial])
    err = np.linalg.norm(pred - ref_pix, axis=1)
    return inside & (err <= tol_px)  # NaN (no fit) fails


def _affine_at(back: np.ndarray, uv: np.ndarray, iu: np.ndarray, iv: np.ndarray) -> np.ndarray:
    """The affine least-squares fit (n, 2) to the finite values of ``back`` (H, W, 2) on the
    4 x 4 pixels ``iu - 1 .. iu + 2``, ``iv - 1 .. iv + 2`` (n,), evaluated at ``uv`` (n, 2);
    NaN where fewer than three of them, or only ones on one line, are finite."""
    h, w = back.shape[:2]
    d = np.arange(-1, 3)
    cu = iu[:, None, None] + d[None, None, :]  # (n, 1, 4)
    cv = iv[:, None, None] + d[None, :, None]  # (n, 4, 1)
    cu, cv = np.broadcast_to(cu, (len(iu), 4, 4)), np.broadcast_to(cv, (len(iu), 4, 4))
    inside = (cu >= 0) & (cu < w) & (cv >= 0) & (cv < h)
    vals = back[np.clip(cv, 0, h - 1), np.clip(cu, 0, w - 1)].reshape(len(iu), 16, 2)
    use = (inside.reshape(len(iu), 16) & np.isfinite(vals[..., 0]))[..., None]
    # design in offsets from the query point: the fit's constant is the value there
    a = np.stack([np.ones(cu.shape), cu - uv[:, 0, None, None], cv - uv[:, 1, None, None]],
                 axis=-1).reshape(len(iu), 16, 3) * use
    ata = np.einsum("nki,nkj->nij", a, a)
    atb = np.einsum("nki,nkj->nij", a, np.where(use, vals, 0.0))
    # three non-collinear cells of the unit grid give det >= 1; collinear ones give 0
    good = np.linalg.det(ata) > 0.5
    out = np.full((len(iu), 2), np.nan)
    if good.any():
        out[good] = np.linalg.solve(ata[good], atb[good])[:, 0, :]
    return out


def usable_pixels(residual: np.ndarray, max_model_residual: float) -> np.ndarray:
    """Pixels (H, W) bool whose local phase model exists and fits within ``max_model_residual``
    times the camera's median residual (or ``MODEL_RESIDUAL_FLOOR_PX``, whichever is larger)."""
    fine = np.isfinite(residual)
    if not fine.any():
        return fine
    limit = max(max_model_residual * float(np.median(residual[fine])), MODEL_RESIDUAL_FLOOR_PX)
    return fine & (residual <= limit)


def pixel_footprint_correction(coord: np.ndarray, modulation: np.ndarray, variance_px2: float
                               ) -> np.ndarray:
    """Projector coordinate (H, W) at the pixel centres, from one measured by pixels that
    average the light over their area (second moment ``variance_px2`` per axis, px^2; 1/12 for
    a full square pixel).

    Averaging ``B (1 + b.x) exp(i (phi + g.x + x.C.x / 2))`` over the pixel shifts the phase by
    ``var (b.g + trace(C) / 2)`` to second order: the fringe amplitude's relative gradient ``b``
    (from ``modulation`` (H, W) of the finest fringes) times the phase gradient ``g``, and half
    the phase curvature. Both come from local quadratic models (``local_phase_model``) of the
    coordinate and of ``ln B``; the shift is subtracted. NaN where either model is missing."""
    coef, _ = local_phase_model(coord)
    b = np.asarray(modulation, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        lnb, _ = local_phase_model(np.where(np.isfinite(coord) & (b > 0), np.log(b), np.nan))
    shift = variance_px2 * (lnb[..., 1] * coef[..., 1] + lnb[..., 2] * coef[..., 2]
                            + coef[..., 3] + coef[..., 5])
    return coord - shift


def phase_noise_px(residual: np.ndarray, modulation: np.ndarray | None = None) -> np.ndarray:
    """Standard deviation (H, W) of a projector-coordinate map's random error, projector px,
    from its local phase model's residuals (H, W) (``local_phase_model``): the residual of
    a least-squares fit of m coefficients to s samples has ``E[rms^2] = sigma^2 (s - m) / s``;
    the camera's median gives sigma, scaled per pixel by ``sqrt(median(B) / B)`` where the
    fringe modulation B (H, W) is given (shot-noise-limited phase noise goes as
    ``sqrt(A) / B``, and A as B for a given fringe contrast)."""
    fine = np.isfinite(residual)
    if not fine.any():
        return np.full(np.shape(residual), np.nan)
    s, m = len(_OFFSETS), len(_POWERS)
    sigma = float(np.median(residual[fine])) * np.sqrt(s / (s - m)) / MEDIAN_CHI_RATIO[s - m]
    if modulation is None:
        return np.full(np.shape(residual), sigma)
    b = np.asarray(modulation, dtype=np.float64)
    ref = float(np.median(b[fine & (b > 0)])) if np.any(fine & (b > 0)) else 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(b > 0, sigma * np.sqrt(ref / b), np.inf)


def _masked(side: _Side, usable: np.ndarray) -> _Side:
    """``side`` with its model coefficients NaN outside ``usable`` (H, W) bool."""
    coef = np.where(usable[..., None], side.coef, np.nan)
    return _Side(side.coord, side.cam, side.r, side.p, side.cols, coef, side.residual)
