"""The one sensor model: statistics against its own analytic mean and variance, and the
renderer's cameras and the fake station camera built on it."""

import numpy as np
import pytest

from fakes.camera import NoiseModel
from sim.optics.sensor import Sensor
from sim.render.images import CameraResponse, camera_response


def test_mean_and_variance_match_the_model():
    s = Sensor(full_well_e=10000.0, dn_per_e=0.4, black_level_dn=16.0, bit_depth=12,
               read_noise_e=5.0)
    rng = np.random.default_rng(3)
    for e in (50.0, 800.0, 5000.0):
        dn = s.digitise(s.expose(np.full(200_000, e), rng)).astype(np.float64)
        four_sigma = 4 * np.sqrt(float(s.variance_dn(e)) / dn.size)
        assert dn.mean() == pytest.approx(float(s.mean_dn(e)), abs=four_sigma)
        assert dn.var() == pytest.approx(float(s.variance_dn(e)), rel=0.02)


def test_saturation_clipping_and_noise_free():
    s = Sensor(full_well_e=1000.0, dn_per_e=255 / 1000, bit_depth=8, shot_noise=False)
    assert not s.noisy
    e = np.array([-5.0, 0.0, 500.0, 1000.0, 5000.0])
    out = s.digitise(s.expose(e, None))
    assert out.dtype == np.uint8
    np.testing.assert_array_equal(out, [0, 0, 128, 255, 255])  # 127.5 rounds half to even
    with pytest.raises(ValueError, match="rng is required"):
        Sensor(full_well_e=1.0, dn_per_e=1.0).expose(e, None)


def test_renderer_and_fake_camera_share_it():
    fake = NoiseModel(bit_depth=12, black_level_adu=16.0, full_well_e=10000.0, read_noise_e=5.0)
    render = CameraResponse(full_well_e=10000.0, gain=(4095 - 16) / 4095, black_level_dn=16.0,
                            bit_depth=12, shot_noise=True, read_noise_e=5.0)
    a, b = fake.sensor, render.sensor
    assert (a.full_well_e, a.black_level_dn, a.bit_depth, a.shot_noise, a.read_noise_e) == \
        (b.full_well_e, b.black_level_dn, b.bit_depth, b.shot_noise, b.read_noise_e)
    assert a.dn_per_e == pytest.approx(b.dn_per_e, rel=1e-12)
    # the renderer's noisy path is the sensor's float32 path, then its compiled rounding
    radiance = np.random.default_rng(0).uniform(0, 1.3, (40, 50)).astype(np.float32)
    got = camera_response(radiance, render, np.random.default_rng(9))
    e = np.maximum(radiance * np.float32(render.exposure_e), np.float32(0))
    want = b.digitise(b.expose(e, np.random.default_rng(9), np.float32))
    assert np.abs(got.astype(int) - want.astype(int)).max() <= 1  # float32 vs float64 DN
    assert np.mean(got != want) < 1e-3


def test_gaussian_exposure_has_the_model_mean_and_variance():
    s = Sensor(full_well_e=10000.0, dn_per_e=0.4, black_level_dn=16.0, bit_depth=12,
               read_noise_e=5.0)
    rng = np.random.default_rng(4)
    for e in (300.0, 5000.0):
        dn = s.digitise(s.expose_gaussian(np.full(200_000, e), rng)).astype(np.float64)
        four_sigma = 4 * np.sqrt(float(s.variance_dn(e)) / dn.size)
        assert dn.mean() == pytest.approx(float(s.mean_dn(e)), abs=four_sigma)
        assert dn.var() == pytest.approx(float(s.variance_dn(e)), rel=0.02)
    full = s.expose_gaussian(np.array([1e6], np.float32), rng)
    assert full[0] == 10000.0  # clipped at the full well
