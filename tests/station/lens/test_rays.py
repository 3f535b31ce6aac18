"""Principal rays and their intersection: exact on synthetic lines, honest uncertainties,
outliers flagged, and what vignetting does to the intersection on the fake bench."""

from __future__ import annotations

import numpy as np
import pytest

from fakes.bench import BenchConfig, FakeBench
from station.lens.centre import intersect_rays
from station.lens.rays import (
    FLAG_BAD_FIT,
    FLAG_FEW_DEPTHS,
    FLAG_OUTLIER,
    RayFitError,
    fit_principal_rays,
)

DEPTHS = np.array([0.0, 20.0, 40.0, 110.0, 250.0, 290.0])
CENTRE = np.array([16.0, 13.0, -100.0])


def synthetic(n: int, sigma: float, rng: np.random.Generator, depths=DEPTHS):
    """Points (D, n, 3) on n lines through CENTRE with slopes up to +-0.05, noise sigma."""
    slope = rng.uniform(-0.05, 0.05, (n, 2))
    z = np.broadcast_to(depths[:, None], (len(depths), n))
    xy = CENTRE[:2] + slope[None] * (z - CENTRE[2])[..., None]
    xy = xy + rng.normal(0.0, sigma, xy.shape)
    pts = np.concatenate([xy, z[..., None]], axis=-1)
    return pts, np.full((len(depths), n, 2), sigma), slope


def test_noise_free_lines_and_centre_are_exact():
    pts, std, slope = synthetic(50, 0.0, np.random.default_rng(0))
    rays = fit_principal_rays(pts, std, np.ones(pts.shape[:2], bool))
    np.testing.assert_allclose(rays.slope, slope, atol=1e-12)
    np.testing.assert_allclose(rays.xy_at(CENTRE[2]), np.broadcast_to(CENTRE[:2], (50, 2)),
                               atol=1e-9)
    assert np.nanmax(rays.residual_norm()) < 1e-9
    assert (rays.flags == 0).all()
    c = intersect_rays(rays)
    np.testing.assert_allclose(c.position, CENTRE, atol=1e-8)


def test_centre_uncertainty_matches_the_scatter():
    """200 noisy repeats: the reported std of the intersection matches the spread of the
    estimates (within 25%), and the residuals scatter like the stated noise."""
    rng = np.random.default_rng(1)
    sigma = 0.02
    est, std, res = [], [], []
    for _ in range(200):
        pts, s, _ = synthetic(120, sigma, rng)
        rays = fit_principal_rays(pts, s, np.ones(pts.shape[:2], bool), floor_mm=1e-6)
        c = intersect_rays(rays)
        est.append(c.position)
        std.append(c.std)
        res.append(rays.residual[..., 0].ravel())
    est, std = np.array(est), np.array(std)
    np.testing.assert_allclose(est.std(axis=0) / np.median(std, axis=0), 1.0, atol=0.25)
    assert np.all(np.abs(est.mean(axis=0) - CENTRE) < 4 * est.std(axis=0) / np.sqrt(200))
    # per-axis residual variance = sigma^2 (D - 2) / D for a 2-parameter line per axis
    np.testing.assert_allclose(np.std(np.concatenate(res)), sigma * np.sqrt(4 / 6), rtol=0.05)


def test_outliers_and_missing_depths_are_flagged_not_used():
    rng = np.random.default_rng(2)
    pts, std, slope = synthetic(40, 0.01, rng)
    valid = np.ones(pts.shape[:2], bool)
    pts[2, 0, 0] += 0.5  # pixel 0: one outlier (50 sigma)
    pts[1, 1, 1] -= 0.5  # pixel 1: two outliers, one more than allowed
    pts[4, 1, 0] += 0.5
    valid[:4, 2] = False  # pixel 2: signal at 2 depths only
    rays = fit_principal_rays(pts, std, valid, min_depths=3, max_outliers=1)
    assert rays.flags[0] == FLAG_OUTLIER and rays.flags[1] & FLAG_BAD_FIT
    assert rays.flags[2] == FLAG_FEW_DEPTHS and (rays.flags[3:] == 0).all()
    assert not rays.used[2, 0] and rays.used[:, 0].sum() == 5
    assert rays.usable.tolist()[:3] == [True, False, False]
    np.testing.assert_allclose(rays.slope[0], slope[0], atol=3e-4)  # refit without it
    assert np.isnan(rays.residual[2, 0]).all()


def test_intersection_is_robust_to_wrong_rays():
    """10 % of the rays miss the centre by 1 mm (not flagged: they are straight lines);
    Huber weights keep the centre within 0.02 mm (plain least squares: ~0.1 mm off)."""
    rng = np.random.default_rng(3)
    pts, std, _ = synthetic(200, 0.005, rng)
    pts[:, :20, 0] += 1.0
    rays = fit_principal_rays(pts, std, np.ones(pts.shape[:2], bool))
    c = intersect_rays(rays)
    assert np.linalg.norm(c.position[:2] - CENTRE[:2]) < 0.02
    assert c.weights[:20].max() < 0.2 * np.median(c.weights[20:])


@pytest.fixture(scope="module")
def benches():
    """Fake benches with the reference distances of test_derive, cheap sampling."""
    common = {"lcd_size": (120, 96), "lcd_distance_at_zero_mm": 100.0, "pupil_samples": 400,
              "subpixels": 1, "spherical_mm": 0.0}
    return {"plain": FakeBench(BenchConfig.small(vignetting_shift_mm=0.0, **common)),
            "vignetted": FakeBench(BenchConfig.small(**common))}


def bench_rays(bench: FakeBench, depths=(0.0, 40.0, 250.0)):
    pitch = bench.config.lcd_pitch_mm
    pts = np.stack([np.concatenate([bench.true_centroids_lcd_px(z).reshape(-1, 2) * pitch,
                                    np.full((1200, 1), z)], axis=1) for z in depths])
    return fit_principal_rays(pts, np.zeros(pts.shape[:2]), np.ones(pts.shape[:2], bool))


def test_unvignetted_rays_meet_at_the_pupil_centre(benches):
    b = benches["plain"]
    rays = bench_rays(b)
    # centroid rays are straight lines, up to LCD pixelation of the LTC (< 0.05 LCD px)
    assert np.nanmax(rays.residual_norm()) < 0.05 * b.config.lcd_pitch_mm
    c = intersect_rays(rays)
    assert np.linalg.norm(c.position - b.optical_centre_station_mm()) < 0.1


def test_vignetting_moves_the_intersection_behind_the_pupil(benches):
    """A pixel's clipped pupil is the lens of two radius-R circles 60 x_n apart: its centroid
    is at 30 x_n, so its centroid ray is ``x_n (30 (1 - d / z_f) + d)``, zero at
    ``d = -30 / (1 - 30 / z_f) = -34.09 mm`` for every pixel: the rays still meet in one
    point, 34 mm behind the pupil, near the axis as well as far from it."""
    b = benches["vignetted"]
    rays = bench_rays(b)
    assert np.nanmax(rays.residual_norm()) < 0.05 * b.config.lcd_pitch_mm
    zf = b.config.focus_distance_mm
    expected = b.optical_centre_station_mm() - np.array([0.0, 0.0, 30.0 / (1 - 30.0 / zf)])
    c = intersect_rays(rays)
    np.testing.assert_allclose(c.position, expected, atol=0.3)
    w, h = b.config.camera_size
    v, u = np.divmod(np.arange(w * h), w)
    near = np.hypot(u - (w - 1) / 2, v - (h - 1) / 2) < 4  # 48 pixels within 4 px of the axis
    z_near = intersect_rays(rays, use=near).position[2]
    assert abs(z_near - expected[2]) < 2.0  # 400 pupil samples resolve small clips coarsely
    assert b.optical_centre_station_mm()[2] - z_near > 30.0


def test_errors():
    pts, std, _ = synthetic(3, 0.0, np.random.default_rng(0), depths=np.array([0.0]))
    with pytest.raises(RayFitError, match="need points at >= 2 depths, got 1"):
        fit_principal_rays(pts, std, np.ones((1, 3), bool))
    pts, std, _ = synthetic(3, 0.0, np.random.default_rng(0))
    with pytest.raises(RayFitError, match="min_depths must be >= 2"):
        fit_principal_rays(pts, std, np.ones((6, 3), bool), min_depths=1)
    valid = np.zeros((6, 3), bool)
    valid[:, 0] = True
    rays = fit_principal_rays(pts, std, valid)
    with pytest.raises(RayFitError, match=r"1 usable principal ray\(s\); need >= 2 \(2 pixels "
                       "have too few depths"):
        intersect_rays(rays)
