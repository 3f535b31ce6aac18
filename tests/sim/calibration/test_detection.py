"""Feature detection on rendered boards against the true projections of the features."""

from __future__ import annotations

import numpy as np
import pytest

from sim.calibration.board import detect
from sim.calibration.capture import Capture
from sim.calibration.virtual import calibration_rig, default_poses, render_capture
from sim.render.board import CalibrationBoard

from .conftest import CHESS, rms

CHARUCO = CalibrationBoard(kind="charuco", rows=7, columns=10, square_mm=20.0, marker_mm=15.0)


def _truth(capture, board, pose, camera):
    X = capture.poses[pose].apply(board.object_points())
    return capture.rig.cameras[camera].project(X)


def test_chessboard_corners_on_the_small_capture(small_capture):
    cap = Capture(small_capture.directory)
    for j, pose in enumerate(cap.poses[:3]):
        for c in range(2):
            f = detect(cap.stack(pose, c)[0], CHESS)
            assert f is not None and len(f.ids) == 54
            assert rms(f.uv - _truth(small_capture, CHESS, j, c)[f.ids]) < 0.02


@pytest.mark.slow
def test_charuco_corners_also_on_a_partly_hidden_board(tmp_path):
    rig = calibration_rig(scale=0.5)
    rc = render_capture(tmp_path / "c", CHARUCO, rig, default_poses(CHARUCO)[1:2])
    white = Capture(rc.directory).stack("pose_000", 0)[0]
    truth = _truth(rc, CHARUCO, 0, 0)
    f = detect(white, CHARUCO)
    assert len(f.ids) == 54 and rms(f.uv - truth[f.ids]) < 0.02
    hidden = white.copy()
    hidden[:, :300] = hidden.max()  # the left half of the board covered
    g = detect(hidden, CHARUCO)
    assert 10 <= len(g.ids) < 54 and rms(g.uv - truth[g.ids]) < 0.02
    assert np.all(truth[g.ids][:, 0] > 300)
