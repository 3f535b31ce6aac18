"""Calibration parts against known answers: board geometry and albedo, the footprint integral,
projector features on an exact homography, the bundle adjustment on synthetic observations,
the stereoCalibrate rig file."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sim.calibration.board import load_board
from sim.calibration.bundle import Layout, Observations, adjust, initial_vector
from sim.calibration.errors import CalibrationError
from sim.calibration.projector import local_homography, sample
from sim.calibration.virtual import calibration_rig, default_poses
from sim.optics.rig import Rig, relative_to_camera_0, save_stereo_calibrate
from sim.render.board import CalibrationBoard, _footprint_integral

CHESS = CalibrationBoard(kind="chessboard", rows=7, columns=10, square_mm=20.0)


def test_chessboard_features_and_albedo():
    pts = CHESS.object_points()
    assert pts.shape == (54, 3) and CHESS.pattern_size == (9, 6)
    assert np.allclose(pts[0], [20, 20, 0]) and np.allclose(pts[-1], [180, 120, 0])
    # square (0, 0) dark, (0, 1) light, outside the board light
    a = CHESS.albedo(np.array([[10.0, 10.0], [30.0, 10.0], [-5.0, 10.0], [30.0, 30.0]]))
    assert a.tolist() == [0.1, 0.9, 0.9, 0.1]


def test_circle_grids_dark_at_every_centre_light_between():
    for b in (CalibrationBoard(kind="circles", rows=4, columns=5, pitch_mm=20.0),
              CalibrationBoard(kind="asymmetric_circles", rows=5, columns=4, pitch_mm=30.0)):
        c = b.object_points()[:, :2]
        assert np.all(b.albedo(c) == b.dark_albedo)
        assert np.all(b.albedo(c + [b.diameter_mm * 0.51, 0]) == b.light_albedo)
        assert np.all(b.albedo(c + [0, b.diameter_mm * 0.49]) == b.dark_albedo)


def test_charuco_board_squares_match_the_chessboard_corners():
    b = CalibrationBoard(kind="charuco", rows=5, columns=7, square_mm=20.0, marker_mm=14.0)
    corners = np.asarray(b.charuco.getChessboardCorners())
    assert np.allclose(corners, b.object_points())


def test_footprint_integral_of_a_straight_edge():
    # a 1 x 1 mm footprint centred 0.3 mm left of the edge x = 20 between squares (0,0) dark
    # and (0,1) light: light fraction 0.2, its centroid 0.4 mm right of the centre
    centre = np.array([[19.7, 10.0]])
    J = np.eye(2)[None]
    mean, shift = _footprint_integral(CHESS, centre, J)
    assert mean[0] == pytest.approx(0.8 * 0.1 + 0.2 * 0.9, abs=2e-3)
    # albedo-weighted centroid: (0.8 * 0.1 * -0.1 + 0.2 * 0.9 * 0.4) / mean
    want = (0.8 * 0.1 * -0.1 + 0.2 * 0.9 * 0.4) / (0.8 * 0.1 + 0.2 * 0.9)
    assert shift[0, 0] == pytest.approx(want, abs=3e-3) and abs(shift[0, 1]) < 3e-3


def test_board_file(tmp_path):
    f = tmp_path / "board.toml"
    f.write_text('kind = "chessboard"\nrows = 7\ncolumns = 10\nsquare_mm = 20.0\n')
    assert load_board(f) == CHESS
    f.write_text('kind = "chessboard"\nrows = 7\ncolumns = 10\n')
    with pytest.raises(CalibrationError, match="square_mm"):
        load_board(f)
    f.write_text('kind = "chessboard"\nrows = 8\ncolumns = 10\nsquare_mm = 20.0\n')
    with pytest.raises(CalibrationError, match="one odd and one even"):
        load_board(f)


def _phase_maps(H: np.ndarray, shape=(120, 160)):
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(float)
    p = cv2.perspectiveTransform(np.stack([xx, yy], -1).reshape(-1, 1, 2), H).reshape(*shape, 2)
    return p[..., 0].copy(), p[..., 1].copy()


def test_local_homography_is_exact_on_a_plane_and_rejects_outliers():
    H = np.array([[1.2, 0.05, 30.0], [-0.03, 1.1, 12.0], [2e-4, -1e-4, 1.0]])
    u_p, v_p = _phase_maps(H)
    uv = np.array([[60.3, 50.7], [90.55, 70.25]])
    truth = cv2.perspectiveTransform(uv.reshape(-1, 1, 2), H).reshape(-1, 2)
    assert np.abs(local_homography(u_p, v_p, uv) - truth).max() < 1e-6
    # bilinear sampling of the same maps misses by the homography's curvature
    assert np.abs(sample(u_p, v_p, uv) - truth).max() > 1e-5
    rng = np.random.default_rng(1)
    bad = rng.random(u_p.shape) < 0.05
    u_p[bad] += rng.choice([-30.0, 30.0], bad.sum())  # wrong fringe orders
    assert np.abs(local_homography(u_p, v_p, uv) - truth).max() < 1e-6


def test_bundle_adjustment_recovers_a_known_rig_from_exact_observations():
    rig = relative_to_camera_0(calibration_rig(camera_dist=(-0.1, 0.05, 0.001, -0.0005, 0.0)))
    poses = default_poses(CHESS, 8)
    true_rig = calibration_rig()
    obj = CHESS.object_points()
    devs = [*rig.cameras, rig.projector]
    R0, T0 = true_rig.cameras[0].R_array, true_rig.cameras[0].T_array
    dev, pose, point, uv = [], [], [], []
    pr, pt = [], []
    for j, p in enumerate(poses):
        Rb = R0 @ np.asarray(p.R)
        tb = R0 @ np.asarray(p.t) + T0
        pr.append(cv2.Rodrigues(Rb)[0].ravel())
        pt.append(tb)
        Xc0 = obj @ Rb.T + tb
        for d, D in enumerate(devs):
            dev.append(np.full(len(obj), d))
            pose.append(np.full(len(obj), j))
            point.append(np.arange(len(obj)))
            uv.append(D.project(Xc0))
    obs = Observations(np.concatenate(dev), np.concatenate(pose), np.concatenate(point),
                       np.concatenate(uv), obj)
    layout = Layout(["k1k2p1p2k3", "k1k2p1p2k3", "k1k2"], len(poses))
    # start 2 % off in focal length, 10 px off in principal point, 1 degree / 5 mm off
    K0 = [D.K_array * [[1.02, 1, 1], [1, 1.02, 1], [1, 1, 1]] + [[0, 0, 10], [0, 0, -10], [0, 0, 0]]
          for D in devs]
    er = [cv2.Rodrigues(D.R_array)[0].ravel() + np.radians(1.0) for D in devs[1:]]
    et = [D.T_array + 5.0 for D in devs[1:]]
    x0 = initial_vector(layout, K0, [np.zeros(5)] * 3, np.array(pr) + 0.01,
                        np.array(pt) + 2.0, er, et)
    sol = adjust(layout, x0, obs)
    assert np.sqrt(np.mean(sol.residuals**2)) < 1e-6
    for d, D in enumerate(devs):
        assert np.allclose(sol.K[d], D.K_array, atol=1e-5)
        assert np.allclose(sol.R[d], D.R_array, atol=1e-9)
        assert np.allclose(sol.T[d], D.T_array, atol=1e-6)
    assert np.allclose(sol.dist[0], devs[0].dist_array, atol=1e-7)
    assert np.all(sol.fx_rel_std < 1e-6)


def test_stereo_calibrate_file_round_trip(tmp_path):
    rig = calibration_rig(camera_dist=(-0.1, 0.0, 0.001, 0.0, 0.0),
                          projector_dist=(0.02, 0.0, 0.0, 0.0, 0.0))
    path = tmp_path / "rig.yaml"
    save_stereo_calibrate(rig, path)
    text = path.read_text()
    assert all(f"\n{k}:" in text for k in ("M1", "D1", "M2", "D2", "R", "T", "M3", "D3", "R3",
                                          "T3"))
    back = Rig.load(path)
    want = relative_to_camera_0(rig)
    for a, b in zip([*back.cameras, back.projector], [*want.cameras, want.projector], strict=True):
        assert np.allclose(a.K_array, b.K_array) and np.allclose(a.dist_array, b.dist_array)
        assert np.allclose(a.R_array, b.R_array, atol=1e-12)
        assert np.allclose(a.T_array, b.T_array, atol=1e-9) and a.size == b.size
    # the same world points project to the same pixels through both rigs
    X = np.array([[10.0, -20.0, 30.0], [-40.0, 15.0, -25.0]])
    X0 = X @ rig.cameras[0].R_array.T + rig.cameras[0].T_array
    assert np.allclose(back.projector.project(X0), rig.projector.project(X), atol=1e-9)
