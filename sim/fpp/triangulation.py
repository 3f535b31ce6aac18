"""Triangulation: two cameras' pixel pairs (linear least squares, as ``cv2.triangulatePoints``),
one camera against the projector's planes of constant coordinate, and the normals of an
organised cloud. Points in mm in the world frame unless named otherwise."""

from __future__ import annotations

import numpy as np

from sim.errors import SimInputError
from sim.optics.rig import DeviceCalibration

STEREO_SENSITIVITY_PX = 1e-3
"""Rectified px: the step of the finite difference that gives a stereo point's sensitivity."""


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
        raise SimInputError(f"axis must be 'u' or 'v', got {axis!r}")
    if np.shape(coord) != (cam.height, cam.width):
        raise SimInputError(
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
