"""sim.optics.projection: pinhole projection with OpenCV distortion and its inverse."""

import cv2
import numpy as np

from sim.optics.projection import (
    camera_to_world,
    directions_to_world,
    normalized_to_pixel,
    pixel_to_normalized,
    project_points,
)

K = np.array([[1200.0, 0.0, 639.5], [0.0, 1180.0, 479.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.12, 0.05, 0.001, -0.0007, 0.0])


def _pose():
    R, _ = cv2.Rodrigues(np.array([0.1, -0.2, 0.05]))
    return R, np.array([10.0, -5.0, 700.0])


def test_pixel_centre_convention_principal_point_is_axis():
    np.testing.assert_allclose(pixel_to_normalized(np.array([[639.5, 479.5]]), K), 0.0)


def test_undistort_inverts_distort_to_sub_micropixel():
    rng = np.random.default_rng(1)
    uv = rng.uniform([0, 0], [1279, 959], size=(500, 2))
    back = normalized_to_pixel(pixel_to_normalized(uv, K, DIST), K, DIST)
    np.testing.assert_allclose(back, uv, atol=1e-6)


def test_project_points_matches_opencv_and_manual_pinhole():
    rng = np.random.default_rng(2)
    X = rng.uniform([-100, -100, -50], [100, 100, 50], size=(200, 3))
    R, T = _pose()
    uv = project_points(X, K, DIST, R, T)
    ref, _ = cv2.projectPoints(X.reshape(-1, 1, 3), cv2.Rodrigues(R)[0], T, K, DIST)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)
    pc = X @ R.T + T
    manual = (pc[:, :2] / pc[:, 2:]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    np.testing.assert_allclose(project_points(X, K, None, R, T), manual, atol=1e-9)


def test_camera_to_world_inverts_world_to_camera():
    R, T = _pose()
    X = np.array([[1.0, 2.0, 3.0], [-4.0, 5.0, 600.0]])
    np.testing.assert_allclose(camera_to_world(X @ R.T + T, R, T), X, atol=1e-12)
    d = np.array([[0.0, 0.0, 1.0]])
    np.testing.assert_allclose(directions_to_world(d @ R.T, R), d, atol=1e-15)
