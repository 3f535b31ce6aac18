"""Each node's aim offset makes the measured lens's principal rays follow the station's
measured slopes: against the fake bench's true LTC centroids, the lens file's implied
principal-ray slopes come closer to the true ones with it than without."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from fakes.bench import BenchConfig, FakeBench
from sim.optics.projection import pixel_to_normalized
from station.api import derive_lens, lens_config
from station.lens.derive import aim_offsets, local_ray_slopes, sample_moment
from station.lens.geometry import LensFitConfig
from tests.support.ltc_stores import write_true_ltc_store

DEPTHS = [0.0, 30.0, 60.0, 250.0, 290.0, 320.0]


@pytest.fixture(scope="module")
def bench_store(tmp_path_factory):
    bench = FakeBench(BenchConfig.small(lcd_size=(120, 96), lcd_distance_at_zero_mm=100.0,
                                        pupil_samples=150, subpixels=1))
    path = write_true_ltc_store(tmp_path_factory.mktemp("aim") / "ltc.zarr", bench, DEPTHS,
                                period=24, tile_px=16)
    return bench, path


def implied_slopes(lens, uv):
    """The principal-ray slope (n, 2) the lens file implies at pixels uv: xy_n + e minus the
    samples' sum w p / z_k."""
    x, y, w = lens.samples_at(uv)
    m = sample_moment(x, y, w, lens.aim_depths)
    return pixel_to_normalized(uv, lens.camera_matrix, lens.dist_coeffs) \
        + lens.aim_offset_at(uv) - m


def test_aim_offsets_bring_the_principal_rays_to_the_true_slopes(bench_store):
    bench, path = bench_store
    plain = derive_lens(path, LensFitConfig.basic(), progress=False)
    aimed = derive_lens(path, LensFitConfig.basic(aim_offset_sigma_px=2.0), progress=False)
    assert plain.lens.aim_offset is None
    e = aimed.lens.aim_offset
    assert e.shape == plain.lens.weights.shape[:2] + (2,)
    # its mean removed before the smoothing (whose border handling leaves a trace)
    assert np.all(np.abs(e.mean(axis=(0, 1))) < 0.05 * np.sqrt((e**2).mean()))
    # the samples are the same: the offsets only move where they aim
    np.testing.assert_array_equal(aimed.lens.aperture_x_mm, plain.lens.aperture_x_mm)
    # the true principal rays: lines through the exact LTC centroids at the depths (station
    # frame, as the station fits them), turned into the camera frame
    w, h = bench.config.camera_size
    pitch = bench.config.lcd_pitch_mm
    z = np.asarray(DEPTHS)
    c = np.stack([bench.true_centroids_lcd_px(d).reshape(-1, 2) * pitch for d in DEPTHS])
    zc = z - z.mean()
    s = np.einsum("d,dnk->nk", zc, c - c.mean(axis=0)) / (zc @ zc)
    d3 = np.concatenate([s, np.ones((len(s), 1))], axis=1) @ aimed.geometry.rotation.T
    true = d3[:, :2] / d3[:, 2:]
    uu, vv = np.meshgrid(np.arange(w), np.arange(h))
    uv = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(np.float64)
    measured = local_ray_slopes(aimed.geometry, np.arange(w * h), 4)

    def smooth_miss(lens, ref, sigma_px):
        """RMS (urad) of the field of implied minus reference slopes, low-passed (Gaussian of
        sigma_px) and without its mean, 3 px from the border."""
        d = (implied_slopes(lens, uv) - ref).reshape(h, w, 2)
        d = np.stack([gaussian_filter(d[..., k], sigma_px, mode="nearest") for k in range(2)],
                     axis=-1)[3:-3, 3:-3]
        d = d - d.mean(axis=(0, 1))
        return float(np.sqrt((d**2).sum(axis=-1).mean()) * 1e6)

    # the lens now follows the station's measured principal rays at the offsets' own scale
    # (4.2 -> 0.7 urad here) ...
    before = smooth_miss(plain.lens, measured, 2.0)
    after = smooth_miss(aimed.lens, measured, 2.0)
    assert after < 0.3 * before, (before, after)
    # ... and so its systematic part comes closer to the true rays' (8.9 -> 7.9 urad on this
    # bench, whose per-pixel slope noise is ~70 urad: the measurement limits it)
    before, after = smooth_miss(plain.lens, true, 4.0), smooth_miss(aimed.lens, true, 4.0)
    assert after < 0.95 * before, (before, after)


def test_aim_offsets_fill_flagged_nodes_and_keep_a_linear_field():
    """Flagged nodes take the nearest good node's offset; the mean is removed; smoothing
    keeps a field linear in the node indices away from the border."""
    gv, gu = 12, 16
    j, i = np.mgrid[0:gv, 0:gu].astype(np.float64)
    field = np.stack([1e-6 * i, -2e-6 * j], axis=-1)
    good = np.ones((gv, gu), bool)
    good[5, 7] = False
    slope_term = field + 3e-6  # a constant: removed
    moment = np.zeros_like(field)
    slope_term[5, 7] = 1.0  # a flagged node's own value is never used
    e = aim_offsets(slope_term, moment, good, sigma_nodes=1.0)
    want = field - field[good].mean(axis=0)
    np.testing.assert_allclose(e[3:-3, 3:-3], want[3:-3, 3:-3], atol=0.3e-6)
    e0 = aim_offsets(slope_term, moment, good, sigma_nodes=0.0)
    np.testing.assert_allclose(e0[5, 7], e0[5, 6], atol=1e-15)
    np.testing.assert_allclose(e0[good].mean(axis=0), 0.0, atol=1e-15)


def test_unknown_or_bad_lens_settings_are_refused_by_name(bench_store):
    from station.errors import UsageError

    _, path = bench_store
    with pytest.raises(UsageError, match="aim_offset_sigma"):
        lens_config(aim_offset_sigma=2.0)
    with pytest.raises(UsageError, match="aim_offset_sigma_px"):
        lens_config(aim_offset_sigma_px=-1.0)
