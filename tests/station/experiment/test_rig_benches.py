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
