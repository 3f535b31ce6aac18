"""``ltc patterns --calibration``, ``ltc calibrate`` and its refusals (exit 1, one line naming
the pose and camera), on quarter-size rendered captures."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from sim.calibration.capture import CalibrationPatterns
from sim.optics.rig import Rig, relative_to_camera_0
from station.cli import main

BOARD = 'kind = "chessboard"\nrows = 7\ncolumns = 10\nsquare_mm = 20.0\n'


@pytest.fixture
def board(tmp_path):
    f = tmp_path / "board.toml"
    f.write_text(BOARD)
    return f


def _run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_patterns_writes_the_projector_images_in_capture_order(tmp_path, capsys):
    code, out, _ = _run(capsys, "patterns", "--calibration", "--projector-size", "192x108",
                        "--u-fringes", "1,8", "--v-fringes", "1,6", "--steps", "3",
                        "--out", tmp_path / "p")
    assert code == 0 and "13 projector images" in out
    files = sorted((tmp_path / "p").glob("pattern_*.png"))
    assert len(files) == 1 + 2 * 3 + 2 * 3
    ims = [cv2.imread(str(f), cv2.IMREAD_UNCHANGED) for f in files]
    assert all(im.shape == (108, 192) and im.dtype == np.uint8 for im in ims)
    assert np.all(ims[0] == 255)
    # image 4 (u, period 192 / 8 = 24 px, shift 0): 0.5 + 0.5 cos(2 pi u / 24), 8-bit
    u = np.arange(192)
    assert np.abs(ims[4][0].astype(float) - 255 * (0.5 + 0.5 * np.cos(2 * np.pi * u / 24))).max() \
        <= 0.5 + 1e-9
    # image 7 (v, period 108, shift 0) varies along rows only
    assert np.all(ims[7] == ims[7][:, :1])
    pats = CalibrationPatterns.model_validate_json((tmp_path / "p" / "capture.json").read_text())
    assert pats.count == 13 and pats.v.periods_px == [108.0, 18.0]


@pytest.mark.slow
def test_calibrate_writes_a_rig_and_a_report(small_capture, board, tmp_path, capsys):
    out, rep = tmp_path / "rig.yaml", tmp_path / "report"
    code, text, err = _run(capsys, "calibrate", small_capture.directory, "--board", board,
                           "--out", out, "--report", rep, "--json")
    assert code == 0, err
    s = json.loads(text)
    assert s["poses"] == 6 and max(s["rms_px"].values()) < 0.02
    rig, true = Rig.load(out), relative_to_camera_0(small_capture.rig)
    for a, b in zip([*rig.cameras, rig.projector], [*true.cameras, true.projector], strict=True):
        assert a.K_array[0, 0] == pytest.approx(b.K_array[0, 0], rel=1e-3)
        assert np.abs(a.T_array - b.T_array).max() < 0.2
    for f in ("report.md", "residuals.png", "coverage.png", "error_per_pose.png"):
        assert (rep / f).stat().st_size > 0
    assert "| projector |" in (rep / "report.md").read_text()
    code, _, err = _run(capsys, "calibrate", small_capture.directory, "--board", board,
                        "--out", out)
    assert code == 2 and "--force" in err


def _copy(capture, tmp_path, name):
    d = tmp_path / name
    shutil.copytree(capture.directory, d)
    return d


def _refused(capsys, capture_dir, board, tmp_path) -> str:
    code, _, err = _run(capsys, "calibrate", capture_dir, "--board", board, "--out",
                        tmp_path / "rig.yaml")
    assert code == 1
    assert err.count("\n") == 1 and err.startswith("ltc calibrate: error: ")
    assert not (tmp_path / "rig.yaml").exists()
    return err


def test_refuses_a_board_not_found(small_capture, board, tmp_path, capsys):
    d = _copy(small_capture, tmp_path, "c")
    white = d / "pose_002" / "camera_1" / "000.png"
    im = cv2.imread(str(white), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(white), np.full_like(im, int(np.median(im))))
    err = _refused(capsys, d, board, tmp_path)
    assert "pose_002, camera 1: board not found" in err


def test_refuses_fewer_than_three_poses(small_capture, board, tmp_path, capsys):
    d = _copy(small_capture, tmp_path, "c")
    for p in sorted(d.glob("pose_*"))[2:]:
        shutil.rmtree(p)
    poses = sorted(p.name for p in d.glob("pose_*"))
    assert len(poses) == 2
    err = _refused(capsys, d, board, tmp_path)
    assert f"2 usable pose(s) ({poses[0]}, {poses[1]}) seen by camera 0 and camera 1" in err


@pytest.mark.slow
def test_refuses_poses_that_leave_the_focal_length_unconstrained(fronto_capture, board,
                                                                 tmp_path, capsys):
    err = _refused(capsys, fronto_capture.directory, board, tmp_path)
    assert "pose_000 .. pose_003, camera 0:" in err and "focal length is unconstrained" in err


@pytest.mark.slow
def test_refuses_a_capture_out_of_sync_with_the_projector(small_capture, board, tmp_path,
                                                          capsys):
    d = _copy(small_capture, tmp_path, "c")
    # every camera recorded each fringe image one pattern late (the first fringe image twice)
    for folder in d.glob("pose_*/camera_*"):
        files = sorted(folder.glob("*.png"))
        for late, early in zip(reversed(files[2:]), reversed(files[1:-1]), strict=True):
            shutil.copyfile(early, late)
    err = _refused(capsys, d, board, tmp_path)
    assert "projector's reprojection error" in err and "out of sync" in err
    assert "gamma" in err and ", camera 0 and camera 1:" in err


@pytest.mark.slow
def test_render_calibration_writes_a_capture_with_the_scene_s_rig_and_response(
        board, tmp_path, capsys):
    from sim.calibration.virtual import calibration_rig

    calibration_rig(scale=0.25).save(tmp_path / "rig.yaml")
    (tmp_path / "scene.toml").write_text(
        'rig = "rig.yaml"\n[[lenses]]\nkind = "pinhole"\n[[lenses]]\nkind = "pinhole"\n'
        '[[objects]]\nkind = "sphere"\n[patterns]\nkind = "phase_shift"\nperiods_px = [16.0]\n'
        '[render.camera]\nbit_depth = 12\n[render.projector]\ngamma = 1.0\n')
    code, out, err = _run(capsys, "render", tmp_path / "scene.toml", "--calibration", board,
                          "--poses", "3", "--out", tmp_path / "cap")
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "cap").glob("pose_*")) == \
        ["pose_000", "pose_001", "pose_002"]
    files = sorted((tmp_path / "cap" / "pose_001" / "camera_1").glob("*.png"))
    pats = CalibrationPatterns.model_validate_json((tmp_path / "cap" / "capture.json").read_text())
    assert len(files) == pats.count == 25 and pats.projector_size == (480, 270)
    white = cv2.imread(str(files[0]), cv2.IMREAD_UNCHANGED)
    assert white.dtype == np.uint16 and white.shape == (256, 320) and 0 < white.max() <= 4095
