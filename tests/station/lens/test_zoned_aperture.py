"""The aperture map through a focus per pupil zone (``aperture.resample`` with ``g2_per_mm2``,
``aperture.zone_map``): checked against the LTC of an analytic lens with spherical aberration
and vignetting, traced ray by ray (``sim.optics.AberratedLens``) and binned into LCD pixels."""

from __future__ import annotations

import numpy as np
import pytest

from sim.optics.lens import AberratedLens
from station.lens.aperture import ApertureGrid, resample, zone_map
from station.lens.kernels import resample_zoned_kernel

PITCH_MM = 0.2715
RIM_MM = 8.0
FOCUS_MM, RIM_FOCUS_MM = 760.0, 775.0  # spherical aberration: the rim focuses 15 mm farther
C0 = 1.0 / FOCUS_MM
C1 = (1.0 / RIM_FOCUS_MM - 1.0 / FOCUS_MM) / RIM_MM**2
GRID = ApertureGrid(12.0, 64)


def lens_ltc(xy_n: tuple[float, float], d_mm: float):
    """The LTC (1, P, P) of the pixel at normalised ``xy_n`` on an LCD ``d_mm`` from the pupil
    (each ray's weight binned into the LCD pixel it meets; pixel centres at integer indices),
    its window origin (1, 2), centroid (1, 2) mm, and the pupil's own moments (the truth):
    mean (2,) mm, RMS radius mm, x skew."""
    lens = AberratedLens(pupil_diameter_mm=2 * RIM_MM, focus_distance_mm=FOCUS_MM,
                         vignetting_shift_mm=30.0, spherical_mm=RIM_FOCUS_MM - FOCUS_MM,
                         samples=60000, edge="hard")
    b = lens.bundle(np.array([xy_n]))
    o, d, w = b.origins[0], b.directions[0], b.weights[0]
    q = o[:, :2] + d[:, :2] * (d_mm / d[:, 2])[:, None]
    centroid = (w[:, None] * q).sum(axis=0) / w.sum()
    p = 48
    origin = np.floor(centroid / PITCH_MM + 0.5).astype(np.int64) - p // 2
    ij = np.floor(q / PITCH_MM + 0.5).astype(np.int64) - origin
    h = np.zeros((1, p, p))
    np.add.at(h[0], (ij[:, 1], ij[:, 0]), w)
    return h, origin[None], centroid[None], moments(o[:, 0], o[:, 1], w)


def moments(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float, float]:
    w = w / w.sum()
    mean = np.array([(w * x).sum(), (w * y).sum()])
    dx, dy = x - mean[0], y - mean[1]
    var_x = (w * dx**2).sum()
    return mean, float(np.sqrt((w * (dx**2 + dy**2)).sum())), float((w * dx**3).sum()
                                                                    / var_x**1.5)


def grid_stats(mass: np.ndarray) -> tuple[np.ndarray, float, float]:
    c = GRID.centres_mm
    xx, yy = np.meshgrid(c, c)
    return moments(xx.ravel(), yy.ravel(), mass.ravel())


def test_zoned_map_without_aberration_is_the_affine_map():
    """With no change of focus over the pupil (g2 = 0) the zoned kernel is the one-focus
    resampling, to rounding."""
    rng = np.random.default_rng(1)
    h = rng.random((3, 24, 24))
    origin = np.array([[100, 200], [101, 199], [99, 201]])
    ray_d = (origin + 12) * 0.27 + rng.normal(0.0, 0.1, (3, 2))
    ray_c = rng.normal(0.0, 0.3, (3, 2))
    rot = np.array([[np.cos(0.01), -np.sin(0.01)], [np.sin(0.01), np.cos(0.01)]])
    step = GRID.cell_mm / 2
    for ratio in (4.0, -4.0):
        affine = resample(h, origin, ray_d, ray_c, ratio, 0.27, GRID, rot, 2)
        zoned = np.zeros_like(affine)
        resample_zoned_kernel(h, origin, ray_d, ray_c, 1.0 / ratio, 0.0, RIM_MM**2, 0.27,
                              GRID.cells, 2, GRID.cell_mm**2, rot,
                              -GRID.half_width_mm + 0.5 * step, step, zoned)
        np.testing.assert_allclose(zoned, affine, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("d_mm", [600.0, 680.0, 920.0])
@pytest.mark.parametrize("xy_n", [(0.0, 0.0), (0.08, 0.0)])
def test_zoned_map_recovers_the_pupil_that_one_focus_distorts(xy_n, d_mm):
    """Through each zone's own focus the LTC maps back onto the pupil: its RMS radius after
    the LCD pixel's known box blur, no skew, its mean on the principal ray. One focus for
    every zone (the RMS-best, 769 mm) skews the vignetted pupil by 0.04-0.08 on the near
    side."""
    h, origin, centroid, (mean_true, rms_true, skew_true) = lens_ltc(xy_n, d_mm)
    ratio, g2, fold, blur, _ = zone_map(np.array([d_mm]), 0.0, C0, C1, RIM_MM)
    assert not fold[0]
    zoned = resample(h, origin, centroid, mean_true[None], float(ratio[0]), PITCH_MM, GRID,
                     None, 2, g2_per_mm2=float(g2[0]), rim_mm=RIM_MM)[0]
    mean, rms, skew = grid_stats(zoned)
    # the LCD pixel binned, then held over its area again: twice its box variance, mapped
    # through the zones (blur_ratio), and the grid's cells
    box = 2.0 * 2.0 * (PITCH_MM * blur[0]) ** 2 / 12.0 + 2.0 * GRID.cell_mm**2 / 12.0
    # (an LCD pixel spans 1/3 of the pupil's radius at 680 mm: the variance correction for
    # the binning holds to about 1 %)
    assert np.sqrt(rms**2 - box) == pytest.approx(rms_true, rel=1.5e-2)
    assert abs(skew - skew_true) < 0.01
    np.testing.assert_allclose(mean, mean_true, atol=0.01)
    single = resample(h, origin, centroid, mean_true[None], 1.0 / (1.0 - d_mm / 769.0),
                      PITCH_MM, GRID, None, 2)[0]
    if xy_n != (0.0, 0.0) and d_mm < FOCUS_MM:
        assert abs(grid_stats(single)[2] - skew_true) > 0.03


def test_zone_map_refuses_a_depth_between_the_zones_foci():
    """An LCD between the centre's focus (760 mm) and the rim's (775 mm) mixes the zones: its
    scale changes sign inside the pupil."""
    ratio, g2, fold, blur, _ = zone_map(np.array([600.0, 765.0, 920.0]), 0.0, C0, C1, RIM_MM)
    assert fold.tolist() == [False, True, False]
    g_rim = 1.0 - 600.0 / RIM_FOCUS_MM  # the mean of 1 / g^2 over a uniform pupil
    u = (np.arange(200000) + 0.5) / 200000
    mean_inv_g2 = np.mean(1.0 / (1.0 / ratio[0] + (g_rim - 1.0 / ratio[0]) * u) ** 2)
    assert blur[0] ** 2 == pytest.approx(mean_inv_g2, rel=1e-9)
    assert ratio[0] == pytest.approx(1.0 / (1.0 - 600.0 / FOCUS_MM))
    assert g2[2] == pytest.approx(-920.0 * C1)
