"""Rendered calibration captures, each rendered once per session."""

from __future__ import annotations

import numpy as np
import pytest

from sim.calibration.virtual import calibration_rig, default_poses, render_capture
from sim.render.board import CalibrationBoard
from sim.render.scene import Pose

CHESS = CalibrationBoard(kind="chessboard", rows=7, columns=10, square_mm=20.0)
SMALL = 0.25  # 320 x 256 cameras, 480 x 270 projector: refusals and the command line


@pytest.fixture(scope="session")
def small_capture(tmp_path_factory):
    """Six poses of the chessboard for the quarter-size rig (noise-free, pinhole)."""
    out = tmp_path_factory.mktemp("cal") / "small"
    return render_capture(out, CHESS, calibration_rig(scale=SMALL),
                          default_poses(CHESS, 15)[::2][:6])


@pytest.fixture(scope="session")
def fronto_capture(tmp_path_factory):
    """Four fronto-parallel poses (no tilt) at different places and depths."""
    out = tmp_path_factory.mktemp("cal") / "fronto"
    w, h = CHESS.size_mm
    poses = [Pose(t=[x - w / 2, y - h / 2, z]) for x, y, z in
             ((0, 0, 0), (20, 10, 40), (-20, -10, -40), (10, -15, 60))]
    return render_capture(out, CHESS, calibration_rig(scale=SMALL), poses)


def rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(np.asarray(a) ** 2, axis=-1))))
