"""Cloud against cloud by pixel correspondence (``compare_by_pixel``): the comparison the
experiment uses sets no floor of its own."""

from __future__ import annotations

import numpy as np

from sim.metrology.compare import compare_by_pixel, compare_clouds
from sim.optics.lens import PinholeLens
from sim.render.fringe_patterns import PhaseShiftSet
from sim.render.images import RenderSettings
from sim.render.scene import Scene, SphereObject
from sim.scanner import Scanner
from station.experiment.run import build_rig, ExperimentConfig

NOISY = {"projector": {"input_bits": 8},
         "camera": {"exposure_e": 8000.0, "full_well_e": 10000.0, "bit_depth": 12,
                    "shot_noise": True, "read_noise_e": 5.0}}


def test_pinhole_against_pinhole_with_another_noise_seed_is_zero_on_average():
    rig = build_rig(ExperimentConfig())
    scene = Scene(objects=[SphereObject(name="s", pose={"t": [0.0, 0.0, -20.0]})])
    patterns = PhaseShiftSet(periods_px=[256.0, 32.0, 8.0], steps=4, direction="u")
    base = Scanner(rig, (PinholeLens(), PinholeLens()), patterns, scene,
                   RenderSettings.model_validate(NOISY))
    a, b = (base.scan(base.render(rng=np.random.default_rng(s))) for s in (0, 1))
    same = compare_by_pixel(a, a)
    assert same.mean == 0 and same.rmse == 0 and same.unmatched == (0, 0)
    c = compare_by_pixel(b, a)
    n = c.distances.size
    assert n > 200
    # noise only: the mean is zero within its standard error, the RMSE is the noise's
    assert abs(c.mean) < 4 * c.rmse / np.sqrt(n)
    nn = compare_clouds(b.points, a.points, align=False)
    assert c.rmse < nn.rmse  # the rims' differing points no longer count
    # every compared point is a pixel both clouds measured, away from the silhouette
    assert c.index.max() < len(b.points) and n <= len(a.points) - 50


def test_smoothing_a_measured_lens_removes_node_noise_and_keeps_the_field():
    """Node-to-node noise in the aperture's shape averages out, the slow field dependence
    stays, and each node keeps its own samples' centroid (its principal ray) exactly."""
    from sim.optics.measured_lens import MeasuredLens, smoothed_lens

    rng = np.random.default_rng(3)
    gv, gu, k = 12, 16, 8
    nu, nv = np.arange(gu) * 4.0, np.arange(gv) * 4.0
    base = np.linspace(-3, 3, k)
    field = 0.02 * nu[None, :, None] + 0.01 * nv[:, None, None]  # slow shift with the field, mm
    stretch = 1.0 + 0.01 * nu[None, :, None]  # the shape changes slowly with the field
    truth_x = base[None, None] * stretch + field
    noise = rng.normal(0, 0.3, truth_x.shape)
    noise -= noise.mean(axis=2, keepdims=True)  # shape noise; the centroid is the ray's
    noisy = truth_x + noise
    w = np.full((gv, gu, k), 1 / k)
    lens = MeasuredLens(800.0, np.zeros(3), (64, 48), nu, nv, noisy, np.zeros_like(noisy), w,
                        np.ones((gv, gu)), "bilinear")
    assert smoothed_lens(lens, 0) is lens
    s = smoothed_lens(lens, 2)
    inner = (slice(3, -3), slice(3, -3))
    err = lambda a: np.sqrt(np.mean((a[inner] - truth_x[inner]) ** 2))
    assert err(s.aperture_x_mm) < 0.3 * err(noisy)  # noise averaged over ~25 nodes
    np.testing.assert_allclose(s.weights.sum(axis=2), 1.0)
    np.testing.assert_allclose((s.aperture_x_mm * s.weights).sum(axis=2),
                               truth_x.mean(axis=2), atol=1e-12)
