"""Calibration of full-size virtual captures against the rig that rendered them: 1280 x 1024
cameras, a 1920 x 1080 projector, 12 poses, noise-free pinhole (chessboard with camera
distortion, asymmetric circle grid), and 12-bit noise with a thin lens (twice the bounds);
and a sphere scanned with the calibrated rig against the same scan with the true rig."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sim.calibration.calibrator import calibrate
from sim.calibration.virtual import calibration_rig, default_poses, render_capture
from sim.fpp.decode import DecodeSettings, scan
from sim.metrology.measure import measure_sphere
from sim.optics.lens import AberratedLens, PinholeLens
from sim.optics.rig import relative_to_camera_0
from sim.render.board import CalibrationBoard
from sim.render.fringe_patterns import PhaseShiftSet
from sim.render.images import RenderSettings, render_views
from sim.render.scene import Scene, SphereObject

pytestmark = [pytest.mark.slow, pytest.mark.timeout(1800)]

CHESS = CalibrationBoard(kind="chessboard", rows=7, columns=10, square_mm=20.0)
CIRCLES = CalibrationBoard(kind="asymmetric_circles", rows=9, columns=6, pitch_mm=30.0)
CAMERA_DIST = (-0.1, 0.0, 0.001, 0.0, 0.0)
POSES = 12
# the acceptance bounds: RMS px (cameras, projector), focal %, principal point px,
# relative rotation deg, relative translation mm
BOUNDS = {"cam_rms": 0.02, "proj_rms": 0.04, "f_pct": 0.05, "pp_px": 0.3, "rot_deg": 0.01,
          "t_mm": 0.05}


def _report(name: str, err: dict) -> None:
    """The measured errors, printed (seen with ``pytest -s``)."""
    print(f"\n{name}: " + ", ".join(f"{k} {float(v):.7g}" for k, v in err.items()))


def _errors(result, true_rig) -> dict:
    true = relative_to_camera_0(true_rig)
    out = {"cam_rms": max(result.rms_px["camera_0"], result.rms_px["camera_1"]),
           "proj_rms": result.rms_px["projector"], "f_pct": 0.0, "pp_px": 0.0, "rot_deg": 0.0,
           "t_mm": 0.0}
    for a, b in zip([*result.rig.cameras, result.rig.projector],
                    [*true.cameras, true.projector], strict=True):
        K, Kt = a.K_array, b.K_array
        out["f_pct"] = max(out["f_pct"], 100 * abs(K[0, 0] / Kt[0, 0] - 1),
                           100 * abs(K[1, 1] / Kt[1, 1] - 1))
        out["pp_px"] = max(out["pp_px"], float(np.abs(K[:2, 2] - Kt[:2, 2]).max()))
        dR = a.R_array @ b.R_array.T
        ang = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
        out["rot_deg"] = max(out["rot_deg"], float(ang))
        out["t_mm"] = max(out["t_mm"], float(np.abs(a.T_array - b.T_array).max()))
    return out


def _distortion_field_error_px(dev, true_dev, uv: np.ndarray) -> float:
    """Largest difference (px) between the two devices' distortion displacement fields
    ``fx (distort(x) - x)`` at the normalised points of pixels uv (n, 2) (the true device's),
    so that a difference of principal point or focal length does not count."""
    xy = true_dev.normalized(uv)
    X = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    shift = []
    for d in (dev, true_dev):
        K1 = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1]])
        p, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K1, d.dist_array)
        shift.append((p.reshape(-1, 2) - xy) * true_dev.K_array[0, 0])
    return float(np.abs(shift[0] - shift[1]).max())


@pytest.fixture(scope="session")
def chess_run(tmp_path_factory):
    rig = calibration_rig(camera_dist=CAMERA_DIST)
    rc = render_capture(tmp_path_factory.mktemp("acc") / "chess", CHESS, rig,
                        default_poses(CHESS, POSES))
    return rc, calibrate(rc.directory, CHESS)


def test_chessboard_noise_free_with_distortion(chess_run):
    rc, result = chess_run
    err = _errors(result, rc.rig)
    _report("chessboard, noise-free, distortion", err)
    for k, bound in BOUNDS.items():
        assert err[k] <= bound, (k, err)
    for c in range(2):
        dev, true = result.rig.cameras[c], rc.rig.cameras[c]
        assert dev.dist_array[0] == pytest.approx(-0.1, abs=0.002)
        assert dev.dist_array[2] == pytest.approx(0.001, abs=5e-5)
        # over the part of the image the board covered (k3 is free beyond it)
        seen = np.concatenate([r.uv for r in result.residuals if r.device == f"camera_{c}"])
        assert _distortion_field_error_px(dev, true, seen) < 0.01
    assert len(result.poses) == POSES and len(result.residuals) == 3 * POSES


def test_circle_grid_noise_free(tmp_path_factory):
    rig = calibration_rig()
    rc = render_capture(tmp_path_factory.mktemp("acc") / "circles", CIRCLES, rig,
                        default_poses(CIRCLES, POSES))
    result = calibrate(rc.directory, CIRCLES, distortion=("k1k2", "k1k2", "k1k2"))
    err = _errors(result, rig)
    _report("asymmetric circle grid, noise-free", err)
    for k, bound in BOUNDS.items():
        assert err[k] <= bound, (k, err)


def test_twelve_bit_noise_and_thin_lens_within_twice_the_bounds(tmp_path_factory):
    rig = calibration_rig()
    settings = RenderSettings.model_validate({"camera": {
        "bit_depth": 12, "exposure_e": 9000.0, "full_well_e": 10000.0, "shot_noise": True,
        "read_noise_e": 10.0}})
    lens = AberratedLens(pupil_diameter_mm=2.0, focus_distance_mm=760.0, samples=8)
    rc = render_capture(tmp_path_factory.mktemp("acc") / "noisy", CHESS, rig,
                        default_poses(CHESS, POSES), lenses=[lens, lens], settings=settings,
                        seed=3)
    result = calibrate(rc.directory, CHESS, distortion=("k1k2", "k1k2", "k1k2"))
    err = _errors(result, rig)
    _report("chessboard, 12-bit noise, thin lens", err)
    for k, bound in BOUNDS.items():
        assert err[k] <= 2 * bound, (k, err)


def test_sphere_scanned_with_the_calibrated_rig(chess_run):
    rc, result = chess_run
    true = rc.rig
    pats = PhaseShiftSet(direction="u", periods_px=[1920.0, 240.0, 30.0], steps=4)
    geom = Scene(objects=[SphereObject(diameter_mm=50.8007)]).trace_geometry()
    res = render_views(geom, true, [PinholeLens(), PinholeLens()],
                       pats.images(true.projector.size),
                       RenderSettings.model_validate({"camera": {"bit_depth": 16}}),
                       np.random.default_rng(0))
    stacks = [c.images for c in res.cameras]
    d = {}
    for name, rig in (("true", true), ("calibrated", result.rig)):
        cloud = scan(stacks, pats, rig, DecodeSettings())
        d[name] = measure_sphere(cloud.points, 50.8007)[0]["diameter_mm"]
    _report("sphere diameter, mm", {**d, "difference_um": 1000 * (d["calibrated"] - d["true"])})
    assert abs(d["calibrated"] - d["true"]) < 0.002, d
