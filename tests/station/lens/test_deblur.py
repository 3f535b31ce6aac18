"""The fused aperture distribution's deblurring before sampling (``aperture.deblur``): the
known blur kernels, the compiled Richardson-Lucy steps against a numpy reference, and a
blurred, noisy pupil restored towards the true one."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from station.lens.aperture import (
    ApertureGrid,
    blur_kernels,
    deblur,
    grid_moments,
    support_floor,
)
from station.lens.kernels import richardson_lucy_kernel

RATIO = np.array([4.5, 5.9, 8.6, -10.9, -7.0, -5.1])
PITCH_MM = 0.75
FOOTPRINT_MM = np.array([1.12, 1.20, 1.27, 1.57, 1.64, 1.72])  # box-equivalent, 2 x 2 points


def mixed(rows: np.ndarray, w: np.ndarray) -> np.ndarray:
    return sum(wi * np.outer(r, r) for wi, r in zip(w, rows, strict=True))


def test_blur_kernels_have_the_box_and_footprint_variances():
    cell = 0.7
    rows = blur_kernels(RATIO, PITCH_MM, FOOTPRINT_MM, 2, cell, 16)
    assert rows.shape == (6, 33) and np.allclose(rows.sum(axis=1), 1.0)
    assert np.allclose(rows, rows[:, ::-1])  # symmetric
    t = np.arange(-16, 17)
    var = (rows * t**2).sum(axis=1) * cell**2
    expect = ((PITCH_MM * RATIO) ** 2 + (FOOTPRINT_MM * RATIO) ** 2) / 12.0
    # integrating over the cells moves the variance by less than a quarter cell squared
    assert np.all(np.abs(var - expect) < cell**2 / 4), var - expect
    # a box footprint: the trapezoid of two boxes, same variance rule
    box = blur_kernels(RATIO, PITCH_MM, FOOTPRINT_MM, 0, cell, 24)
    vb = (box * np.arange(-24, 25) ** 2).sum(axis=1) * cell**2
    assert np.all(np.abs(vb - expect) < cell**2 / 4), vb - expect


def test_richardson_lucy_kernel_equals_the_numpy_formulas():
    rng = np.random.default_rng(3)
    g, n = 20, 3
    rows = blur_kernels(RATIO, PITCH_MM, FOOTPRINT_MM, 2, 1.2, g // 2)
    w = np.array([[0.7, 0, 0, 0, 0, 0.3], [0, 1, 0, 0, 0, 0], [0.2, 0.2, 0.2, 0.2, 0.1, 0.1]])
    d = np.zeros((n, g, g))
    d[:, 4:15, 5:17] = rng.random((n, 11, 12))
    d /= d.sum(axis=(1, 2), keepdims=True)
    x = np.empty_like(d)
    cells = np.arange(g)[:, None] + np.arange(-(g // 2), g // 2 + 1)[None]
    norm_rows = (rows[:, None, :] * ((cells >= 0) & (cells < g))[None]).sum(axis=2)
    richardson_lucy_kernel(d, w, rows, norm_rows, 7, x)
    for k in range(n):
        ker = mixed(rows, w[k])
        def conv(a, ker=ker):
            return ndimage.convolve(a, ker, mode="constant")
        norm = conv(np.ones((g, g)))
        ref = d[k].copy()
        for _ in range(7):
            model = conv(ref)
            ratio = np.where(model > 1e-15, d[k] / np.where(model > 1e-15, model, 1), 0.0)
            ref = ref * conv(ratio) / norm
        assert np.allclose(x[k], ref, rtol=1e-10, atol=1e-15)


def _r4(m: np.ndarray, grid: ApertureGrid) -> float:
    c = grid.centres_mm
    xx, yy = np.meshgrid(c, c)
    mean, _ = grid_moments(m[None], grid)
    r2 = (xx - mean[0, 0]) ** 2 + (yy - mean[0, 1]) ** 2
    return float((m * r2**2).sum() ** 0.25)


def test_deblur_restores_a_blurred_noisy_pupil():
    """A disk and a cat's eye (a vignetted pupil) blurred by the known mixed kernel, with the
    LTC's noise over a margin around them: cut and deblurred, their L1 error and their fourth
    radial moment come close to the true pupil's."""
    grid = ApertureGrid(14.0, 32)
    p = grid.points(8).reshape(32, 8, 32, 8, 2)
    disk = np.hypot(p[..., 0], p[..., 1]) < 8.0
    eye = disk & (np.hypot(p[..., 0] - 5.0, p[..., 1] - 2.0) < 7.0)
    w = np.array([[0.8, 0, 0, 0, 0, 0.2]])
    rows = blur_kernels(RATIO, PITCH_MM, FOOTPRINT_MM, 2, grid.cell_mm, 16)
    rng = np.random.default_rng(0)
    for shape in (disk, eye):
        true = shape.sum(axis=(1, 3)).astype(np.float64)
        true /= true.sum()
        blurred = ndimage.convolve(true, mixed(rows, w[0]), mode="constant")
        margin = ndimage.binary_dilation(blurred > 0, iterations=3)
        noisy = blurred + np.where(margin, 0.03 * blurred.max() * rng.standard_normal(true.shape),
                                   0.0)
        raw = np.maximum(noisy, 0) / np.maximum(noisy, 0).sum()
        cut = deblur(noisy[None], w, grid, RATIO, PITCH_MM, FOOTPRINT_MM, 2, 0, 0.1)[0]
        out = deblur(noisy[None], w, grid, RATIO, PITCH_MM, FOOTPRINT_MM, 2, 20, 0.1)[0]
        assert np.isclose(out.sum(), 1.0) and out.min() >= 0
        l1 = [np.abs(a - true).sum() for a in (raw, cut, out)]
        r4 = [_r4(a, grid) / _r4(true, grid) - 1 for a in (raw, cut, out)]
        assert l1[2] < l1[1] < l1[0] and l1[2] < 0.7 * l1[0], l1
        assert r4[0] > 0.12 and abs(r4[2]) < 0.08 and abs(r4[2]) < 0.5 * abs(r4[1]), r4


def test_support_floor_keeps_the_main_body_only():
    m = np.zeros((1, 10, 10))
    m[0, 2:6, 2:6] = 1.0
    m[0, 4, 6] = 0.05  # an attached edge cell below the floor
    m[0, 8, 8] = 0.5  # a detached noise cell above it
    m[0, 0, 9] = -0.3
    out = support_floor(m, 0.1)[0]
    assert out[2:6, 2:6].min() == 1.0 and out[4, 6] == 0 and out[8, 8] == 0
    assert out.min() == 0 and out.sum() == 16.0
    assert np.array_equal(support_floor(m, 0.0)[0], np.maximum(m[0], 0))
