"""sim.optics.lens against analytic optics: ray geometry, pupil sampling, vignetting, aberrations."""

import numpy as np
import pytest

from sim.optics.lens import AberratedLens, GaussianLens, PinholeLens, hit_plane, sunflower_disk


def test_sunflower_disk_is_uniform_on_unit_disk():
    p = sunflower_disk(2000)
    r2 = np.sum(p**2, axis=1)
    assert r2.max() <= 1.0
    np.testing.assert_allclose(p.mean(axis=0), 0.0, atol=2e-3)
    # uniform disk: E[x^2] = E[y^2] = 1/4
    np.testing.assert_allclose((p**2).mean(axis=0), 0.25, rtol=5e-3)


def test_sunflower_disk_rejects_empty():
    with pytest.raises(ValueError, match="n >= 1"):
        sunflower_disk(0)


def test_pinhole_ray_points_along_normalised_coordinates():
    xy = np.array([[0.1, -0.2], [0.0, 0.0]])
    b = PinholeLens().bundle(xy)
    assert b.directions.shape == (2, 1, 3)
    d = b.directions[:, 0]
    np.testing.assert_allclose(d[:, :2] / d[:, 2:], xy, atol=1e-15)
    np.testing.assert_allclose(b.weights, 1.0)


def test_ideal_thin_lens_rays_meet_at_in_focus_point():
    lens = AberratedLens(pupil_diameter_mm=8.0, focus_distance_mm=500.0, samples=97)
    xy = np.array([[0.05, 0.02]])
    b = lens.bundle(xy)
    hits = hit_plane(b.origins, b.directions, 500.0)
    np.testing.assert_allclose(hits[0], np.broadcast_to([25.0, 10.0], (97, 2)), atol=1e-9)
    assert b.weights.sum() == pytest.approx(1.0)
    # blur disk at another depth: radius = R |z - z_f| / z_f
    h300 = hit_plane(b.origins, b.directions, 300.0)[0] - np.array([0.05, 0.02]) * 300
    r = np.linalg.norm(h300, axis=1).max()
    assert r == pytest.approx(4.0 * 200 / 500 * np.sqrt(96.5 / 97), rel=1e-9)  # outermost sample


def test_spherical_aberration_moves_rim_focus():
    lens = AberratedLens(pupil_diameter_mm=10.0, focus_distance_mm=400.0, spherical_mm=5.0,
                         samples=400)
    b = lens.bundle(np.zeros((1, 2)))
    o, d = b.origins[0], b.directions[0]
    rho = np.linalg.norm(o[:, :2], axis=1) / 5.0
    # axial crossing distance of each ray: t where x=y=0
    z_cross = -o[:, 0] / d[:, 0] * d[:, 2]
    np.testing.assert_allclose(z_cross, 400.0 + 5.0 * rho**2, rtol=1e-9)


def _lens_area_fraction(d_over_r: float) -> float:
    """Overlap of two unit circles at centre distance d, relative to one circle's area."""
    d = d_over_r
    area = 2 * np.arccos(d / 2) - (d / 2) * np.sqrt(4 - d**2)
    return area / np.pi


def test_vignetting_transmission_is_circle_overlap():
    lens = AberratedLens(pupil_diameter_mm=8.0, focus_distance_mm=500.0,
                         vignetting_shift_mm=20.0, samples=4000)
    xy = np.array([[0.0, 0.0], [0.1, 0.0], [0.1, 0.1]])
    t = lens.bundle(xy).weights.sum(axis=1)
    expected = [1.0] + [_lens_area_fraction(20.0 * np.hypot(*p) / 4.0) for p in xy[1:]]
    np.testing.assert_allclose(t, expected, atol=2e-3)


def test_coma_shifts_rim_rays_along_field():
    lens = AberratedLens(pupil_diameter_mm=8.0, focus_distance_mm=500.0, coma_mm=3.0,
                         samples=200)
    xy = np.array([[0.1, 0.0]])
    b = lens.bundle(xy)
    hits = hit_plane(b.origins, b.directions, 500.0)[0]
    rho2 = np.sum(b.origins[0, :, :2] ** 2, axis=1) / 16.0
    np.testing.assert_allclose(hits[:, 0], 50.0 + 3.0 * rho2 * 0.1, atol=1e-9)
    np.testing.assert_allclose(hits[:, 1], 0.0, atol=1e-9)


def test_gaussian_lens_second_moment_and_focus():
    lens = GaussianLens(sigma_mm=1.5, focus_distance_mm=600.0, samples=2000)
    b = lens.bundle(np.array([[0.02, -0.01]]))
    w = b.weights[0]
    assert w.sum() == pytest.approx(1.0)
    var = np.sum(w[:, None] * b.origins[0, :, :2] ** 2, axis=0)
    np.testing.assert_allclose(var, 1.5**2, rtol=1e-3)  # exact despite the truncation
    hits = hit_plane(b.origins, b.directions, 600.0)[0]
    np.testing.assert_allclose(hits, np.broadcast_to([12.0, -6.0], hits.shape), atol=1e-9)


def test_lens_config_rejects_unknown_and_bad_fields():
    with pytest.raises(ValueError, match="pupil_diameter_mm"):
        AberratedLens(pupil_diameter_mm=-1.0, focus_distance_mm=10.0)
    with pytest.raises(ValueError, match="focal"):
        AberratedLens(pupil_diameter_mm=1.0, focus_distance_mm=10.0, focal=3)
