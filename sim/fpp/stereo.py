"""Stereo correspondence by equal projector coordinate along epipolar lines, and triangulation.

Method (``stereo_cloud``), for the maps of projector coordinate ``u_p`` (NaN = invalid) of two
cameras, each camera in turn the reference and the other the search camera:

1. ``cv2.stereoRectify`` gives the rectified frame (rows are epipolar lines).
2. Every valid reference pixel is used **at its own centre, with its own measured phase**: no
   interpolation on the reference side. Its rectified coordinates follow from the calibration
   (undistortion, rotation), exactly.
3. A coarse match: the search map resampled on the rectified grid (``interpolation_order``
   1 or 3, float64 maps as ``cv2.initUndistortRectifyMap``'s) is searched along the rectified
   row nearest the pixel's for every monotone run holding its phase (binary search).
4. The sub-pixel match is where a **local model of the search camera's phase** equals the
   reference phase, on the reference pixel's own epipolar line (its exact rectified row, mapped
   into the search image through the distortion): the model is the least-squares quadratic
   over the 3 x 3 original pixels around the nearest search pixel (``local_phase_model``),
   solved by Newton steps that re-centre on the nearest pixel. The coarse step only picks the
   run; the result does not depend on the interpolation order.
5. Triangulation in the rectified frame (``triangulate``, linear least squares as
   ``cv2.triangulatePoints``), then to the world frame.

Why it is unbiased. The reference phase is measured, not interpolated. The search model's
error is the part of the phase its quadratic cannot follow: third-order terms, which on the
symmetric 3 x 3 stencil are odd in the offset from the model's centre pixel, so their effect on
the matched position averages to zero over the offsets the pixels of a surface fall at (a
linear interpolation's error, in contrast, has one sign between nodes: ``-t (1 - t) phi'' / 2``,
and biased the diameter of a sphere by micrometres to tens of micrometres as the sphere spans
hundreds to tens of pixels). Running both directions puts both cameras' pixels in the cloud.

Consistency checks: a pixel is used only where its whole 3 x 3 stencil is valid and the
model's RMS residual is within ``max_model_residual`` times the camera's median (mixed pixels
at silhouettes, steep flanks, phase errors); the search runs must be monotone and the model's
slope along the row non-zero at the converged match, inside the centre pixel's cell; where a
row holds the phase more than once, the candidate whose point projects into the projector
closest to ``u_p`` wins (without a projector calibration such pixels are dropped), and points
further than ``max_projector_error_px`` are dropped; left-right: a match must be confirmed
by the other direction's matches (interpolated at the matched position) within
``max_lr_error_px``; continuity: a point whose 8 neighbours are not all reconstructed, or
whose range differs from one of theirs by more than ``max_range_step`` pixel footprints, is
dropped (silhouettes and the points a blurred silhouette leaves between two surfaces). A point
that cannot be made right is dropped, not kept wrong.

``camera_projector_cloud`` triangulates one camera against the projector (ray and the
projector's plane of constant coordinate, refined through the projector's distortion).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.stats import chi2

from sim.optics.projection import camera_to_world, project_points
from sim.optics.rig import DeviceCalibration
from sim.tolerances import MODEL_RESIDUAL_FLOOR_PX, STEREO_STEP

STEREO_SENSITIVITY_PX = 1e-3
"""Rectified px: the step of the finite difference that gives a stereo point's sensitivity."""


@dataclass(frozen=True)
class Rectification:
    """Rectified stereo geometry.

    R1, R2 : (3, 3) rotations from each camera's frame to its rectified frame.
    P1, P2 : (3, 4) projection matrices of the rectified cameras (rectified camera-1 frame).
    rows : (2,) int, first and last rectified row of the common grid.
    cols1, cols2 : (2,) int, first and last rectified column of each camera's grid.
    """

    R1: np.ndarray
    R2: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    rows: tuple[int, int]
    cols1: tuple[int, int]
    cols2: tuple[int, int]


@dataclass(frozen=True)
class PointCloud:
    """Points (n, 3) mm in the world frame, with optional unit normals (n, 3), quality (n,) and
    named per-point fields (n,) (e.g. ``camera``, ``u``, ``v``: the reference camera and its
    pixel; ``modulation``; ``phase_error``; ``uncertainty_mm``)."""

    points: np.ndarray
    normals: np.ndarray | None = None
    quality: np.ndarray | None = None
    fields: dict[str, np.ndarray] = field(default_factory=dict)


def relative_pose(cam1: DeviceCalibration, cam2: DeviceCalibration) -> tuple[np.ndarray, np.ndarray]:
    """``R, T`` taking camera-1 coordinates to camera-2 coordinates (OpenCV ``stereoCalibrate``)."""
    r = cam2.R_array @ cam1.R_array.T
    return r, cam2.T_array - r @ cam1.T_array


def _to_rectified(uv: np.ndarray, cam: DeviceCalibration, r: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Rectified pixel coordinates (n, 2) of original pixels (n, 2)."""
    xy = cam.normalized(uv)
    ray = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ r.T @ p[:, :3].T
    return ray[:, :2] / ray[:, 2:3]


def _bounds(valid: np.ndarray, cam: DeviceCalibration, r: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Rectified bounding box ``[[x0, y0], [x1, y1]]`` of the valid pixels (of those on the
    valid region's boundary: the rectification maps the region's inside inside)."""
    pad = np.pad(valid, 1, constant_values=False)
    inner = pad[:-2, 1:-1] & pad[2:, 1:-1] & pad[1:-1, :-2] & pad[1:-1, 2:]
    v, u = np.nonzero(valid & ~inner)
    xy = _to_rectified(np.stack([u, v], axis=1), cam, r, p)
    return np.stack([np.floor(xy.min(axis=0)) - 1, np.ceil(xy.max(axis=0)) + 1]).astype(int)


def stereo_rectification(
    cam1: DeviceCalibration, cam2: DeviceCalibration, valid1: np.ndarray, valid2: np.ndarray
) -> Rectification:
    """Rectify the pair (``cv2.stereoRectify``, zero disparity at infinity) and size a grid that
    covers the valid pixels ``valid1`` (H1, W1) and ``valid2`` (H2, W2) bool."""
    for cam, valid in ((cam1, valid1), (cam2, valid2)):
        if valid.shape != (cam.height, cam.width):
            raise ValueError(
                f"camera '{cam.name}': phase map is {valid.shape[1]} x {valid.shape[0]} pixels "
                f"but its calibration is for {cam.width} x {cam.height}"
            )
        if not valid.any():
            raise ValueError(f"camera '{cam.name}': no valid pixels to match")
    r, t = relative_pose(cam1, cam2)
    r1, r2, p1, p2, *_ = cv2.stereoRectify(
        cam1.K_array, cam1.dist_array, cam2.K_array, cam2.dist_array, cam1.size, r, t.reshape(3, 1),
        flags=cv2.CALIB_ZERO_DISPARITY, alpha=-1,
    )
    if abs(p2[1, 3]) > abs(p2[0, 3]):
        raise ValueError("the cameras are displaced vertically; only horizontal stereo is supported")
    b1, b2 = _bounds(valid1, cam1, r1, p1), _bounds(valid2, cam2, r2, p2)
    rows = (int(max(b1[0, 1], b2[0, 1])), int(min(b1[1, 1], b2[1, 1])))
    if rows[1] < rows[0]:
        raise ValueError("the two cameras' valid regions share no epipolar lines")
    return Rectification(
        r1, r2, p1, p2, rows, (int(b1[0, 0]), int(b1[1, 0])), (int(b2[0, 0]), int(b2[1, 0]))
    )


def rectify_map(
    cam: DeviceCalibration, r_rect: np.ndarray, p_rect: np.ndarray, cols: tuple[int, int],
    rows: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray]:
    """Source pixel ``(map_u, map_v)``, each (rows, cols) float64, of every rectified pixel
    ``(x, y)`` with x in ``cols`` and y in ``rows`` (inclusive): what
    ``cv2.initUndistortRectifyMap`` computes, in float64."""
    x = np.arange(cols[0], cols[1] + 1, dtype=np.float64)
    y = np.arange(rows[0], rows[1] + 1, dtype=np.float64)
    xx, yy = np.meshgrid(x, y)
    k_inv = np.linalg.inv(p_rect[:, :3])
    rays = np.stack([xx.ravel(), yy.ravel(), np.ones(xx.size)], axis=1) @ k_inv.T
    rays = rays @ r_rect  # rectified frame -> camera frame: R^T d
    uv = project_points(rays, cam.K_array, cam.dist_array, np.eye(3), np.zeros(3))
    return uv[:, 0].reshape(xx.shape), uv[:, 1].reshape(xx.shape)


def _cubic_weights(t: np.ndarray) -> np.ndarray:
    """Cubic Lagrange weights (..., 4) of the nodes -1, 0, 1, 2 at fraction ``t`` (...)."""
    return np.stack(
        [
            -t * (t - 1) * (t - 2) / 6,
            (t + 1) * (t - 1) * (t - 2) / 2,
            -(t + 1) * t * (t - 2) / 2,
            (t + 1) * t * (t - 1) / 6,
        ],
        axis=-1,
    )


def sample_image(
    image: np.ndarray, map_u: np.ndarray, map_v: np.ndarray, order: int = 3
) -> np.ndarray:
    """Samples of ``image`` (H, W) at ``(map_u, map_v)`` (any shape): bilinear (``order=1``)
    or separable cubic Lagrange over 4 x 4 pixels (``order=3``, exact for cubic surfaces).
    NaN where any pixel of the stencil is NaN or outside the image."""
    if order not in (1, 3):
        raise ValueError(f"interpolation order must be 1 or 3, got {order}")
    img = np.asarray(image, dtype=np.float64)
    h, w = img.shape
    u0, v0 = np.floor(map_u), np.floor(map_v)
    lo, hi = (0, 1) if order == 1 else (-1, 2)
    inside = (u0 + lo >= 0) & (v0 + lo >= 0) & (u0 + hi <= w - 1) & (v0 + hi <= h - 1)
    iu = np.where(inside, u0, -lo).astype(np.int64)
    iv = np.where(inside, v0, -lo).astype(np.int64)
    fu, fv = map_u - u0, map_v - v0
    if order == 1:
        wu = np.stack([1 - fu, fu], axis=-1)
        wv = np.stack([1 - fv, fv], axis=-1)
    else:
        wu, wv = _cubic_weights(fu), _cubic_weights(fv)
    out = np.zeros(np.shape(map_u))
    for a in range(hi - lo + 1):
        row = np.zeros(np.shape(map_u))
        for b in range(hi - lo + 1):
            row += wu[..., b] * img[iv + lo + a, iu + lo + b]
        out += wv[..., a] * row
    return np.where(inside, out, np.nan)


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


def triangulate(p1: np.ndarray, p2: np.ndarray, xy1: np.ndarray, xy2: np.ndarray) -> np.ndarray:
    """Points (n, 3) from pixel pairs (n, 2) of two cameras with projection matrices (3, 4):
    linear least squares on the four DLT equations ``x P[2] - P[0] = 0``, ``y P[2] - P[1] = 0``
    (the inhomogeneous form of ``cv2.triangulatePoints``, vectorised; exact for consistent pairs)."""
    rows = np.stack([
        xy1[:, :1] * p1[2] - p1[0], xy1[:, 1:] * p1[2] - p1[1],
        xy2[:, :1] * p2[2] - p2[0], xy2[:, 1:] * p2[2] - p2[1],
    ], axis=1)  # (n, 4, 4)
    a, b = rows[..., :3], -rows[..., 3]
    ata = np.einsum("nki,nkj->nij", a, a)
    return np.linalg.solve(ata, np.einsum("nki,nk->ni", a, b)[..., None])[..., 0]


def _grid_diff(grid: np.ndarray, axis: int) -> np.ndarray:
    """Difference of neighbours along ``axis`` (0 rows, 1 columns): central where both exist,
    else one-sided, scaled to one grid step; NaN where a point has no neighbour."""
    g = np.moveaxis(grid, axis, 0)
    fwd = np.full_like(g, np.nan)
    bwd = np.full_like(g, np.nan)
    fwd[:-1] = g[1:] - g[:-1]
    bwd[1:] = g[1:] - g[:-1]
    d = 0.5 * (fwd + bwd)
    d = np.where(np.isnan(d), fwd, d)
    d = np.where(np.isnan(d), bwd, d)
    return np.moveaxis(d, 0, axis)


def grid_normals(grid: np.ndarray, towards: np.ndarray) -> np.ndarray:
    """Unit normals (H, W, 3) of an organised cloud (H, W, 3) (NaN where missing) from neighbour
    differences, oriented to face the point ``towards`` (3,) (the camera centre); NaN for
    points without a neighbour along rows or columns."""
    n = np.cross(_grid_diff(grid, 1), _grid_diff(grid, 0))
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    flip = np.sum(n * (towards - grid), axis=2) < 0
    n[flip] *= -1
    return n


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


def _rectified_to_pixel(xy: np.ndarray, cam: DeviceCalibration, r: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Original (distorted) pixel coordinates (n, 2) of rectified pixels (n, 2): the OpenCV
    5-coefficient model, as ``cv2.projectPoints``, vectorised."""
    m = r.T @ np.linalg.inv(p[:, :3])  # rectified pixel -> camera ray
    x, y = xy[:, 0], xy[:, 1]
    rx = m[0, 0] * x + m[0, 1] * y + m[0, 2]
    ry = m[1, 0] * x + m[1, 1] * y + m[1, 2]
    rz = m[2, 0] * x + m[2, 1] * y + m[2, 2]
    xn, yn = rx / rz, ry / rz
    k1, k2, p1, p2, k3 = cam.dist_array
    r2 = xn * xn + yn * yn
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
    k = cam.K_array
    return np.stack([k[0, 0] * xd + k[0, 1] * yd + k[0, 2], k[1, 1] * yd + k[1, 2]], axis=1)


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


def _refine(side: _Side, x: np.ndarray, y: np.ndarray, q: np.ndarray, iterations: int = 5
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Newton search along the rectified rows ``y`` (n,) of ``side`` for the rectified column
    where its local phase model equals ``q`` (n,), from ``x`` (n,): the column, the original
    pixel there (n, 2), and whether it converged inside the stencil of a valid model with a
    non-zero slope along the row."""
    h, w = side.coord.shape
    ok = np.ones(len(x), dtype=bool)
    step = 1e-3  # rectified px, finite difference of the row's mapping into the image
    uv = _rectified_to_pixel(np.stack([x, y], axis=1), side.cam, side.r, side.p)
    duv = (_rectified_to_pixel(np.stack([x + step, y], axis=1), side.cam, side.r, side.p) - uv) / step
    for it in range(iterations + 1):
        if it:
            uv = _rectified_to_pixel(np.stack([x, y], axis=1), side.cam, side.r, side.p)
        node = np.round(uv)
        inside = (node[:, 0] >= 0) & (node[:, 0] < w) & (node[:, 1] >= 0) & (node[:, 1] < h)
        nu = np.clip(node[:, 0], 0, w - 1).astype(np.int64)
        nv = np.clip(node[:, 1], 0, h - 1).astype(np.int64)
        c = side.coef[nv, nu]
        d = uv - node
        f = np.sum(c * _basis(d[:, 0], d[:, 1]), axis=1) - q
        gx, gy = _basis_grad(d[:, 0], d[:, 1])
        df = np.sum(c * gx, axis=1) * duv[:, 0] + np.sum(c * gy, axis=1) * duv[:, 1]
        ok &= inside & np.isfinite(f) & np.isfinite(df) & (df != 0)
        if it == iterations:
            break
        x = np.where(ok, x - np.clip(f / np.where(ok, df, 1.0), -1.0, 1.0), x)
    # converged: the phase matches to a millionth of a pixel's worth of slope
    ok &= np.abs(f) <= 1e-6 * np.abs(df) + 1e-12 * np.maximum(1.0, np.abs(q))
    return x, uv, ok, df


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
    bilinearly interpolated at ``uv_match`` (n, 2), must land within ``tol_px`` of ``ref_pix``."""
    h, w = back.shape[:2]
    u0, v0 = np.floor(uv_match[:, 0]), np.floor(uv_match[:, 1])
    inside = (u0 >= 0) & (v0 >= 0) & (u0 + 1 <= w - 1) & (v0 + 1 <= h - 1)
    iu = np.where(inside, u0, 0).astype(np.int64)
    iv = np.where(inside, v0, 0).astype(np.int64)
    fu, fv = (uv_match[:, 0] - u0)[:, None], (uv_match[:, 1] - v0)[:, None]
    pred = ((1 - fv) * ((1 - fu) * back[iv, iu] + fu * back[iv, iu + 1])
            + fv * ((1 - fu) * back[iv + 1, iu] + fu * back[iv + 1, iu + 1]))
    err = np.linalg.norm(pred - ref_pix, axis=1)
    return inside & (err <= tol_px)


def stereo_cloud(
    coord1: np.ndarray,
    coord2: np.ndarray,
    cam1: DeviceCalibration,
    cam2: DeviceCalibration,
    projector: DeviceCalibration | None = None,
    axis: str = "u",
    max_projector_error_px: float = 0.5,
    quality1: np.ndarray | None = None,
    order: int = 3,
    quality2: np.ndarray | None = None,
    max_lr_error_px: float = 0.25,
    max_model_residual: float = 5.0,
    max_range_step: float = 8.0,
    residual1: np.ndarray | None = None,
    residual2: np.ndarray | None = None,
    rejected: list[dict[str, int]] | None = None,
) -> PointCloud:
    """Point cloud from the projector-coordinate maps (H, W) of two cameras (NaN = invalid).

    projector : its calibration resolves ambiguous matches and rejects points that reproject
        further than ``max_projector_error_px`` from the measured coordinate along ``axis``.
    quality1, quality2 : optional per-pixel quality (e.g. modulation) of each camera, returned
        per point (of the point's reference pixel).
    order : interpolation of the search map for the coarse match, 1 linear or 3 cubic
        (``sample_image``); the sub-pixel position does not depend on it.
    max_lr_error_px : left-right consistency tolerance, pixels.
    max_model_residual : pixels whose local phase model fits worse than this many times the
        median over the camera (silhouettes, mixed pixels, phase errors) are not used.
    max_range_step : points whose range differs from a neighbour's by more than this many
        pixel footprints, or that lack a neighbour, are dropped (depth steps, edges; 8 passes
        surfaces up to 83 degrees oblique; ``inf`` skips the check).
    residual1, residual2 : each map's local phase model residual (H, W) projector px as
        measured, when the maps were corrected afterwards (``pixel_footprint_correction``,
        whose per-pixel shift estimate roughens the map): which pixels are usable, the
        phase noise and the ``phase_error`` field then come from the measurement.
    rejected : if given, filled with one dict per camera: the pixels each check dropped with
        that camera as the reference (``stereo_model_residual``, ``stereo_no_match``,
        ``stereo_projector_error``, ``stereo_left_right``, ``stereo_range_step``).
    Returns points in the world frame, from both directions, with normals (facing each point's
    reference camera), quality and per-point fields (see ``PointCloud``).
    """
    for cam, c in ((cam1, coord1), (cam2, coord2)):
        if np.shape(c) != (cam.height, cam.width):
            raise ValueError(
                f"camera '{cam.name}': projector-coordinate map has shape {np.shape(c)}, "
                f"its calibration expects (height, width) = ({cam.height}, {cam.width})"
            )
    rect = stereo_rectification(cam1, cam2, np.isfinite(coord1), np.isfinite(coord2))
    sides = []
    for coord, cam, r, p, cols, measured_res in (
            (coord1, cam1, rect.R1, rect.P1, rect.cols1, residual1),
            (coord2, cam2, rect.R2, rect.P2, rect.cols2, residual2)):
        coef, res = local_phase_model(coord)
        if measured_res is not None:
            res = np.where(np.isfinite(res), measured_res, np.nan)
        sides.append(_Side(np.asarray(coord, dtype=np.float64), cam, r, p, cols, coef, res))
    usable = []
    for s in sides:
        if not np.isfinite(s.residual).any():
            raise ValueError(f"camera '{s.cam.name}': no valid pixel with 8 valid neighbours to match")
        usable.append(usable_pixels(s.residual, max_model_residual))
    noise = [phase_noise_px(s.residual, q) for s, q in zip(sides, (quality1, quality2))]
    # the search model is used at the matched pixel too: mask its coefficients
    sides = [_masked(s, u) for s, u in zip(sides, usable)]
    tally = [dict.fromkeys(("stereo_model_residual", "stereo_no_match", "stereo_projector_error",
                             "stereo_left_right", "stereo_range_step"), 0) for _ in sides]
    for t, s, u in zip(tally, sides, usable):
        t["stereo_model_residual"] = int(np.isfinite(s.coord).sum() - u.sum())
    results = []
    for a, b in ((0, 1), (1, 0)):
        flat, xy_ref, x_s, uv_s, slope = _match_direction(sides[a], sides[b], rect.rows, order,
                                                         usable[a])
        xy_s = np.stack([x_s, xy_ref[:, 1]], axis=1)
        pa, pb = (rect.P1, rect.P2) if a == 0 else (rect.P2, rect.P1)
        pts_rect = triangulate(pa, pb, xy_ref, xy_s)
        world = camera_to_world(pts_rect @ rect.R1, cam1.R_array, cam1.T_array)
        # mm per projector px of phase error: the search position moves by 1 / slope
        moved = triangulate(pa, pb, xy_ref, xy_s + [STEREO_SENSITIVITY_PX, 0.0])
        sens = np.linalg.norm(moved - pts_rect, axis=1) / STEREO_SENSITIVITY_PX / np.abs(slope)
        w = sides[a].coord.shape[1]
        measured = sides[a].coord.ravel()[flat]
        if projector is not None:
            k = 0 if axis == "u" else 1
            err = np.abs(projector.project(world)[:, k] - measured)
            good = err <= max_projector_error_px
        else:
            err = np.zeros(len(world))
            good = np.ones(len(world), dtype=bool)
        ranked = np.lexsort((np.where(good, err, np.inf), flat))
        first = np.r_[True, np.diff(flat[ranked]) != 0] if len(ranked) else np.zeros(0, bool)
        counts = np.diff(np.r_[np.flatnonzero(first), len(ranked)])
        chosen = ranked[first]
        if projector is None:
            chosen = chosen[counts == 1]
        tally[a]["stereo_no_match"] = int(usable[a].sum()) - len(chosen)
        tally[a]["stereo_projector_error"] = int((~good[chosen]).sum())
        chosen = chosen[good[chosen]]
        ref_pix = np.stack([flat[chosen] % w, flat[chosen] // w], axis=1).astype(np.float64)
        results.append((world[chosen], ref_pix, uv_s[chosen], sens[chosen]))
    kept = []
    for a in (0, 1):
        world, ref_pix, uv_s, sens = results[a]
        other = results[1 - a]
        hs, ws = sides[1 - a].coord.shape
        back = np.full((hs, ws, 2), np.nan)
        back[other[1][:, 1].astype(int), other[1][:, 0].astype(int)] = other[2]
        ok = _lr_consistent(uv_s, ref_pix, back, max_lr_error_px)
        tally[a]["stereo_left_right"] = int((~ok).sum())
        if np.isfinite(max_range_step):
            before = int(ok.sum())
            ok[ok] = _continuous(world[ok], ref_pix[ok], sides[a].cam, max_range_step)
            tally[a]["stereo_range_step"] = before - int(ok.sum())
        node = np.round(uv_s[ok]).astype(np.int64)
        sigma = np.hypot(noise[a][ref_pix[ok][:, 1].astype(int), ref_pix[ok][:, 0].astype(int)],
                         noise[1 - a][node[:, 1], node[:, 0]])
        kept.append((world[ok], ref_pix[ok], sens[ok] * sigma))
    if rejected is not None:
        rejected[:] = tally
    if not any(len(k[0]) for k in kept):
        raise ValueError("stereo matching found no pixel with the same projector coordinate in both cameras")
    points, normals, quality, camera, pixels, perr, unc = [], [], [], [], [], [], []
    for a, (world, ref_pix, u_mm) in enumerate(kept):
        cam = sides[a].cam
        iu, iv = ref_pix[:, 0].astype(int), ref_pix[:, 1].astype(int)
        grid = np.full((cam.height, cam.width, 3), np.nan)
        grid[iv, iu] = world
        points.append(world)
        normals.append(grid_normals(grid, cam.centre_world)[iv, iu])
        qa = (quality1, quality2)[a]
        quality.append(np.asarray(qa, dtype=np.float64)[iv, iu] if qa is not None else np.full(len(world), np.nan))
        camera.append(np.full(len(world), a))
        pixels.append(ref_pix)
        perr.append(sides[a].residual[iv, iu])
        unc.append(u_mm)
    has_q = quality1 is not None or quality2 is not None
    pix = np.concatenate(pixels)
    return PointCloud(np.concatenate(points), np.concatenate(normals),
                      np.concatenate(quality) if has_q else None,
                      {"camera": np.concatenate(camera).astype(np.float64), "u": pix[:, 0],
                       "v": pix[:, 1], "phase_error": np.concatenate(perr),
                       "uncertainty_mm": np.concatenate(unc)})


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


def _continuous(world: np.ndarray, ref_pix: np.ndarray, cam: DeviceCalibration, max_step: float
                ) -> np.ndarray:
    """Points (n,) whose 8 neighbours are all reconstructed, with ranges from the camera within
    ``max_step`` pixel footprints (range / f) of theirs: the edges of what was reconstructed
    and depth steps (silhouettes, and the mixed pixels a blurred silhouette leaves between
    the surfaces) are dropped, on both sides."""
    h, w = cam.height, cam.width
    rng = np.full((h + 2, w + 2), np.nan)
    iu, iv = ref_pix[:, 0].astype(np.int64) + 1, ref_pix[:, 1].astype(np.int64) + 1
    rng[iv, iu] = np.linalg.norm(world - cam.centre_world, axis=1)
    limit = max_step * rng[iv, iu] / min(cam.K_array[0, 0], cam.K_array[1, 1])
    ok = np.ones(len(world), dtype=bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dx or dy:
                step = np.abs(rng[iv + dy, iu + dx] - rng[iv, iu])
                ok &= step <= limit  # NaN (no neighbour) fails
    return ok


def _masked(side: _Side, usable: np.ndarray) -> _Side:
    """``side`` with its model coefficients NaN outside ``usable`` (H, W) bool."""
    coef = np.where(usable[..., None], side.coef, np.nan)
    return _Side(side.coord, side.cam, side.r, side.p, side.cols, coef, side.residual)


def camera_projector_cloud(
    coord: np.ndarray,
    cam: DeviceCalibration,
    projector: DeviceCalibration,
    axis: str = "u",
    iterations: int = 4,
) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate one camera against the projector: ``(points (n, 3) world mm, pixels (n, 2))``.

    coord : (H, W) projector coordinate along ``axis`` ('u' column, 'v' row), NaN = invalid.
    Each pixel's ray is intersected with the projector's plane of constant coordinate (pinhole
    start), then refined by Newton steps on the distorted projection of the projector.
    """
    if axis not in ("u", "v"):
        raise ValueError(f"axis must be 'u' or 'v', got {axis!r}")
    if np.shape(coord) != (cam.height, cam.width):
        raise ValueError(
            f"camera '{cam.name}': projector-coordinate map has shape {np.shape(coord)}, "
            f"its calibration expects (height, width) = ({cam.height}, {cam.width})"
        )
    v, u = np.nonzero(np.isfinite(coord))
    target = coord[v, u]
    uv = np.stack([u, v], axis=1).astype(np.float64)
    origin, d = cam.pixel_rays(uv)
    k = 0 if axis == "u" else 1
    kp = projector.K_array
    o_p = projector.to_device(origin)
    d_p = d @ projector.R_array.T
    # pinhole plane: X - x_n Z = 0 (u) or Y - y_n Z = 0 (v), normalised coordinate of the target
    if k == 0:
        yn_guess = 0.0
        xn = (target - kp[0, 2] - kp[0, 1] * yn_guess) / kp[0, 0]
    else:
        xn = (target - kp[1, 2]) / kp[1, 1]
    num = o_p[:, k] - xn * o_p[:, 2]
    den = d_p[:, k] - xn * d_p[:, 2]
    t = -num / den
    h = 1e-3  # mm, finite-difference step of the Newton refinement
    for _ in range(iterations):
        f0 = projector.project(origin + t[:, None] * d)[:, k] - target
        f1 = projector.project(origin + (t + h)[:, None] * d)[:, k] - target
        t = t - f0 * h / (f1 - f0)
    return origin + t[:, None] * d, uv
