"""Rectified stereo geometry of two cameras (``cv2.stereoRectify``: rows are epipolar lines),
the exact maps between original (distorted) and rectified pixels, and the sampling of an image
on the rectified grid (linear or cubic). Pixels in OpenCV convention, centres at integers."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from sim.errors import SimInputError
from sim.optics.projection import project_points
from sim.optics.rig import DeviceCalibration


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
            raise SimInputError(
                f"camera '{cam.name}': phase map is {valid.shape[1]} x {valid.shape[0]} pixels "
                f"but its calibration is for {cam.width} x {cam.height}"
            )
        if not valid.any():
            raise SimInputError(f"camera '{cam.name}': no valid pixels to match")
    r, t = relative_pose(cam1, cam2)
    r1, r2, p1, p2, *_ = cv2.stereoRectify(
        cam1.K_array, cam1.dist_array, cam2.K_array, cam2.dist_array, cam1.size, r, t.reshape(3, 1),
        flags=cv2.CALIB_ZERO_DISPARITY, alpha=-1,
    )
    if abs(p2[1, 3]) > abs(p2[0, 3]):
        raise SimInputError("the cameras are displaced vertically; only horizontal stereo is "
                            "supported")
    b1, b2 = _bounds(valid1, cam1, r1, p1), _bounds(valid2, cam2, r2, p2)
    rows = (int(max(b1[0, 1], b2[0, 1])), int(min(b1[1, 1], b2[1, 1])))
    if rows[1] < rows[0]:
        raise SimInputError("the two cameras' valid regions share no epipolar lines")
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
        raise SimInputError(f"interpolation order must be 1 or 3, got {order}")
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
