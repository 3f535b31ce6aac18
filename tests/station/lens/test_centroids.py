"""Centroids of LTC windows: exact on analytic and ground-truth LTC, noise propagated."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fakes.bench import BenchConfig, FakeBench
from station.lens.centroids import (
    STATUS_NO_SIGNAL,
    STATUS_OK,
    STATUS_TRUNCATED,
    compute_centroids,
    window_stats,
)
from station.ltc.store import (
    LtcStoreError,
    LtcVolume,
    LtcVolumeError,
    centred_origins,
    create_ltc_store,
    mark_depth_complete,
    open_ltc_volume,
    windows_from_sparse,
)

P = 24
DEPTHS = (0.0, 250.0)  # stage readings: 100 mm and 350 mm from the pupil (focus at 250 mm)


@pytest.fixture(scope="module")
def bench() -> FakeBench:
    return FakeBench(BenchConfig.small(lcd_size=(120, 96), lcd_distance_at_zero_mm=100.0,
                                       pupil_samples=150, subpixels=2))


def bench_windows(bench: FakeBench, z: float) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free windows (H*W, P, P) centred on the true centroids, and their origins."""
    c = bench.config
    org = centred_origins(bench.true_centroids_lcd_px(z).reshape(-1, 2), P)
    return windows_from_sparse(bench.true_ltc(z, normalise=True), c.lcd_size, P, org), org


@pytest.fixture(scope="module")
def volume(bench) -> LtcVolume:
    w, h = bench.config.camera_size
    wins, orgs = zip(*(bench_windows(bench, z) for z in DEPTHS), strict=True)
    d = len(DEPTHS)
    return LtcVolume(np.array(wins).reshape(d, h, w, P, P), np.array(orgs).reshape(d, h, w, 2),
                     np.ones((d, h, w)), np.zeros((d, h, w)), np.array(DEPTHS),
                     bench.config.lcd_pitch_mm, camera_matrix=bench.K, name="bench")


def test_analytic_windows():
    h = np.zeros((3, 9, 9))
    h[0, 2:5, 5:8] = 1 / 9  # 3x3 box centred on (x=6, y=3)
    h[1, 4, 4], h[1, 4, 5] = 0.25, 0.75  # two pixels: x = 4.75
    h[2, 0:3, 3:6] = 1 / 9  # a box touching the top border
    st = window_stats(h, np.zeros(3))
    np.testing.assert_allclose(st.centroid[:2], [[6.0, 3.0], [4.75, 4.0]], atol=1e-12)
    np.testing.assert_allclose(st.moments[0], [2 / 3, 2 / 3, 0.0], atol=1e-12)
    np.testing.assert_allclose(st.moments[1], [0.1875, 0.0, 0.0], atol=1e-12)
    assert st.status.tolist() == [STATUS_OK, STATUS_OK, STATUS_TRUNCATED]
    np.testing.assert_array_equal(st.centroid_std[:2], 0.0)


def test_centroids_equal_the_true_ones(bench, volume, monkeypatch):
    c = compute_centroids(volume)
    monkeypatch.setattr("station.lens.centroids.WINDOWS_PER_BATCH", 97)  # odd batches, odd tiles
    tiled = compute_centroids(volume, rows_per_tile=7)
    np.testing.assert_array_equal(tiled.xy_lcd_px, c.xy_lcd_px)
    np.testing.assert_array_equal(tiled.moments_px2, c.moments_px2)
    assert c.valid.all()
    for i, z in enumerate(DEPTHS):
        np.testing.assert_allclose(c.xy_lcd_px[i], bench.true_centroids_lcd_px(z), atol=1e-9)
    pts = c.points_mm()
    np.testing.assert_allclose(pts[..., :2], c.xy_lcd_px * bench.config.lcd_pitch_mm)
    np.testing.assert_array_equal(pts[1, ..., 2], DEPTHS[1])
    # second moments: the LTC widens with defocus, 150 mm before and 100 mm beyond focus
    tr = c.moments_px2[..., 0] + c.moments_px2[..., 1]
    assert np.median(tr[0]) > np.median(tr[1])


@pytest.mark.parametrize("z", [DEPTHS[0], 110.0])  # a large LTC, and one near focus
def test_noise_propagates_to_the_centroid_std(bench, z):
    """Monte Carlo: the predicted centroid and second-moment stds match the scatter of 400
    noisy copies; for a small LTC the region centroid is far less noisy than the whole
    window's (docs/optics.md section 5)."""
    w, _ = bench.config.camera_size
    win = bench_windows(bench, z)[0][15 * w + 20]
    sigma = 6e-4  # the default camera's per-weight noise for P = 24 (see test_derive)
    rng = np.random.default_rng(1)
    noisy = win[None] + rng.normal(0.0, sigma, (400, P, P))
    st = window_stats(noisy, np.full(400, sigma))
    assert (st.status == STATUS_OK).all()
    truth = window_stats(win[None], np.zeros(1)).centroid[0]
    scatter = st.centroid.std(axis=0)
    predicted = np.median(st.centroid_std, axis=0)
    np.testing.assert_allclose(scatter / predicted, 1.0, atol=0.15)
    assert np.all(np.abs(st.centroid.mean(axis=0) - truth) < 4 * predicted / np.sqrt(400) + 0.01)
    tr_scatter = (st.moments[:, 0] + st.moments[:, 1]).std()
    assert 0.8 < tr_scatter / np.median(st.trace_std) < 1.25
    if z == 110.0:
        y, x = np.mgrid[0:P, 0:P]
        whole = np.stack([(noisy * x).sum((1, 2)), (noisy * y).sum((1, 2))], 1) / noisy.sum(
            (1, 2))[:, None]
        assert np.all(whole.std(axis=0) > 3 * scatter)


def test_no_signal_windows():
    rng = np.random.default_rng(0)
    h = np.full((2, 8, 8), np.nan)
    h[1] = rng.normal(0, 1e-3, (8, 8))
    h[1] += (1 - h[1].sum()) / 64  # sums to 1 but is flat: nothing above the noise
    st = window_stats(h, np.array([np.nan, 0.05]))
    assert st.status.tolist() == [STATUS_NO_SIGNAL, STATUS_NO_SIGNAL]
    assert np.isnan(st.centroid).all() and not st.region.any()


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda h, s: h.__setitem__((1, 2, 3, 0, 0), np.nan),
         r"bench: ltc\[1, 2, 3\] mixes NaN and finite weights"),
        (lambda h, s: h.__setitem__((0, 4, 5), 0.0),
         r"bench: ltc\[0, 4, 5\] has finite weights summing to <= 0"),
        (lambda h, s: s.__setitem__((1, 0, 7), np.nan),
         r"bench: ltc\[1, 0, 7\] has a finite LTC but its noise estimate is NaN"),
    ],
)
def test_broken_windows_raise_with_their_location(volume, edit, message):
    ltc, noise = np.array(volume.ltc), np.array(volume.noise)
    edit(ltc, noise)
    with pytest.raises(LtcVolumeError, match=message):
        compute_centroids(dataclasses.replace(volume, ltc=ltc, noise=noise))


@pytest.mark.parametrize(
    ("over", "message"),
    [
        ({"depths_mm": np.array([0.0])},
         "depths_mm has 1 depth.s.; the lens derivation needs at least 2"),
        ({"depths_mm": np.array([0.0, 0.0])}, "depths_mm must be finite and distinct"),
        ({"pitch_mm": 0.0}, "pitch_mm must be > 0"),
        ({"camera_matrix": np.eye(2)}, "camera_matrix must be a finite 3x3 K"),
    ],
)
def test_volume_validation(volume, over, message):
    with pytest.raises(LtcVolumeError, match=f"bench: {message}"):
        dataclasses.replace(volume, **over)


def test_volume_shape_validation(volume):
    with pytest.raises(LtcVolumeError, match=r"ltc has shape \(2, 30, 40, 24, 23\), expected"):
        dataclasses.replace(volume, ltc=np.zeros((2, 30, 40, 24, 23)))
    with pytest.raises(LtcVolumeError, match=r"gain has shape \(2, 30, 41\), expected \(2, 30, "
                       r"40\)"):
        dataclasses.replace(volume, gain=np.zeros((2, 30, 41)))


def test_open_store_reads_camera_matrix_and_checks_attributes(tmp_path, bench, volume):
    c = bench.config
    g = create_ltc_store(tmp_path / "a.zarr", depths_mm=list(DEPTHS), camera_size=c.camera_size,
                         period=P, pitch_mm=c.lcd_pitch_mm, lcd_size=c.lcd_size,
                         attrs={"camera_matrix": bench.K.tolist()})
    for name in ("ltc", "origin", "gain", "noise"):
        g[name][:] = np.asarray(getattr(volume, name))
    for i in range(len(DEPTHS)):
        mark_depth_complete(g, i, all_tiles=True)
    v = open_ltc_volume(tmp_path / "a.zarr")
    np.testing.assert_array_equal(v.camera_matrix, bench.K)
    got = compute_centroids(v)
    np.testing.assert_allclose(got.xy_lcd_px, compute_centroids(volume).xy_lcd_px, atol=1e-4)
    del g.attrs["pitch_mm"]
    with pytest.raises(LtcStoreError, match=r"a\.zarr: attribute 'pitch_mm' is missing"):
        open_ltc_volume(tmp_path / "a.zarr")
