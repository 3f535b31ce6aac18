"""The validation experiment (``benchmarks/validation.py``), reduced to its core claim: on the
``--quick`` configuration the station measures the rig camera's lens on the fake bench, and at a
large-defocus sphere position the scanner with that lens reproduces the real scanner's cloud far
more closely than the Gaussian baseline does. Plus the experiment's pieces against known answers."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from fakes.bench import FakeBench
from fakes.hardware import parse_fake_settings
from sim.optics.measured_lens import (MeasuredLens, centre_moments, gaussian_equivalent, load_lens,
                                      save_lens)
from sim.optics.rig import DeviceCalibration

ROOT = Path(__file__).resolve().parents[2]


def _load_benchmark():
    spec = importlib.util.spec_from_file_location("validation_benchmark",
                                                  ROOT / "benchmarks" / "validation.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


V = _load_benchmark()


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    """The reduced experiment: station run, lens, and one large-defocus position compared."""
    cfg = V.quick_config()
    rig = V.build_rig(cfg)
    out = tmp_path_factory.mktemp("validation")
    lens_path, station = V.measure_lens(cfg, rig, out)
    measured = load_lens(lens_path)
    lenses = V.scanner_lenses(cfg, measured)
    large = next(p for p in V.positions(cfg, rig) if p.group == "large")
    row = V.compare_position(cfg, rig, large, lenses)
    return cfg, rig, station, measured, lenses, row


def _lens(x, y, w, size=(9, 7), K=None) -> MeasuredLens:
    """A one-node measured lens with the given aperture samples (mm) and weights."""
    k = len(w)
    return MeasuredLens(focus_distance_mm=500.0, optical_centre_mm=np.zeros(3), camera_size=size,
                        node_u=np.array([0.0]), node_v=np.array([0.0]),
                        aperture_x_mm=np.reshape(x, (1, 1, k)),
                        aperture_y_mm=np.reshape(y, (1, 1, k)),
                        weights=np.reshape(np.asarray(w) / np.sum(w), (1, 1, k)),
                        transmittance=np.ones((1, 1)), camera_matrix=K)


def test_the_measured_lens_reproduces_the_real_scanner_at_large_defocus_and_the_gaussian_does_not(
        quick):
    row = quick[-1]
    assert row["group"] == "large" and row["defocus_mm"] < -100
    m, g, p = row["measured"], row["gaussian"], row["pinhole"]
    # the real lens's vignetting makes the real scanner err by far more than the noise floor,
    # which the Gaussian (centred, the same for every pixel) cannot reproduce, like the pinhole
    assert abs(g["mean_mm"]) > 0.3 and g["rmse_mm"] > 0.3
    assert abs(p["mean_mm"]) > 0.3
    # the measured lens makes the same errors as the real one
    assert abs(m["mean_mm"]) < 0.1 * abs(g["mean_mm"])
    assert m["rmse_mm"] < 0.2 * g["rmse_mm"]
    assert m["rmse_mm"] < 0.1
    assert m["centre_vs_real_mm"] < 0.2 * g["centre_vs_real_mm"]
    assert V.summary([row])["claim_holds"]


def test_the_station_measures_the_rig_cameras_lens(quick):
    cfg, rig, station, measured, lenses, _ = quick
    assert min(station["valid_fraction"]) > 0.99
    np.testing.assert_allclose(measured.camera_matrix, rig.cameras[0].K_array, atol=1e-12)
    true_centre = [(cfg.lcd_size[0] - 1) / 2 * cfg.lcd_pitch_mm,
                   (cfg.lcd_size[1] - 1) / 2 * cfg.lcd_pitch_mm, -cfg.lcd_distance_at_zero_mm]
    np.testing.assert_allclose(station["lens"]["optical_centre_mm"], true_centre, atol=0.1)
    # spherical aberration: the plane of least blur lies between the paraxial and rim foci
    assert cfg.focus_distance_mm - 5 < measured.focus_distance_mm < (
        cfg.focus_distance_mm + cfg.spherical_mm + 5)
    # the Gaussian's width is the measured pupil's: a uniform disk of radius R has sigma R / 2
    r = lenses["real"].pupil_radius_mm
    assert lenses["gaussian"].sigma_mm == pytest.approx(r / 2, rel=0.1)
    assert lenses["gaussian"].focus_distance_mm == measured.focus_distance_mm


def test_station_config_makes_the_bench_camera_the_rig_camera():
    cfg = V.quick_config()
    cam = V.build_rig(cfg).cameras[0]
    config = V.station_config(cfg, cam)
    bench = FakeBench(parse_fake_settings(config.fake).bench_config())
    np.testing.assert_allclose(bench.K, cam.K_array, rtol=1e-12)
    assert tuple(bench.config.camera_size) == tuple(cam.size)
    truth = V.truth_lens(cfg, bench.config.pupil_samples)
    assert bench.lens == truth
    np.testing.assert_allclose(config.camera.matrix, cam.K_array)
    assert config.display.pitch_mm == bench.config.lcd_pitch_mm == cfg.lcd_pitch_mm


def test_cropped_rig_cameras_look_at_the_world_origin_from_the_working_distance():
    cfg = V.quick_config()
    rig = V.build_rig(cfg)
    for cam in rig.cameras:
        w, h = cfg.camera_size
        np.testing.assert_allclose(cam.project(np.zeros((1, 3))), [[(w - 1) / 2, (h - 1) / 2]],
                                   atol=1e-9)
        assert cam.to_device(np.zeros((1, 3)))[0, 2] == pytest.approx(cfg.focus_distance_mm)
    assert not np.any([c.dist_array for c in rig.cameras])


@pytest.mark.parametrize("change, message", [
    ({"K": [[100.0, 0, 5.0], [0, 100.0, 3.0], [0, 0, 1]]}, "principal point at the sensor centre"),
    ({"K": [[100.0, 0, 4.0], [0, 101.0, 3.0], [0, 0, 1]]}, "square pixels"),
    ({"dist": [0.1, 0, 0, 0, 0]}, "has no distortion"),
])
def test_station_config_refuses_a_camera_the_bench_cannot_be(change, message):
    base = {"name": "cam", "K": [[100.0, 0, 4.0], [0, 100.0, 3.0], [0, 0, 1]],
            "dist": [0.0] * 5, "R": np.eye(3), "T": [0.0, 0.0, 0.0], "size": (9, 7)}
    cam = DeviceCalibration(**{**base, **change})
    with pytest.raises(ValueError, match=message):
        V.station_config(V.quick_config(), cam)


def test_gaussian_baseline_takes_the_second_moment_at_the_optical_centre():
    a = 3.0
    lens = _lens([a, -a, 0, 0], [0, 0, a, -a], [1, 1, 1, 1],
                 K=np.array([[50.0, 0, 4.0], [0, 50.0, 3.0], [0, 0, 1]]))
    mean, cov = centre_moments(lens)
    np.testing.assert_allclose(mean, 0, atol=1e-12)
    np.testing.assert_allclose(cov, np.diag([a * a / 2, a * a / 2]), atol=1e-12)
    g = gaussian_equivalent(lens)
    assert g.sigma_mm == pytest.approx(a / np.sqrt(2))
    assert (g.focus_distance_mm, g.samples) == (500.0, 4)
    b = g.bundle(np.zeros((1, 2)))
    w, xy = b.weights[0], b.origins[0, :, :2]
    assert np.mean(w @ xy**2) == pytest.approx(a * a / 2, rel=1e-9)  # per-axis variance


def test_summary_averages_per_group_and_judges_the_claim_at_every_large_position():
    def row(group, m, g):
        r = {"group": group}
        for n in V.LENSES:
            r[n] = {"mean_mm": 0.0, "rmse_mm": 1.0}
        r["measured"] = {"mean_mm": m[0], "rmse_mm": m[1]}
        r["gaussian"] = {"mean_mm": g[0], "rmse_mm": g[1]}
        return r

    rows = [row("slight", (0.01, 0.02), (-0.03, 0.04)), row("large", (-0.1, 0.2), (0.5, 0.6)),
            row("large", (0.3, 0.2), (0.5, 0.6))]
    s = V.summary(rows)
    assert s["large"]["measured"]["abs_mean_mm"] == pytest.approx(0.2)
    assert s["large"]["gaussian"]["rmse_mm"] == pytest.approx(0.6)
    assert s["slight"]["gaussian"]["abs_mean_mm"] == pytest.approx(0.03)
    assert s["claim_holds"]
    rows.append(row("large", (0.1, 0.7), (0.5, 0.6)))  # one position where the RMSE is worse
    assert not V.summary(rows)["claim_holds"]
    assert "| L" not in V.tables([]) and not V.summary([])["claim_holds"]


def test_an_output_folder_holding_a_run_is_refused(tmp_path):
    (tmp_path / "run.zarr").mkdir()
    with pytest.raises(FileExistsError, match="already holds run.zarr"):
        V.check_out_dir(tmp_path)
    V.check_out_dir(tmp_path / "new")  # a new folder is fine


def test_a_lens_for_another_camera_is_refused(tmp_path):
    path = save_lens(tmp_path / "lens.npz", _lens([0.0], [0.0], [1.0], size=(9, 7)))
    with pytest.raises(ValueError, match=r"lens is for a \(9, 7\) camera"):
        V.main(["--out", str(tmp_path / "out"), "--lens", str(path), "--quick", "--quiet"])


def test_readme_section_is_replaced_or_appended_and_nothing_else_changes(tmp_path):
    path = tmp_path / "README.md"
    path.write_text(f"# B\n\n## Rendering\nkeep\n\n{V.SECTION}\nold\n### Results\nold\n\n"
                    "## Other\nkeep too\n")
    V.write_readme(f"{V.SECTION}\n\nnew\n", path)
    assert path.read_text() == (f"# B\n\n## Rendering\nkeep\n\n{V.SECTION}\n\nnew\n\n"
                                "## Other\nkeep too\n")
    path.write_text("# B\n\n## Rendering\nkeep\n\n")
    V.write_readme(f"{V.SECTION}\n\nnew\n", path)
    assert path.read_text() == f"# B\n\n## Rendering\nkeep\n\n{V.SECTION}\n\nnew\n"
    with pytest.raises(FileNotFoundError, match="not found"):
        V.write_readme("x", tmp_path / "missing.md")
