"""Cloud against cloud by pixel correspondence (``compare_by_pixel``): the comparison the
experiment uses sets no floor of its own."""

from __future__ import annotations

import numpy as np
import pytest

from sim.metrology.compare import compare_by_pixel
from sim.optics.lens import PinholeLens
from sim.render.fringe_patterns import PhaseShiftSet
from sim.render.images import RenderSettings
from sim.render.scene import Scene, SphereObject
from sim.scanner import Scanner
from station.experiment.run import ExperimentConfig, build_rig

NOISY = {"projector": {"input_bits": 8},
         "camera": {"exposure_e": 8000.0, "full_well_e": 10000.0, "bit_depth": 12,
                    "shot_noise": True, "read_noise_e": 5.0}}


def test_pinhole_against_pinhole_with_another_noise_seed_is_zero_on_average():
    rig = build_rig(ExperimentConfig())
    sphere = SphereObject(name="s", pose={"t": [0.0, 0.0, -20.0]})
    scene = Scene(objects=[sphere])
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
    # and it is the noise's: the two points of a pixel lie on one camera ray, so they differ
    # by as much as their deviations from the true sphere (the common systematic part cancels)
    centre, radius = np.array([0.0, 0.0, -20.0]), sphere.diameter_mm / 2
    key = {k: i for i, k in enumerate(zip(*(a.fields[f] for f in ("camera", "v", "u")),
                                          strict=True))}
    ref = [key[k] for k in zip(*(b.fields[f][c.index] for f in ("camera", "v", "u")),
                               strict=True)]
    dev_b = np.linalg.norm(b.points[c.index] - centre, axis=1) - radius
    dev_a = np.linalg.norm(a.points[ref] - centre, axis=1) - radius
    assert c.rmse == pytest.approx(np.sqrt(np.mean((dev_b - dev_a) ** 2)), rel=0.02)
    assert c.rmse < np.sqrt(np.mean(dev_a**2) + np.mean(dev_b**2))
    # every compared point is a pixel both clouds measured, away from the silhouette
    assert c.index.max() < len(b.points) and n <= len(a.points) - 50


def test_smoothing_a_measured_lens_removes_node_noise_and_keeps_the_field():
    """Node-to-node noise in the aperture's shape averages out, the slow field dependence
    stays, and the centroids' linear field (the principal rays) passes exactly. The
    aperture is a 3 mm disk of K = 64 sunflower samples (as the station's ring strata spread
    them), stretched along x with the field."""
    from sim.optics.measured_lens import MeasuredLens, smoothed_lens

    rng = np.random.default_rng(3)
    gv, gu, k = 12, 16, 64
    nu, nv = np.arange(gu) * 4.0, np.arange(gv) * 4.0
    j = np.arange(k)
    r, t = 3.0 * np.sqrt((j + 0.5) / k), j * np.pi * (3.0 - np.sqrt(5.0))
    field = 0.02 * nu[None, :, None] + 0.01 * nv[:, None, None]  # slow shift with the field, mm
    stretch = 1.0 + 0.01 * nu[None, :, None]  # the shape changes slowly with the field
    truth_x = r * np.cos(t) * stretch + field
    truth_y = np.broadcast_to(r * np.sin(t), truth_x.shape)
    noise = rng.normal(0, 0.3, (2,) + truth_x.shape)
    noise -= noise.mean(axis=3, keepdims=True)  # shape noise; the centroid is the ray's
    noisy_x, noisy_y = truth_x + noise[0], truth_y + noise[1]
    w = np.full((gv, gu, k), 1 / k)
    lens = MeasuredLens(800.0, np.zeros(3), (64, 48), nu, nv, noisy_x, noisy_y, w,
                        np.ones((gv, gu)), "bilinear")
    assert smoothed_lens(lens, 0) is lens
    s = smoothed_lens(lens, 2)
    inner = (slice(3, -3), slice(3, -3))
    def err(a, b):
        return np.sqrt(np.mean((a[inner] - b[inner]) ** 2))
    for got, noisy, truth in ((s.aperture_x_mm, noisy_x, truth_x),
                              (s.aperture_y_mm, noisy_y, truth_y)):
        assert err(got, truth) < 0.3 * err(noisy, truth)  # noise averaged over ~25 nodes
    np.testing.assert_allclose(s.weights.sum(axis=2), 1.0)
    np.testing.assert_allclose((s.aperture_x_mm * s.weights).sum(axis=2),
                               truth_x.mean(axis=2), atol=1e-12)


def test_smoothing_keeps_the_apertures_size_when_samples_do_not_correspond():
    """Nodes holding the same elliptical aperture with its samples in a different order at
    every node: averaging the samples alone would collapse the aperture towards its centroid;
    the smoothed lens keeps every node's centroid, second moment (mm^2) and radial profile
    (a disk stays a disk: its normalised fourth moment within 2 %)."""
    from sim.optics.measured_lens import MeasuredLens, smoothed_lens

    rng = np.random.default_rng(5)
    gv, gu, k = 9, 11, 64
    r, t = np.sqrt(rng.uniform(0, 1, k)), rng.uniform(0, 2 * np.pi, k)
    disk_x, disk_y = 4.0 * r * np.cos(t), 3.0 * r * np.sin(t)  # an ellipse, 4 x 3 mm
    order = np.argsort(rng.uniform(size=(gv, gu, k)), axis=2)  # a new order at every node
    x, y = disk_x[order] + 0.5, disk_y[order] - 0.25
    w = np.full((gv, gu, k), 1 / k)
    lens = MeasuredLens(800.0, np.zeros(3), (48, 40), np.arange(gu) * 4.0,
                        np.arange(gv) * 4.0, x, y, w, np.ones((gv, gu)), "bilinear")
    s = smoothed_lens(lens, 2)
    def cov(a, b):
        return (a * b).mean() - a.mean() * b.mean()
    truth = np.array([[cov(disk_x, disk_x), cov(disk_x, disk_y)],
                      [cov(disk_x, disk_y), cov(disk_y, disk_y)]])

    def kurtosis(z: np.ndarray, w: np.ndarray) -> float:
        r2 = (z**2).sum(axis=0)
        return float((w * r2**2).sum() / (w * r2).sum() ** 2)

    d = np.stack([disk_x - disk_x.mean(), disk_y - disk_y.mean()])
    white = np.linalg.solve(np.linalg.cholesky(truth), d)  # the disk's radial profile
    for j, i in ((0, 0), (4, 5), (8, 10)):
        sx, sy, sw = s.aperture_x_mm[j, i], s.aperture_y_mm[j, i], s.weights[j, i]
        c = np.array([(sw * sx).sum(), (sw * sy).sum()])
        np.testing.assert_allclose(c, [disk_x.mean() + 0.5, disk_y.mean() - 0.25], atol=1e-12)
        dx, dy = sx - c[0], sy - c[1]
        got = np.array([[(sw * dx * dx).sum(), (sw * dx * dy).sum()],
                        [(sw * dx * dy).sum(), (sw * dy * dy).sum()]])
        np.testing.assert_allclose(got, truth, atol=1e-9 * truth.max())
        z = np.linalg.solve(np.linalg.cholesky(truth), np.stack([dx, dy]))
        assert abs(kurtosis(z, sw) / kurtosis(white, np.full(k, 1 / k)) - 1) < 0.02
    plain = x[4, 5].var()  # what averaging alone does, for scale
    assert (np.mean([x[j, i] for j in range(3, 6) for i in range(4, 7)], axis=0).var()
            < 0.3 * plain)


def test_smoothing_averages_the_centroids_noise_and_keeps_their_curved_field():
    """The node centroids (principal rays on the aperture plane) lose their noise, while a
    quadratic field passes exactly, at the border too and with an irregular last column (the
    station's nodes: every 4th pixel plus the last)."""
    from sim.optics.measured_lens import MeasuredLens, smoothed_lens

    rng = np.random.default_rng(11)
    nu, nv = np.r_[np.arange(0, 64, 4.0), 66.0], np.arange(0, 48, 4.0)
    gv, gu, k = len(nv), len(nu), 16
    uu, vv = (nu[None, :] - 33) / 33, (nv[:, None] - 22) / 22
    field_x = 0.5 * uu + 0.2 * uu**2 - 0.1 * uu * vv  # mm, strongly curved (vignetting)
    field_y = 0.3 * vv - 0.15 * vv**2 + 0.05 * uu**2
    j = np.arange(k)
    r, t = 2.0 * np.sqrt((j + 0.5) / k), j * np.pi * (3.0 - np.sqrt(5.0))
    px, py = r * np.cos(t), r * np.sin(t)
    px, py = px - px.mean(), py - py.mean()  # the samples about their centroid
    w = np.full((gv, gu, k), 1 / k)

    def centroids(noise_mm: float) -> tuple[np.ndarray, np.ndarray]:
        e = rng.normal(0, noise_mm, (2, gv, gu))
        lens = MeasuredLens(800.0, np.zeros(3), (67, 45), nu, nv,
                            px + (field_x + e[0])[..., None],
                            py + (field_y + e[1])[..., None], w,
                            np.ones((gv, gu)), "bilinear")
        s = smoothed_lens(lens, 2)
        return ((s.aperture_x_mm * s.weights).sum(axis=2) - field_x,
                (s.aperture_y_mm * s.weights).sum(axis=2) - field_y)

    for err in centroids(0.0):
        np.testing.assert_allclose(err, 0.0, atol=1e-9)
    ex, ey = centroids(0.010)
    rms = np.sqrt(np.mean(ex**2 + ey**2) / 2)
    border = np.sqrt(np.mean(np.r_[ex[0], ex[-1], ex[:, 0], ex[:, -1]] ** 2))
    assert rms < 0.4 * 0.010 and border < 0.75 * 0.010  # noise of 10 um per node averaged

