"""Pinhole projection with OpenCV distortion, and its inverse (pixel -> normalised ray).

Conventions (docs/architecture.md): OpenCV camera frame (x right, y down, z forward), pixel
centres at integer coordinates, ``u`` the column. ``R, T`` map world to device:
``X_dev = R @ X_world + T``. Distances in mm.
"""

from __future__ import annotations

import cv2
import numpy as np


def _as_dist(dist: np.ndarray | None) -> np.ndarray:
    return np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64).ravel()


def pixel_to_normalized(
    uv: np.ndarray, K: np.ndarray, dist: np.ndarray | None = None
) -> np.ndarray:
    """Undistorted normalised coordinates ``(x_n, y_n)`` of pixels.

    uv : (n, 2) float, pixel coordinates (u column, v row).
    Returns (n, 2) float64 with ``x_n = X/Z``, ``y_n = Y/Z`` of the ray in the camera frame.
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    d = _as_dist(dist)
    if not np.any(d):
        K = np.asarray(K, dtype=np.float64)
        xn = (uv[:, 0] - K[0, 2] - K[0, 1] * (uv[:, 1] - K[1, 2]) / K[1, 1]) / K[0, 0]
        yn = (uv[:, 1] - K[1, 2]) / K[1, 1]
        return np.stack([xn, yn], axis=1)
    pts = cv2.undistortPoints(
        uv.reshape(-1, 1, 2),
        np.asarray(K, dtype=np.float64),
        d,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-14),
    )
    return pts.reshape(-1, 2)


def normalized_to_pixel(
    xy_n: np.ndarray, K: np.ndarray, dist: np.ndarray | None = None
) -> np.ndarray:
    """Pixel coordinates (n, 2) of normalised coordinates (n, 2), applying distortion."""
    xy_n = np.asarray(xy_n, dtype=np.float64).reshape(-1, 2)
    pts3 = np.concatenate([xy_n, np.ones((len(xy_n), 1))], axis=1)
    return project_points(pts3, K, dist, np.eye(3), np.zeros(3))


def project_points(
    points_mm: np.ndarray,
    K: np.ndarray,
    dist: np.ndarray | None,
    R: np.ndarray,
    T: np.ndarray,
) -> np.ndarray:
    """Project world points (n, 3) mm to pixels (n, 2) with ``s [u v 1] = K [R|T] X`` and distortion."""
    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    d = _as_dist(dist)
    R = np.asarray(R, dtype=np.float64)
    T = np.asarray(T, dtype=np.float64).ravel()
    K = np.asarray(K, dtype=np.float64)
    if not np.any(d):
        pc = pts @ R.T + T
        xn = pc[:, :2] / pc[:, 2:3]
        u = K[0, 0] * xn[:, 0] + K[0, 1] * xn[:, 1] + K[0, 2]
        v = K[1, 1] * xn[:, 1] + K[1, 2]
        return np.stack([u, v], axis=1)
    rvec, _ = cv2.Rodrigues(R)
    uv, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), rvec, T, K, d)
    return uv.reshape(-1, 2)


def camera_to_world(
    points_cam: np.ndarray, R: np.ndarray, T: np.ndarray
) -> np.ndarray:
    """Points (..., 3) from the device frame to the world frame: ``R^T (p - T)``."""
    return (np.asarray(points_cam) - np.asarray(T).ravel()) @ np.asarray(R)


def directions_to_world(dirs_cam: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Directions (..., 3) from the device frame to the world frame: ``R^T d``."""
    return np.asarray(dirs_cam) @ np.asarray(R)
