"""The experiment's rig and station benches against what they are built from: each camera's
fake bench is that rig camera (K, sensor) carrying its own ground-truth lens."""

from __future__ import annotations

import numpy as np
import pytest

from fakes.bench import FakeBench
from fakes.hardware import parse_fake_settings
from station.experiment.run import ExperimentConfig, build_rig, station_config, truth_lens


def test_each_station_bench_is_its_rig_camera_with_its_own_true_lens():
    cfg = ExperimentConfig()
    rig = build_rig(cfg)
    lenses = []
    for i, cam in enumerate(rig.cameras):
        config = station_config(cfg, rig, i)
        bench = FakeBench(parse_fake_settings(config.fake).bench_config())
        np.testing.assert_allclose(bench.K, cam.K_array, rtol=1e-12)
        assert tuple(bench.config.camera_size) == tuple(cam.size)
        assert bench.lens == truth_lens(cfg, i, cfg.bench_samples)
        # the real scanner's lens is the same lens, sampled more densely
        assert truth_lens(cfg, i, cfg.real_samples) == bench.lens.model_copy(
            update={"samples": cfg.real_samples})
        np.testing.assert_allclose(config.camera.matrix, cam.K_array)
        assert config.display.pitch_mm == bench.config.lcd_pitch_mm == cfg.lcd_pitch_mm
        lenses.append(bench.lens)
    assert lenses[0] != lenses[1]  # the two cameras' lenses differ, as the issue asks


def test_cropped_rig_cameras_look_at_the_world_origin_from_the_working_distance():
    cfg = ExperimentConfig()
    rig = build_rig(cfg)
    w, h = cfg.camera_size
    for cam in rig.cameras:
        np.testing.assert_allclose(cam.project(np.zeros((1, 3))), [[(w - 1) / 2, (h - 1) / 2]],
                                   atol=1e-9)
        assert cam.to_device(np.zeros((1, 3)))[0, 2] == pytest.approx(cfg.focus_distance_mm)
    assert not np.any([c.dist_array for c in rig.cameras])


def test_every_object_of_the_built_in_configs_lies_in_both_crops():
    """``check_views`` passes the demo and the --paper-size configs, and its pixel box is the
    one a pinhole render lights (an independent renderer, the demo's near ball bar)."""
    from sim.optics.lens import PinholeLens
    from sim.render.fringe_patterns import PhaseShiftSet
    from sim.render.images import RenderSettings
    from sim.scanner import Scanner
    from station.experiment.run import (
        RENDER,
        check_views,
        paper_size_config,
        positions,
        scene_of,
        view_extents_px,
    )

    for cfg in (ExperimentConfig(), paper_size_config()):
        check_views(cfg, build_rig(cfg))
    cfg = ExperimentConfig()
    rig = build_rig(cfg)
    pos = next(p for p in positions(cfg, rig) if p.name == "B3")
    scanner = Scanner(rig, (PinholeLens(), PinholeLens()),
                      PhaseShiftSet(periods_px=[256.0], steps=4, direction="u"),
                      scene_of(pos, cfg, None), RenderSettings.model_validate(RENDER))
    images = scanner.render()
    for cam, (u0, u1, v0, v1) in zip(images.cameras, view_extents_px(pos, cfg, rig), strict=True):
        v, u = np.nonzero(cam.images.max(axis=0) > 0)
        # lit pixels: those whose centre's ray meets a ball, within the box, touching it
        assert u0 - 0.5 <= u.min() <= u0 + 1.5 and u1 - 1.5 <= u.max() <= u1 + 0.5
        assert v0 - 0.5 <= v.min() <= v0 + 1.5 and v1 - 1.5 <= v.max() <= v1 + 0.5


def test_an_object_outside_a_crop_is_refused_before_anything_is_written(tmp_path, capsys):
    from station.cli import main

    # the paper-size crop's near large-defocus ball bar as first configured: it stopped a
    # 3-hour run at its stereo match, one camera seeing one ball, the other the other
    bad = tmp_path / "b3.toml"
    bad.write_text("ballbar_large = [[-120.0, 0.0]]\nballbar_large_roll_deg = 20.0\n")
    out = tmp_path / "out"
    assert main(["experiment", str(bad), "--paper-size", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "B3 (ballbar at z -120 mm) overhangs camera 0's 1536 x 768 crop" in err
    assert "camera 1's" in err and "ballbar_" in err and not out.exists()
