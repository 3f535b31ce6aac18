"""``ltc lens``: from an LTC store on disk to a lens file, a JSON report and figures."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fakes.bench import BenchConfig, FakeBench
from ltc_stores import write_true_ltc_store
from sim.optics.measured_lens import load_lens
from sim.optics.rig import Rig, small_rig
from station.cli import main

P = 24
DEPTHS = [0.0, 30.0, 60.0, 250.0, 290.0]
PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def bench() -> FakeBench:
    return FakeBench(BenchConfig.small(lcd_size=(120, 96), lcd_distance_at_zero_mm=100.0,
                                       pupil_samples=150, subpixels=1))


def write_store(path, bench: FakeBench, with_k: bool = True):
    """An LTC store of the bench's true LTC plus noise of std 6e-4 per weight."""
    return write_true_ltc_store(path, bench, DEPTHS, period=P, with_k=with_k)


@pytest.fixture(scope="module")
def store(tmp_path_factory, bench):
    return write_store(tmp_path_factory.mktemp("cli") / "ltc.zarr", bench)


def test_lens_json_figures_and_file(tmp_path, store, bench, capsys):
    out, figs = tmp_path / "lens.npz", tmp_path / "figs"
    assert main(["lens", str(store), "--out", str(out), "--json", "--figures", str(figs),
                 "--grid-step", "2", "--basic"]) == 0
    report = json.loads(capsys.readouterr().out)
    lens = load_lens(out)
    assert report["out"] == str(out) and report["samples"] == 32 == lens.samples
    assert report["nodes"] == [16, 21] and lens.weights.shape == (16, 21, 32)
    np.testing.assert_array_equal(lens.camera_matrix, bench.K)
    np.testing.assert_allclose(report["optical_centre_mm"], lens.optical_centre_mm)
    assert np.linalg.norm(lens.optical_centre_mm - bench.optical_centre_station_mm()) < 0.5
    assert report["focus_distance_mm"] == pytest.approx(lens.focus_distance_mm)
    assert report["ray_residual_mean_mm"] > 0 and report["ray_residual_std_mm"] > 0
    assert sorted(p.name for p in figs.iterdir()) == [
        "aperture.png", "ltc_depths.png", "principal_rays.png", "ray_residuals.png"]
    for p in figs.iterdir():
        assert p.read_bytes()[:8] == PNG and p.stat().st_size > 10_000
    assert report["figures"] == [str(figs / n) for n in ("ltc_depths.png", "principal_rays.png",
                                                        "aperture.png", "ray_residuals.png")]


def test_lens_options_and_text_report(tmp_path, store, capsys):
    out = tmp_path / "lens.npz"
    rc = main(["lens", str(store), "--out", str(out), "--samples", "12", "--grid-step", "10",
               "--interpolation", "nearest", "--focus-mm", "250", "--basic"])
    text = capsys.readouterr().out
    assert rc == 0
    lens = load_lens(out)
    assert lens.samples == 12 and lens.interpolation == "nearest"
    np.testing.assert_array_equal(lens.node_u, [0, 10, 20, 30, 39])
    np.testing.assert_array_equal(lens.node_v, [0, 10, 20, 29])
    assert lens.focus_distance_mm == pytest.approx(250.0)
    assert "optical centre" in text and "configured 250.000 mm" in text
    assert "focus distance: configured 250.000 mm (used), fitted" in text


def test_rig_gives_the_camera_matrix(tmp_path, bench, capsys):
    store = write_store(tmp_path / "nok.zarr", bench, with_k=False)
    base = small_rig()
    cam = base.cameras[0].model_copy(update={"K": bench.K.tolist(), "dist": [0.0] * 5,
                                             "size": bench.config.camera_size})
    rig = Rig(cameras=[cam, base.cameras[1]], projector=base.projector)
    rig_path = tmp_path / "rig.json"
    rig.save(rig_path)
    out = tmp_path / "lens.npz"
    assert main(["lens", str(store), "--out", str(out), "--json", "--grid-step", "8",
                 "--rig", str(rig_path), "--rig-camera", cam.name]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["camera_matrix_known"] and report["optical_centre_method"].startswith("pinhole")
    np.testing.assert_array_equal(load_lens(out).camera_matrix, bench.K)
    assert main(["lens", str(store), "--out", str(tmp_path / "b.npz"), "--rig",
                 str(rig_path), "--rig-camera", "nope"]) == 1
    assert "no camera named 'nope'; cameras are" in capsys.readouterr().err
    assert main(["lens", str(store), "--out", str(tmp_path / "b.npz"), "--rig",
                 str(rig_path), "--rig-camera", base.cameras[1].name]) == 1
    assert "is (164, 87) pixels but the LTC store's camera is (40, 30)" in capsys.readouterr().err
    assert main(["lens", str(store), "--out", str(tmp_path / "c.npz"), "--json",
                 "--grid-step", "8"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert not report["camera_matrix_known"]
    assert any("principal-ray intersection" in n for n in report["notes"])


def test_errors_are_reported_not_raised(tmp_path, store, capsys):
    out = tmp_path / "lens.npz"
    assert main(["lens", str(tmp_path / "none.zarr"), "--out", str(out)]) == 1
    assert "ltc lens: error:" in (err := capsys.readouterr().err) and "no such LTC store" in err
    out.write_bytes(b"x")
    assert main(["lens", str(store), "--out", str(out)]) == 2
    assert f"{out} exists; pass --force to overwrite it" in capsys.readouterr().err
    with pytest.raises(SystemExit) as usage:  # argparse refuses the value
        main(["lens", str(store), "--out", str(out), "--force", "--samples", "0"])
    assert usage.value.code == 2
    assert "argument --samples: must be >= 1, got 0" in capsys.readouterr().err
    assert main(["lens", str(store), "--out", str(out), "--force"]) == 2  # not a lens file
    assert "is a file but not a lens file" in capsys.readouterr().err and out.read_bytes() == b"x"
    out.unlink()
    assert main(["lens", str(store), "--out", str(out), "--focus-mm", "250",
                 "--centre", "rays", "--grid-step", "10"]) == 0
    assert load_lens(out).focus_distance_mm == pytest.approx(250.0)


def test_the_recommended_settings_are_the_defaults_everywhere():
    """``ltc lens`` without options, ``ltc run`` without [sequence] lens_* and the experiment
    all derive with ``LensFitConfig()``: the recommended settings."""
    from station.api import lens_config
    from station.experiment.bench import build_rig, station_config
    from station.experiment.config import ExperimentConfig
    from station.lens.geometry import LensFitConfig

    rec = LensFitConfig()
    assert (rec.samples, rec.grid_step, rec.aperture_cells, rec.deconvolve_iterations,
            rec.support_floor, rec.focus_zones, rec.aim_offset_sigma_px) == (
        256, 4, 64, 20, 0.1, True, 8.0)
    assert lens_config() == rec
    cfg = ExperimentConfig()
    seq = station_config(cfg, build_rig(cfg), 0).sequence
    assert lens_config(samples=seq.lens_samples, grid_step=seq.lens_grid_step,
                       pixel_samples=seq.lens_pixel_samples, **seq.lens_settings) == rec
    basic = LensFitConfig.basic()
    assert (basic.samples, basic.grid_step, basic.focus_zones) == (32, 1, False)


def test_the_text_report_formats_every_figure_with_units():
    from station.commands.lens import text

    r = {"optical_centre_mm": [1.0, 2.0, -100.0], "optical_centre_std_mm": [0.001] * 3,
         "optical_centre_method": "pinhole", "principal_ray_intersection_mm": [1.0, 2.0, -99.0],
         "focus_plane_z_mm": 150.0, "focus_distance_mm": 250.0,
         "focus_distance_fitted_mm": None, "focus_distance_config_mm": 250.0,
         "ray_residual_mean_mm": None, "ray_residual_std_mm": None, "ray_residual_count": 0,
         "pixels_usable": 10, "pixels": 12, "pixels_few_depths": 1,
         "pixels_outlier_removed": 0, "pixels_bad_fit": 1, "samples": 256, "nodes": [3, 4],
         "nodes_filled": 0, "aperture_cells": 64, "aperture_half_width_mm": 4.5,
         "camera_rotation_deg": 0.25, "notes": [], "figures": [], "out": "lens.npz"}
    out = text(r)
    assert "None" not in out
    assert "fitted n/a, configured 250.000 mm" in out
    assert "mean n/a, std n/a over 0 points" in out
    assert "(1.0000, 2.0000, -100.0000) mm" in out and "0.250 deg" in out
