"""The real-scan folder's refusals: each one line naming the position and the camera, exit 1
(a missing position, images of mismatched sizes, a rig that does not fit the images, a lens
measured on another camera, an artefact not in the scan)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from realdata import PATTERNS, small_test_rig, sphere

from sim.optics.measured_lens import MeasuredLens, save_lens
from station.cli import main
from station.validation.folder import (
    BallBarArtefact,
    Pose,
    PositionFile,
    RealScanError,
    load_real_scan,
    write_position,
    write_scan_file,
)


def measured_lens_for(camera, K=None) -> MeasuredLens:
    """A small valid measured lens for ``camera`` (nodes every 32 px, 3 samples each)."""
    w, h = camera.size
    nu = np.r_[np.arange(0, w - 1, 32.0), w - 1.0]
    nv = np.r_[np.arange(0, h - 1, 32.0), h - 1.0]
    shape = (len(nv), len(nu), 3)
    x = np.broadcast_to(np.array([-1.0, 0.0, 1.0]), shape).copy()
    return MeasuredLens(focus_distance_mm=760.0, optical_centre_mm=np.zeros(3),
                        camera_size=(w, h), node_u=nu, node_v=nv, aperture_x_mm=x,
                        aperture_y_mm=np.zeros(shape), weights=np.full(shape, 1 / 3),
                        transmittance=np.ones(shape[:2]),
                        camera_matrix=camera.K_array if K is None else K,
                        dist_coeffs=np.zeros(5))


def flat_stacks(rig, size=None, n=None) -> list[np.ndarray]:
    count = n or len(PATTERNS.descriptors(tuple(rig.projector.size)))
    out = []
    for c in rig.cameras:
        w, h = size or c.size
        out.append(np.full((count, h, w), 1000.0))
    return out


@pytest.fixture
def folder(tmp_path) -> tuple[Path, object]:
    rig = small_test_rig((64, 48))
    write_scan_file(tmp_path / "real", rig, PATTERNS)
    write_position(tmp_path / "real", "S1", PositionFile(artefact=sphere()), flat_stacks(rig))
    (tmp_path / "thin.toml").write_text('kind = "thin"\npupil_diameter_mm = 4.0\n'
                                        'focus_distance_mm = 760.0\nsamples = 4\n')
    return tmp_path / "real", rig


def run_cli(capsys, *argv) -> tuple[int, str]:
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    return code, err[-1] if err else ""


def test_the_folder_reads_back(folder):
    real, rig = folder
    scan = load_real_scan(real)
    assert [p.name for p in scan.positions] == ["S1"]
    assert scan.rig.cameras[0].size == rig.cameras[0].size
    assert scan.spec.pixel_variance_px2 == pytest.approx(1 / 12)
    stacks = scan.positions[0].images(scan.rig, scan.patterns)
    assert stacks[1].shape == (12, 48, 64) and stacks[1].dtype == np.uint16
    assert np.all(stacks[0] == 1000)


def test_missing_position(folder, tmp_path, capsys):
    real, _ = folder
    code, line = run_cli(capsys, "validate", real, "--lenses", tmp_path / "thin.toml",
                         tmp_path / "thin.toml", "--positions", "S9", "--out", tmp_path / "o")
    assert code == 1 and line.startswith("ltc validate: error: position S9:")
    with pytest.raises(RealScanError, match="position S1: no position.toml"):
        (real / "positions" / "S1" / "position.toml").unlink()
        load_real_scan(real)


def test_mismatched_image_sizes(folder, tmp_path, capsys):
    real, rig = folder
    import cv2

    cv2.imwrite(str(real / "positions" / "S1" / "camera_1" / "pattern_005.png"),
                np.zeros((40, 64), np.uint16))
    code, line = run_cli(capsys, "validate", real, "--lenses", tmp_path / "thin.toml",
                         tmp_path / "thin.toml", "--out", tmp_path / "o")
    assert code == 1
    assert line.startswith("ltc validate: error: position S1, camera 1:")
    assert "pattern_005.png" in line and "64 x 40" in line


def test_a_rig_that_does_not_fit_the_images(folder, tmp_path, capsys):
    real, rig = folder
    other = small_test_rig((80, 48))
    (real / "rig.json").write_text(other.model_dump_json())
    code, line = run_cli(capsys, "validate", real, "--lenses", tmp_path / "thin.toml",
                         tmp_path / "thin.toml", "--out", tmp_path / "o")
    assert code == 1
    assert line.startswith("ltc validate: error: position S1, camera 0: images are 64 x 48 px")
    assert "80 x 48" in line and "rig does not fit" in line


def test_a_lens_measured_on_another_camera(folder, tmp_path, capsys):
    real, rig = folder
    good = save_lens(tmp_path / "good.npz", measured_lens_for(rig.cameras[0]))
    small = small_test_rig((32, 48)).cameras[0]
    wrong_size = save_lens(tmp_path / "size.npz", measured_lens_for(small))
    K = rig.cameras[1].K_array.copy()
    K[0, 0] += 2.0
    wrong_k = save_lens(tmp_path / "k.npz", measured_lens_for(rig.cameras[1], K))
    for bad, what in ((wrong_size, "32 x 48 camera"), (wrong_k, "camera matrix")):
        code, line = run_cli(capsys, "validate", real, "--lenses", good, bad, "--out",
                             tmp_path / "o")
        assert code == 1 and line.startswith("ltc validate: error: camera 1 (every position)")
        assert what in line
    # the Python API refuses it too
    from sim.optics.measured_lens import load_lens
    from sim.render.scene import Scene, SphereObject
    from sim.scanner import Scanner

    s = Scanner(rig, (load_lens(good), load_lens(good)), PATTERNS,
                Scene(objects=[SphereObject(name="s")]))
    with pytest.raises(ValueError, match="camera 1: .*camera matrix"):
        s.with_lenses([load_lens(good), load_lens(wrong_k)])


@pytest.mark.slow
def test_an_artefact_not_in_the_scan(tmp_path, capsys):
    """The images show the 50.8 mm sphere; the position file says a ball bar of 38.1 mm
    balls: refused naming the position."""
    from realdata import thin_lens, world_point, write_real_folder

    real = tmp_path / "real"
    write_real_folder(real, {"B1": ("slight", sphere(), Pose(t=world_point(0.0)))},
                      small_test_rig((96, 64)), lens=thin_lens(4.0, 4), factor=1)
    pf = PositionFile(artefact=BallBarArtefact(ball_diameter_mm=38.1,
                                               centre_distance_mm=209.8))
    import tomli_w

    (real / "positions" / "B1" / "position.toml").write_text(
        tomli_w.dumps(pf.model_dump(mode="json", exclude_none=True)))
    (tmp_path / "thin.toml").write_text('kind = "thin"\npupil_diameter_mm = 4.0\n'
                                        'focus_distance_mm = 760.0\nsamples = 4\n')
    code, line = run_cli(capsys, "validate", real, "--lenses", tmp_path / "thin.toml",
                         tmp_path / "thin.toml", "--out", tmp_path / "o")
    assert code == 1
    assert line.startswith("ltc validate: error: position B1: artefact not found")
    assert "38.1 mm" in line
    assert json.loads((tmp_path / "o" / "validation.json").read_text())["positions"] == ["B1"]
    # each position folder is what ltc scan reads; it says what each check rejected
    code = main(["scan", str(real / "positions" / "B1"), "--rig", str(real / "rig.json"),
                 "--patterns", str(real / "patterns.json"), "--out", str(tmp_path / "b.ply")])
    out = capsys.readouterr().out.splitlines()
    assert code == 0 and out[1].startswith("camera 0: ") and "pixels decoded; rejected: " \
        "modulation" in out[1] and out[2].startswith("camera 1: ")
