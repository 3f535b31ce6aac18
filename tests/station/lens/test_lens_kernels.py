"""The compiled lens kernels against the numpy formulas they replace (kept here as the
reference): ``window_stats`` and ``aperture.resample``; and the ring sampler's properties."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from station.lens.aperture import ApertureGrid, grid_moments, resample, ring_samples
from station.lens.centroids import (
    NOISE_SIGMAS,
    PEAK_FRACTION,
    REGION_MARGIN_PX,
    STATUS_NO_SIGNAL,
    STATUS_OK,
    STATUS_TRUNCATED,
    window_stats,
)


def window_stats_reference(h: np.ndarray, sigma: np.ndarray,
                           margin: int = REGION_MARGIN_PX) -> dict:
    """The numpy formulas of ``window_stats`` (before they were compiled); ``margin``: the
    region's growth, LCD px."""
    n, p = h.shape[0], h.shape[1]
    signal = np.isfinite(h).reshape(n, -1).all(axis=1)
    hz = np.where(signal[:, None, None], h, 0.0)
    sm = ndimage.uniform_filter(hz, size=(1, 3, 3), mode="constant")
    peak = sm.reshape(n, -1).max(axis=1)
    thr = np.maximum(NOISE_SIGMAS * np.where(signal, sigma, 0.0) / 3.0, PEAK_FRACTION * peak)
    above = (sm > thr[:, None, None]) & signal[:, None, None] & (peak > 0)[:, None, None]
    labels, _ = ndimage.label(above, structure=np.array([np.zeros((3, 3)), np.ones((3, 3)),
                                                         np.zeros((3, 3))], dtype=bool))
    ipk = sm.reshape(n, -1).argmax(axis=1)
    lab_pk = labels.reshape(n, -1)[np.arange(n), ipk]
    core = (labels == lab_pk[:, None, None]) & (lab_pk > 0)[:, None, None]
    raw_thr = np.maximum(NOISE_SIGMAS * np.where(signal, sigma, 0.0),
                         PEAK_FRACTION * hz.reshape(n, -1).max(axis=1))
    strong = core & (hz > raw_thr[:, None, None])
    edge = (strong[:, 0].any(1) | strong[:, -1].any(1) | strong[:, :, 0].any(1)
            | strong[:, :, -1].any(1))
    disk = np.hypot(*np.mgrid[-margin:margin + 1, -margin:margin + 1]) <= margin + 0.5
    region = ndimage.binary_dilation(core, structure=disk[None]) if n else core
    hr = np.where(region, hz, 0.0)
    s = hr.sum(axis=(1, 2))
    npx = region.sum(axis=(1, 2))
    ok = signal & (lab_pk > 0) & (s > NOISE_SIGMAS * sigma * np.sqrt(np.maximum(npx, 1)))
    safe = np.where(ok, s, 1.0)
    y, x = np.mgrid[0:p, 0:p].astype(np.float64)
    cx = (hr * x).sum(axis=(1, 2)) / safe
    cy = (hr * y).sum(axis=(1, 2)) / safe
    dx = np.where(region, x - cx[:, None, None], 0.0)
    dy = np.where(region, y - cy[:, None, None], 0.0)
    mxx = (hr * dx * dx).sum(axis=(1, 2)) / safe
    myy = (hr * dy * dy).sum(axis=(1, 2)) / safe
    mxy = (hr * dx * dy).sum(axis=(1, 2)) / safe
    sig = np.where(ok, sigma, 0.0) / safe
    std = np.stack([sig * np.sqrt((dx * dx).sum(axis=(1, 2))),
                    sig * np.sqrt((dy * dy).sum(axis=(1, 2)))], axis=1)
    r2 = dx * dx + dy * dy
    tr = mxx + myy
    tr_std = sig * np.sqrt((np.where(region, r2 - tr[:, None, None], 0.0) ** 2).sum(axis=(1, 2)))
    status = np.where(ok, np.where(edge, STATUS_TRUNCATED, STATUS_OK), STATUS_NO_SIGNAL)
    nan2 = np.where(ok[:, None], 0.0, np.nan)
    return {"centroid": np.stack([cx, cy], axis=1) + nan2, "centroid_std": std + nan2,
            "moments": np.stack([mxx, myy, mxy], axis=1) + nan2[:, :1],
            "trace_std": tr_std + nan2[:, 0], "region": region & ok[:, None, None],
            "status": status.astype(np.int8)}


def resample_reference(h, origin, ray_at_depth_mm, ray_at_centre_mm, ratio, pitch_mm, grid,
                       rotation2=None, sub=2):
    """The numpy formulas of ``aperture.resample`` (before they were compiled)."""
    n, p = h.shape[0], h.shape[-1]
    pts = grid.points(sub).reshape(-1, 2)
    if rotation2 is not None:
        pts = pts @ np.asarray(rotation2)
    s = np.broadcast_to(np.asarray(ratio, dtype=np.float64), (n,))
    inv = 1.0 / s[:, None]
    col = np.floor((ray_at_depth_mm[:, :1] + (pts[None, :, 0] - ray_at_centre_mm[:, :1]) * inv)
                   / pitch_mm + 0.5).astype(np.int64) - origin[:, :1]
    row = np.floor((ray_at_depth_mm[:, 1:] + (pts[None, :, 1] - ray_at_centre_mm[:, 1:]) * inv)
                   / pitch_mm + 0.5).astype(np.int64) - origin[:, 1:]
    inside = (col >= 0) & (col < p) & (row >= 0) & (row < p)
    flat = np.where(inside, row * p + col, 0) + (np.arange(n) * p * p)[:, None]
    val = np.where(inside, h.reshape(-1)[flat], 0.0)
    dens = val / ((pitch_mm * s) ** 2)[:, None]
    g = grid.cells
    return dens.reshape(n, g, sub, g, sub).mean(axis=(2, 4)) * grid.cell_mm**2


def _windows(n: int, p: int = 24, seed: int = 0):
    """Elliptical Gaussian windows of every size and position (some cut by the border, some
    faint, one NaN), with noise."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:p, 0:p]
    cx, cy = rng.uniform(-2, p + 1, n), rng.uniform(-2, p + 1, n)
    sx, sy = rng.uniform(0.4, 6, n), rng.uniform(0.4, 6, n)
    h = np.exp(-0.5 * (((x - cx[:, None, None]) / sx[:, None, None]) ** 2
                       + ((y - cy[:, None, None]) / sy[:, None, None]) ** 2))
    h /= h.sum(axis=(1, 2), keepdims=True)
    sigma = rng.uniform(0, 3e-3, n)
    sigma[::7] = 0.0
    h += rng.normal(size=h.shape) * sigma[:, None, None]
    h[3] = np.nan
    return h, sigma


@pytest.mark.parametrize("margin", [0, 1, 3, 5])
def test_the_region_grown_from_its_edge_pixels_is_the_dilation_for_any_margin(margin):
    """The kernel paints the disk of a core pixel only where the core has an edge: the region
    is still exactly the core dilated by the disk (ndimage), at every margin."""
    from station.lens.kernels import stats_kernel

    h, sigma = _windows(1500, seed=margin + 1)
    n, p = h.shape[0], h.shape[1]
    signal = np.isfinite(h).reshape(n, -1).all(axis=1)
    hz = np.ascontiguousarray(np.where(signal[:, None, None], h, 0.0))
    out = [np.empty((n, 2)), np.empty((n, 2)), np.empty((n, 3)), np.empty(n),
           np.empty((n, p, p), bool), np.empty(n, np.int8)]
    stats_kernel(hz, sigma, signal, NOISE_SIGMAS, PEAK_FRACTION, margin, *out)
    ref = window_stats_reference(h, sigma, margin)
    assert ref["region"].sum() > 0
    np.testing.assert_array_equal(out[4], ref["region"])


def test_window_stats_equals_the_numpy_formulas():
    h, sigma = _windows(3000)
    got, ref = window_stats(h, sigma), window_stats_reference(h, sigma)
    np.testing.assert_array_equal(got.status, ref["status"])
    np.testing.assert_array_equal(got.region, ref["region"])
    assert {STATUS_OK, STATUS_NO_SIGNAL, STATUS_TRUNCATED} <= set(got.status.tolist())
    for name in ("centroid", "centroid_std", "moments", "trace_std"):
        a, b = getattr(got, name), ref[name]
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b), err_msg=name)
        scale = np.nanmax(np.abs(b))
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * scale, err_msg=name)


def test_resample_equals_the_numpy_formulas():
    rng = np.random.default_rng(1)
    n, p = 200, 24
    h = rng.uniform(0, 1, (n, p, p))
    for k in range(0, n, 2):  # a region inside the window, as the derivation passes them
        r, c = rng.integers(0, p - 1, 2)
        h[k, :r] = 0.0
        h[k, :, :c] = 0.0
        h[k, r + rng.integers(1, 6):] = 0.0
    origin = rng.integers(-5, 5, (n, 2))
    ray_d = rng.uniform(0, 5, (n, 2))
    ray_c = rng.uniform(-1, 1, (n, 2))
    grid = ApertureGrid(6.0, 32)
    a = np.radians(3.0)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    for ratio in (-1.7, 0.6, rng.uniform(0.3, 2.0, n)):
        got = resample(h, origin, ray_d, ray_c, ratio, 0.27, grid, rot, 2)
        ref = resample_reference(h, origin, ray_d, ray_c, ratio, 0.27, grid, rot, 2)
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-15)


def test_ring_strata_keep_the_mean_and_equal_masses_in_a_fixed_order():
    """Every stratum carries 1/k of the mass, the samples' mean is the distribution's (also
    after the Lloyd steps), and sample j lies in the same part of the aperture for a disk
    and a shifted, vignetted one."""
    grid = ApertureGrid(4.0, 32)
    pts = grid.points().reshape(-1, 2)
    disk = (np.hypot(pts[:, 0], pts[:, 1]) < 3.0).astype(float)
    cat = disk * (np.hypot(pts[:, 0] - 1.5, pts[:, 1]) < 3.0) * (1 + 0.1 * pts[:, 1])
    mass = np.stack([disk, cat, np.eye(32).ravel()]).reshape(3, 32, 32)
    for k in (1, 7, 32):
        x, w = ring_samples(mass, grid, k, iterations=0)
        np.testing.assert_allclose(w, 1.0 / k, atol=1e-12)
        mean, _ = grid_moments(mass, grid)
        np.testing.assert_allclose(np.einsum("nk,nki->ni", w, x), mean, atol=1e-12)
        x, w = ring_samples(mass, grid, k)
        np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-12)
        np.testing.assert_allclose(np.einsum("nk,nki->ni", w, x), mean, atol=1e-12)
    x, _ = ring_samples(mass[:2], grid, 32)
    d = x[0] - x.mean(axis=1)[0]
    e = x[1] - x.mean(axis=1)[1]
    ang = np.degrees(np.abs(np.angle(np.exp(1j * (np.arctan2(d[:, 1], d[:, 0])
                                                  - np.arctan2(e[:, 1], e[:, 0]))))))
    assert np.median(ang) < 30


def test_stable_argsort_is_numpy_mergesort():
    """The ring sampler's radix sort gives np.argsort(kind="mergesort")'s permutation: random
    keys, many ties (equal keys stay in index order), +0.0 beside -0.0, subnormals, and
    every length from none to more cells than an aperture grid has."""
    from station.lens.kernels import stable_argsort

    rng = np.random.default_rng(7)
    for trial in range(200):
        n = int(rng.integers(0, 1200)) if trial else 0
        keys = [rng.uniform(0, 2 * np.pi, n), rng.integers(0, 4, n).astype(float),
                np.where(rng.random(n) < 0.5, 0.0, -0.0), rng.normal(size=n),
                rng.normal(size=n) * 1e-310][trial % 5]
        m = max(n, 1)
        got = stable_argsort(keys, n, np.empty(m), np.empty(m, np.uint64),
                             np.empty(m, np.uint64), np.empty(m, np.int64),
                             np.empty(m, np.int64), np.empty(256, np.int64))
        np.testing.assert_array_equal(got, np.argsort(keys, kind="mergesort"))


def test_grid_moments_equal_the_numpy_formulas():
    rng = np.random.default_rng(2)
    grid = ApertureGrid(3.0, 32)
    mass = rng.uniform(0, 1, (50, 32, 32)) * (rng.uniform(size=(50, 1, 1)) < 0.9)
    pts = grid.points().reshape(-1, 2)
    m = mass.reshape(50, -1)
    tot = m.sum(axis=1, keepdims=True)
    m = m / np.where(tot > 0, tot, 1.0)
    mean = m @ pts
    d = pts[None] - mean[:, None]
    cov = np.einsum("nk,nki,nkj->nij", m, d, d)
    got_mean, got_cov = grid_moments(mass, grid)
    np.testing.assert_allclose(got_mean, mean, rtol=0, atol=1e-13)
    np.testing.assert_allclose(got_cov, cov, rtol=0, atol=1e-13)
