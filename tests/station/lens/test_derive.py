"""Acceptance of the lens derivation on the fake bench.

Bench: ``BenchConfig.small`` (40 x 30 camera, f/2, z_f = 250 mm, vignetting 60 mm per unit
field, 6 mm spherical aberration) with a 120 x 96 LCD 100 mm from the pupil at stage 0, pixel
area sampled 2 x 2.
Depths: stage 0, 20, 40 (100-140 mm: before focus), 110 (near focus), 250, 290 (beyond).

Noise ("default noise"): the fake camera's ``NoiseModel()`` at its reference exposure,
4-step Fourier SPI with a = b = 0.5 and P = 24. A pixel of transmittance T sees
``S = 0.85 full_well T`` electrons for white; each frame's noise is the camera's
``variance_adu`` at the mean level ``a S``; ``station/ltc/spi.py`` propagates it to one
normalised LTC weight as ``sigma_h = sigma_D / (P^2 b S) sqrt(s/2 + 4 (P^2 - s) / n)``
(s = 4 self-conjugate terms, n = 4 steps): about 6.4e-4 for T = 1 (weights ~ 0.005). The
noise is added to the true windows, which are renormalised to sum 1, as SPI does.

The six pixels whose aperture distribution is scored (centre and corners) are computed with
6400 pupil samples instead of the bench's 400: at 400 samples each LCD pixel of a 100 mm
LTC receives about one pupil sample, and that sampling error of the ground truth itself
(not of the derivation) would cost ~2 % of overlap.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fakes.bench import BenchConfig, FakeBench
from fakes.camera import NoiseModel
from sim.optics.measured_lens import match_moments
from sim.optics.plane_ltc import plane_ltc
from station.lens.aperture import (
    ApertureGrid,
    fusion_weights,
    grid_moments,
    resample,
    ring_samples,
    scale_ratio,
)
from station.lens.derive import aperture_set, derive_lens, node_positions
from station.lens.geometry import LensFitConfig, LensFitError, fit_geometry
from station.lens.rays import FLAG_FEW_DEPTHS
from station.ltc.store import LtcVolume, centred_origins, windows_from_sparse

P = 24
DEPTHS = (0.0, 20.0, 40.0, 110.0, 250.0, 290.0)
HELD_OUT = 70.0
SCORED = {"centre": (19, 14), "centre2": (20, 15), "corner00": (0, 0), "corner10": (39, 0),
          "corner01": (0, 29), "corner11": (39, 29)}


def windows(bench: FakeBench, z: float, lens=None, pixels=None, subpixels=None):
    """True LTC windows (n, P, P) centred on their centroids, origins (n, 2), transmittance."""
    c = bench.config
    if lens is None:
        m = bench.true_ltc(z)
    else:
        r, t = bench.camera_pose_in_lcd(z)
        m = plane_ltc(bench.K, None, c.camera_size, lens, r, t, c.lcd_size, c.lcd_pitch_mm,
                      subpixels=subpixels or c.subpixels, pixels=pixels)[pixels]
    t_px = np.asarray(m.sum(axis=1)).ravel()
    lw = c.lcd_size[0]
    mc = m.tocoo()
    cen = np.stack([np.bincount(mc.row, mc.data * (mc.col % lw), len(t_px)),
                    np.bincount(mc.row, mc.data * (mc.col // lw), len(t_px))], 1) / t_px[:, None]
    org = centred_origins(cen, P)
    win = windows_from_sparse(m, c.lcd_size, P, org)
    return win / win.sum(axis=(1, 2), keepdims=True), org, t_px


def spi_noise(transmittance: np.ndarray) -> np.ndarray:
    """Std of one normalised LTC weight (see the module docstring)."""
    nm = NoiseModel()
    s_e = nm.white_fraction * nm.full_well_e * transmittance
    sigma_d = np.sqrt(nm.variance_adu(0.5 * s_e))
    s_adu = nm.gain_adu_per_e * s_e
    return sigma_d / (P * P * 0.5 * s_adu) * np.sqrt(4 / 2 + 4 * (P * P - 4) / 4)


@pytest.fixture(scope="module")
def bench() -> FakeBench:
    return FakeBench(BenchConfig.small(lcd_size=(120, 96), lcd_distance_at_zero_mm=100.0,
                                       subpixels=2))


@pytest.fixture(scope="module")
def truth(bench):
    """(ltc, origin, transmittance) of every depth, scored pixels at 6400 pupil samples."""
    w, h = bench.config.camera_size
    flat = np.array([v * w + u for u, v in SCORED.values()])
    fine = bench.lens.model_copy(update={"samples": 6400})
    out = []
    for z in DEPTHS:
        win, org, t = windows(bench, z)
        win[flat], org[flat], _ = windows(bench, z, fine, flat)
        out.append((win.reshape(h, w, P, P), org.reshape(h, w, 2), t.reshape(h, w)))
    return [np.array(a) for a in zip(*out, strict=True)]


def make_volume(bench, truth, seed: int | None = None, offset: float = 0.0, K=True):
    ltc, org, t = truth
    sigma = spi_noise(t)
    if seed is not None:
        rng = np.random.default_rng(seed)
        ltc = ltc + rng.normal(size=ltc.shape) * sigma[..., None, None]
        ltc = ltc / ltc.sum(axis=(-2, -1), keepdims=True)
    return LtcVolume(ltc.astype(np.float32), org, 3000.0 * t,
                     sigma if seed is not None else np.zeros_like(t),
                     np.array(DEPTHS) + offset, bench.config.lcd_pitch_mm,
                     camera_matrix=bench.K if K else None, name="bench")


@pytest.fixture(scope="module")
def clean(bench, truth):
    vol = make_volume(bench, truth)
    return vol, derive_lens(vol, LensFitConfig.basic())


@pytest.fixture(scope="module")
def noisy(bench, truth):
    vol = make_volume(bench, truth, seed=7)
    return vol, derive_lens(vol, LensFitConfig.basic(grid_step=4))


def true_pupil(bench, grid: ApertureGrid, uv, centre_mm, sub: int = 8) -> np.ndarray:
    """The ground truth: the bench lens's transmission over its pupil, as normalised masses
    on the derivation's aperture grid (which is centred on the estimated centre)."""
    pts = grid.points(sub).reshape(-1, 2) + (centre_mm - bench.optical_centre_station_mm())[:2]
    xn = (np.asarray(uv, float) - bench.K[:2, 2]) / bench.K[0, 0]
    r = bench.lens.pupil_radius_mm
    inside = (np.sum(pts**2, axis=1) <= r * r)[None] * bench.lens.transmission(
        xn, np.broadcast_to(pts, (len(xn),) + pts.shape))
    g = grid.cells
    m = inside.reshape(len(xn), g, sub, g, sub).mean(axis=(2, 4))
    return m / m.sum(axis=(1, 2), keepdims=True)


def overlap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Sum of minima of two normalised distributions (..., G, G)."""
    na = a / a.sum(axis=(-2, -1), keepdims=True)
    return np.minimum(na, b).sum(axis=(-2, -1))


def test_optical_centre_noise_free(bench, clean):
    _, r = clean
    s = r.summary().to_json()
    err = np.linalg.norm(r.geometry.centre.position - bench.optical_centre_station_mm())
    print(f"\nnoise-free: centre {np.round(s['optical_centre_mm'], 4)} true "
          f"{bench.optical_centre_station_mm()} error {err:.4f} mm; ray residual mean "
          f"{s['ray_residual_mean_mm']:.5f} std {s['ray_residual_std_mm']:.5f} mm; "
          f"ray intersection {np.round(s['principal_ray_intersection_mm'], 3)}")
    assert err < 0.1
    assert s["pixels_usable"] == 1200 and s["ray_residual_mean_mm"] < 0.005


def test_optical_centre_with_default_noise(bench, noisy):
    _, r = noisy
    s = r.summary().to_json()
    err = np.linalg.norm(r.geometry.centre.position - bench.optical_centre_station_mm())
    print(f"\ndefault noise: centre {np.round(s['optical_centre_mm'], 4)} +- "
          f"{np.round(s['optical_centre_std_mm'], 4)} error {err:.4f} mm; ray residual mean "
          f"{s['ray_residual_mean_mm']:.5f} std {s['ray_residual_std_mm']:.5f} mm")
    assert err < 0.5
    assert s["pixels_usable"] >= 1190


def test_focus_is_the_plane_of_least_blur(bench, clean):
    """With spherical aberration (rim rays focus 6 mm further) the least-RMS-blur distance
    is ``E[u / z(u)] / E[u / z(u)^2]`` over the pupil (u = (rho/rho_max)^2, uniform):
    the fitted focus distance matches it."""
    c = bench.config
    u = (np.arange(100000) + 0.5) / 100000
    za = c.focus_distance_mm + c.spherical_mm * u
    d_star = np.mean(u / za) / np.mean(u / za**2)
    g = clean[1].geometry
    print(f"\nfocus: fitted z_f {g.focus_distance_fit_mm:.3f} mm, least-blur {d_star:.3f} mm, "
          f"paraxial {c.focus_distance_mm} mm; spread over pixels {g.focus.spread_mm:.3f} mm")
    assert abs(g.focus_distance_fit_mm - d_star) < 0.5
    assert g.focus_distance_mm == g.focus_distance_fit_mm


def test_configured_focus_is_used_and_both_reported(bench, clean):
    vol, r = clean
    g = fit_geometry(vol, LensFitConfig(focus_distance_mm=250.0))
    assert g.focus_distance_mm == pytest.approx(250.0, abs=1e-6)
    assert g.focus_distance_config_mm == 250.0
    assert g.focus.plane_z_mm == pytest.approx(r.geometry.focus_plane_z_mm, abs=0.1)
    assert any("configured 250.000 mm (used), fitted" in n for n in g.notes)
    err = np.linalg.norm(g.centre.position - bench.optical_centre_station_mm())
    print(f"\nconfigured paraxial z_f = 250: centre error {err:.3f} mm (the centroids see the "
          "least-blur focus, not the paraxial one)")
    assert err < 1.0


def test_fused_aperture_matches_the_true_pupil(bench, clean):
    vol, r = clean
    w = bench.config.camera_size[0]
    flat = np.array([v * w + u for u, v in SCORED.values()])
    aps = aperture_set(vol, r.geometry, r.grid, flat)
    ov = overlap(aps.fused, true_pupil(bench, r.grid, list(SCORED.values()),
                                       r.geometry.centre.position))
    print("\nnoise-free overlap with the true pupil: "
          + ", ".join(f"{k} {v:.4f}" for k, v in zip(SCORED, ov, strict=True)))
    assert np.all(ov >= 0.95)


def test_fusing_depths_beats_the_best_single_depth(bench, noisy):
    vol, r = noisy
    w = bench.config.camera_size[0]
    flat = np.array([v * w + u for u, v in SCORED.values()])
    aps = aperture_set(vol, r.geometry, r.grid, flat, keep_depths=True)
    t = true_pupil(bench, r.grid, list(SCORED.values()), r.geometry.centre.position)
    fused_err = 1 - overlap(aps.fused, t)
    single_err = 1 - overlap(aps.per_depth, t[:, None])
    best = single_err.min(axis=1)
    print("\ndefault noise, 1 - overlap: fused vs best single depth: "
          + ", ".join(f"{k} {f:.4f} vs {b:.4f}" for k, f, b in zip(SCORED, fused_err, best, strict=True)))
    assert np.all(fused_err < best)


def test_stage_offset_cancels(bench, truth):
    cfg = LensFitConfig.basic(grid_step=3)
    a = derive_lens(make_volume(bench, truth, seed=3), cfg)
    b = derive_lens(make_volume(bench, truth, seed=3, offset=123.4), cfg)
    for name in ("aperture_x_mm", "aperture_y_mm", "weights", "transmittance"):
        x, y = getattr(a.lens, name), getattr(b.lens, name)
        assert np.abs(x - y).max() <= 1e-6 * np.abs(x).max(), name
    assert abs(a.lens.focus_distance_mm - b.lens.focus_distance_mm) < 1e-6 * 250
    shift = b.lens.optical_centre_mm - a.lens.optical_centre_mm
    np.testing.assert_allclose(shift, [0.0, 0.0, 123.4], atol=1e-6)


def test_samples_keep_the_moments(bench, clean):
    """The K samples have exactly the target mean and covariance, and that covariance (the
    fused distribution's, less the known LCD-pixel and camera-pixel blurs and the cells'
    binning) is the true pupil's within 3 %."""
    _, r = clean
    lens, aps = r.lens, r.apertures
    w = bench.config.camera_size[0]
    x, y = lens.aperture_x_mm.reshape(-1, 32), lens.aperture_y_mm.reshape(-1, 32)
    wk = lens.weights.reshape(-1, 32)
    xy = np.stack([x, y], -1)
    mean = np.einsum("nk,nki->ni", wk, xy)
    d = xy - mean[:, None]
    cov = np.einsum("nk,nki,nkj->nij", wk, d, d)
    np.testing.assert_allclose(mean, aps.mean, atol=1e-9)
    np.testing.assert_allclose(cov, aps.cov, atol=1e-9)
    uv = list(SCORED.values())
    t = true_pupil(bench, r.grid, uv, r.geometry.centre.position, sub=16)
    pts = r.grid.points().reshape(-1, 2)
    tm = t.reshape(len(uv), -1) @ pts
    dd = pts[None] - tm[:, None]
    tc = np.einsum("nk,nki,nkj->nij", t.reshape(len(uv), -1), dd, dd)
    tc -= np.eye(2) * r.grid.cell_mm**2 / 12  # Sheppard: the binned pupil's variance is wider
    flat = [v * w + u for u, v in uv]
    np.testing.assert_allclose(np.trace(aps.cov[flat], axis1=1, axis2=2),
                               np.trace(tc, axis1=1, axis2=2), rtol=0.03)
    np.testing.assert_allclose(aps.mean[flat], tm, atol=0.05)


def test_measured_lens_reproduces_a_held_out_depth(bench, clean):
    """The measured lens, traced by the simulator's own ``plane_ltc`` with the camera's K at
    a depth not used in the fit, gives every pixel's LTC centroid within 0.05 LCD px of the
    truth (median) and its size within 5 %."""
    _, r = clean
    c = bench.config
    o = r.lens.optical_centre_mm
    m = plane_ltc(bench.K, None, c.camera_size, r.lens, np.eye(3),
                  o - np.array([0.0, 0.0, HELD_OUT]), c.lcd_size, c.lcd_pitch_mm, subpixels=3)
    true = bench.true_ltc(HELD_OUT, normalise=True)
    lw = c.lcd_size[0]
    cols = np.arange(m.shape[1])
    x, y = (cols % lw).astype(float), (cols // lw).astype(float)

    def moments(mat):
        s = np.asarray(mat.sum(axis=1)).ravel()
        mx, my = mat @ x / s, mat @ y / s
        return np.stack([mx, my], 1), (mat @ (x * x) + mat @ (y * y)) / s - mx**2 - my**2

    (cm, vm), (ct, vt) = moments(m), moments(true)
    err = np.linalg.norm(cm - ct, axis=1)
    print(f"\nheld-out depth {HELD_OUT} mm: centroid error median {np.median(err):.4f} px, max "
          f"{err.max():.4f} px; size ratio median {np.median(vm / vt):.4f}")
    assert np.median(err) < 0.05 and err.max() < 0.2
    assert abs(np.median(vm / vt) - 1) < 0.05


def test_without_camera_matrix_the_ray_intersection_is_used(bench, truth):
    g = fit_geometry(make_volume(bench, truth, K=False))
    assert g.centre is g.centre_rays and g.camera_matrix is None
    assert any("vignetting pulls behind the pupil" in n for n in g.notes)
    assert bench.optical_centre_station_mm()[2] - g.centre.position[2] > 30


def test_flagged_pixels_are_not_used_and_their_nodes_filled(bench, truth, clean):
    vol = make_volume(bench, truth)
    ltc = np.array(vol.ltc)
    ltc[:4, 5, 5] = np.nan  # pixel (5, 5): signal at 2 of 6 depths
    r = derive_lens(dataclasses.replace(vol, ltc=ltc), LensFitConfig.basic(grid_step=5))
    assert r.geometry.rays.flags[5 * 40 + 5] == FLAG_FEW_DEPTHS
    assert r.filled_nodes == 1
    nodes = r.lens.aperture_x_mm
    assert any(np.array_equal(nodes[1, 1], nodes[j, i]) for j, i in ((0, 1), (1, 0), (1, 2),
                                                                     (2, 1)))
    np.testing.assert_allclose(r.geometry.centre.position, clean[1].geometry.centre.position,
                               atol=1e-3)


def test_errors(bench, truth):
    vol = make_volume(bench, truth)
    with pytest.raises(LensFitError, match="bench: centre_method 'pinhole' needs the camera "
                       "matrix K"):
        fit_geometry(make_volume(bench, truth, K=False), LensFitConfig(centre_method="pinhole"))
    two = dataclasses.replace(vol, ltc=vol.ltc[[0, 4]], origin=vol.origin[[0, 4]],
                              gain=vol.gain[[0, 4]], noise=vol.noise[[0, 4]],
                              depths_mm=vol.depths_mm[[0, 4]])
    with pytest.raises(LensFitError, match=r"bench: the focus distance cannot be fitted \(needs "
                       ">= 3 depths"):
        fit_geometry(two)
    g2 = fit_geometry(two, LensFitConfig(focus_distance_mm=250.0))
    assert g2.focus_distance_mm == pytest.approx(250.0, abs=1e-9) and g2.focus is None
    ltc = np.array(vol.ltc)
    ltc[:3] = np.nan  # every pixel has signal at 3 depths; min_depths 4
    with pytest.raises(LensFitError, match=r"bench: optical centre: 0 usable principal ray"):
        fit_geometry(dataclasses.replace(vol, ltc=ltc), LensFitConfig(min_depths=4))
    ltc = np.full(vol.ltc.shape, np.nan, np.float32)
    ltc[:, 0, :2] = vol.ltc[:, 0, :2]  # two pixels with signal: a centre, but no pose
    with pytest.raises(LensFitError, match="bench: pinhole optical centre: 2 usable principal "
                       "rays; need >= 3"):
        fit_geometry(dataclasses.replace(vol, ltc=ltc))
    ltc = np.array(vol.ltc)
    nu, nv = node_positions(40, 2), node_positions(30, 2)
    ltc[:, nv[:, None], nu[None, :]] = np.nan  # every node of a grid_step-2 lens: no signal
    with pytest.raises(LensFitError, match="no node pixel has a usable LTC"):
        derive_lens(dataclasses.replace(vol, ltc=ltc), LensFitConfig.basic(grid_step=2))


def test_aperture_helper_errors():
    with pytest.raises(ValueError, match="a depth lies on the focus plane z = 150.0 mm"):
        scale_ratio(np.array([0.0, 150.0]), 150.0, -100.0)
    with pytest.raises(ValueError, match="half_width_mm must be > 0"):
        ApertureGrid(0.0, 8)
    with pytest.raises(ValueError, match="cells must be >= 2"):
        ApertureGrid(1.0, 1)
    grid = ApertureGrid(1.0, 4)
    with pytest.raises(ValueError, match="need k >= 1 samples"):
        ring_samples(np.ones((1, 4, 4)), grid, 0)
    with pytest.raises(ValueError, match=r"1 distribution\(s\) have no positive mass"):
        ring_samples(-np.ones((1, 4, 4)), grid, 2)
    _, ws = ring_samples(np.eye(4)[None], grid, 8, iterations=0)  # 4 cells, 8 samples
    np.testing.assert_allclose(ws, 1 / 8, atol=1e-12)  # cells are split: equal masses


def test_resample_maps_an_lcd_pixel_by_similar_triangles():
    """One LCD pixel 1 px right of the principal ray, beyond focus (ratio -2): on the
    aperture it is a 2-pitch box 2 pitches left of the ray's aperture point (inverted)."""
    pitch = 0.25
    h = np.zeros((1, 8, 8))
    h[0, 3, 5] = 1.0
    origin = np.array([[10, 20]])
    q = np.array([[15 * pitch, 23 * pitch]])
    grid = ApertureGrid(2.0, 200)
    m = resample(h, origin, q - [pitch, 0.0], np.array([[0.1, 0.2]]), -2.0, pitch, grid, sub=2)
    assert m.sum() == pytest.approx(1.0, abs=1e-12)
    mean, cov = grid_moments(m, grid)
    np.testing.assert_allclose(mean[0], [0.1 - 2 * pitch, 0.2], atol=1e-9)
    np.testing.assert_allclose(np.diag(cov[0]), (2 * pitch) ** 2 / 12, rtol=0.01)


def test_fusion_weights_minimise_the_predicted_error():
    """Closed form against brute force over the simplex, and the limiting cases."""
    np.testing.assert_allclose(fusion_weights(np.array([[0.1, 0.2, 0.3]]), np.zeros((1, 3)),
                                              np.ones((1, 3), bool)), [[1, 0, 0]], atol=1e-3)
    np.testing.assert_allclose(fusion_weights(np.array([[0.1, 0.1]]), np.array([[0.2, 0.2]]),
                                              np.ones((1, 2), bool)), [[0.5, 0.5]], atol=1e-12)
    rng = np.random.default_rng(0)
    b, n = rng.uniform(0.02, 0.1, (50, 3)), rng.uniform(0.0, 0.2, (50, 3))
    w = fusion_weights(b, n, np.ones((50, 3), bool))
    t = np.linspace(0, 1, 201)
    w1, w2 = np.meshgrid(t, t)
    cand = np.stack([w1, w2, 1 - w1 - w2], -1).reshape(-1, 3)
    cand = cand[cand[:, 2] >= 0]

    def cost(ww, i):
        return (ww @ b[i]) ** 2 + (ww**2) @ (n[i] ** 2)

    for i in range(50):
        assert cost(w[i], i) <= cost(cand, i).min() + 1e-9
    assert fusion_weights(b[:1], n[:1], np.zeros((1, 3), bool)).sum() == 0.0


def test_samples_match_moments():
    grid = ApertureGrid(4.0, 32)
    pts = grid.points().reshape(-1, 2)
    mass = (np.hypot(pts[:, 0] - 0.5, pts[:, 1]) < 3.0).astype(float).reshape(1, 32, 32)
    x, w = ring_samples(mass, grid, 32)
    mean, cov = grid_moments(mass, grid)
    target = cov + np.eye(2) * 0.1
    y = match_moments(x, w, mean, target)
    m = np.einsum("nk,nki->ni", w, y)
    d = y - m[:, None]
    np.testing.assert_allclose(m, mean, atol=1e-12)
    np.testing.assert_allclose(np.einsum("nk,nki,nkj->nij", w, d, d), target, atol=1e-12)


def test_ray_fit_in_pixel_blocks_equals_one_block(bench, truth, monkeypatch):
    """The principal rays are fitted per pixel, so fitting them in blocks (memory bounded
    whatever the sensor) changes nothing, bit for bit; the optical centres summed over
    blocks of rays agree to rounding."""
    import dataclasses

    from station.lens import geometry

    vol = make_volume(bench, truth, seed=11)
    whole = geometry.fit_geometry(vol)
    monkeypatch.setattr(geometry, "RAY_FIT_PIXELS", 37)
    blocks = geometry.fit_geometry(vol)
    for f in dataclasses.fields(whole.rays):
        np.testing.assert_array_equal(getattr(blocks.rays, f.name), getattr(whole.rays, f.name),
                                      err_msg=f.name)
    np.testing.assert_array_equal(blocks.centre.position, whole.centre.position)
    # the centre fits sum over blocks of rays: only the order of the sums changes
    from station.lens import centre

    monkeypatch.setattr(centre, "BLOCK_RAYS", 53)
    summed = geometry.fit_geometry(vol)
    for a, b in ((summed.centre_rays, whole.centre_rays), (summed.centre, whole.centre)):
        np.testing.assert_allclose(a.position, b.position, rtol=0, atol=1e-9)
        np.testing.assert_allclose(a.covariance, b.covariance, rtol=1e-9, atol=1e-15)
        np.testing.assert_array_equal(a.weights > 0, b.weights > 0)


def test_local_plane_fit_passes_a_linear_field_and_averages_the_noise():
    """A field linear in (u, v) comes back exactly at every pixel, border and corners
    included; unusable pixels do not count; independent noise shrinks by about the square
    root of the window's pixel count (9 x 9 = 81: ~9 x, fewer at the border)."""
    from station.lens.derive import local_plane_fit

    w, h = 40, 30
    v, u = np.divmod(np.arange(w * h), w)
    field = np.stack([0.3 + 0.01 * u - 0.02 * v, -1.0 + 0.005 * v], axis=1)
    ok = np.ones(w * h, bool)
    ok[::7] = False
    values = np.where(ok[:, None], field, 1e6)  # unusable pixels hold garbage
    pixels = np.arange(w * h)
    var = np.ones(w * h)
    np.testing.assert_allclose(local_plane_fit(values, var, ok, (w, h), pixels, 4), field,
                               atol=1e-9)
    noise = np.random.default_rng(0).normal(0, 1, field.shape)
    out = local_plane_fit(field + noise, var, np.ones(w * h, bool), (w, h), pixels, 4)
    inner = (u >= 4) & (u < w - 4) & (v >= 4) & (v < h - 4)
    assert np.std((out - field)[inner]) < 0.15
    assert np.std(out - field) < 0.25
    np.testing.assert_array_equal(local_plane_fit(values, var, ok, (w, h), pixels, 0), values)


@pytest.mark.slow
def test_focus_zones_recover_the_spherical_aberration(bench, clean):
    """The focus per pupil zone, fitted to the LTCs at the optical centre with the bench's
    pixels as boxes (the fake integrates each pixel's area), follows the true
    ``z_f + spherical (rho / rho_max)^2`` (250 -> 256 mm) and finds the pupil radius; the lens
    file carries the table and its rays aim at their zone's focus."""
    from station.lens.zones import fit_focus_zones

    vol, r = clean
    c, g = bench.config, r.geometry
    rim = bench.lens.pupil_radius_mm
    table, fit = fit_focus_zones(vol, float(g.centre.position[2]), g.camera_matrix,
                                 g.focus_distance_mm, 0.9 * rim, pixel_samples=0)
    truth = c.focus_distance_mm + c.spherical_mm * (table[:, 0] / rim) ** 2
    print(f"\nfocus zones: rho {np.round(table[:, 0], 2)} mm\n fitted {np.round(table[:, 1], 2)}"
          f"\n true   {np.round(truth, 2)}; radius {fit['radius_mm']:.3f} (true {rim}) mm")
    assert abs(fit["radius_mm"] - rim) < 0.05 * rim
    assert np.max(np.abs(table[:, 1] - truth)) < 1.5
    assert table[-1, 1] - table[0, 1] == pytest.approx(c.spherical_mm, abs=1.5)
    assert fit["cost"] < fit["cost_single_focus"]
    assert r.lens.focus_zones_mm is None  # off by default
    lens = dataclasses.replace(r.lens, focus_zones_mm=table)
    zones = lens.focus_zones_mm
    b = lens.bundle(np.zeros((1, 2)), np.asarray(g.camera_matrix[:2, 2])[None])
    rho = np.hypot(b.origins[0, :, 0], b.origins[0, :, 1])
    t = b.directions[0, :, 2]  # rays of the centre pixel cross the axis at their zone's focus
    z_cross = rho / np.hypot(b.directions[0, :, 0], b.directions[0, :, 1]) * t
    np.testing.assert_allclose(z_cross, np.interp(rho, zones[:, 0], zones[:, 1]), rtol=1e-9)


def _blur_at(bundle, z_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's blur on the plane z: centroid (n, 2) mm and x skew (n,)."""
    o, d, w = bundle.origins, bundle.directions, bundle.weights
    p = o[..., :2] + d[..., :2] * ((z_mm - o[..., 2]) / d[..., 2])[..., None]
    w = w / w.sum(axis=1, keepdims=True)
    c = (w[..., None] * p).sum(axis=1)
    q = p[..., 0] - c[:, None, 0]
    return c, (w * q**3).sum(axis=1) / (w * q**2).sum(axis=1) ** 1.5


@pytest.mark.slow
def test_zoned_lens_follows_the_true_blur_and_finds_the_centre(bench, clean):
    """With ``focus_zones`` the LTCs are mapped onto the aperture plane through each zone's
    focus and the optical centre is refitted with the zones' misses removed. Against the
    bench's own lens (6 mm of spherical aberration, strong vignetting): the centre's axial
    error (one focus: -76 um, the vignetted principal rays' miss taken for a scale), the
    blur's centroid and its skew across focus are all at most half of one focus's."""
    vol, single = clean
    zoned = derive_lens(vol, LensFitConfig.basic(focus_zones=True))
    true_c = bench.optical_centre_station_mm()
    err = {name: float(r.geometry.centre.position[2] - true_c[2]) * 1e3
           for name, r in (("single", single), ("zoned", zoned))}
    assert zoned.lens.focus_zones_mm is not None
    fit = zoned.lens.metadata["focus_zone_fit"]
    assert fit["centre_shift_mm"] * 1e3 == pytest.approx(err["zoned"] - err["single"], abs=1e-6)
    lens = bench.lens.model_copy(update={"samples": 20000})
    w, h = bench.config.camera_size
    uu, vv = np.meshgrid(np.arange(0, w, 3), np.arange(0, h, 3))
    uv = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(np.float64)
    xy = (uv - bench.K[:2, 2]) / bench.K[0, 0]
    scores = {}
    for name, r in (("single", single), ("zoned", zoned)):
        dc, dskew = [], []
        for z in (200.0, 300.0):  # before and beyond the focus (250 - 256 mm)
            ct, st = _blur_at(lens.bundle(xy, uv), z)
            cm, sm = _blur_at(r.lens.bundle(xy, uv), z)
            dc.append(np.abs(cm - ct).mean() * 1e3)
            dskew.append(np.abs(sm - st).mean())
        scores[name] = (max(dc), max(dskew))
    print(f"\ncentre z error {err} um; blur centroid error, skew error {scores}")
    assert abs(err["zoned"]) < 0.5 * abs(err["single"])
    assert scores["zoned"][0] < 0.5 * scores["single"][0]
    assert scores["zoned"][1] < 0.5 * scores["single"][1]
