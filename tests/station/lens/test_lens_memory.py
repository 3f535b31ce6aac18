"""The lens derivation's memory-saving forms give the values of the plain ones, bit for bit
(six full-size depths in 4 GB): the summary's residual statistics and the
transmittance computed in blocks."""

from types import SimpleNamespace

import numpy as np
from scipy import ndimage

from station.lens import derive, result
from station.lens.centroids import STATUS_NO_SIGNAL, STATUS_OK
from station.lens.rays import FLAG_BAD_FIT, PrincipalRays


def _rays(rng, d: int, n: int) -> PrincipalRays:
    res = rng.gamma(2.0, 0.003, (d, n)).astype(np.float32)
    used = rng.random((d, n)) > 0.1
    res[~used] = np.nan
    flags = np.where(rng.random(n) > 0.9, FLAG_BAD_FIT, 0).astype(np.int8)
    z = np.zeros(n)
    return PrincipalRays(z, np.zeros((n, 2)), np.zeros((n, 2)), z, z, None, used, flags, res)


def test_residual_stats_are_numpys_mean_and_std(monkeypatch):
    monkeypatch.setattr(result, "RESIDUAL_PIXELS", 1000)  # several blocks
    rng = np.random.default_rng(3)
    for d, n in ((6, 4321), (2, 999), (3, 1)):
        rays = _rays(rng, d, n)
        parts = []
        for a0 in range(0, n, 1000):
            x = rays.residual_mm[:, a0:a0 + 1000]
            parts.append(x[rays.used[:, a0:a0 + 1000] & rays.usable[None, a0:a0 + 1000]
                           & np.isfinite(x)])
        x = np.concatenate(parts)
        mean, std, count = result._residual_stats(rays)
        assert count == x.size
        if count:
            assert mean == float(x.mean(dtype=np.float64))
            assert std == float(x.std(dtype=np.float64))
    none = _rays(rng, 2, 5)
    none.used[:] = False
    assert result._residual_stats(none) == (None, None, 0)


def test_transmittance_in_row_blocks_equals_the_sensor_wide_filter(monkeypatch):
    rng = np.random.default_rng(4)
    d, h, w = 3, 23, 17
    gain = rng.uniform(1000.0, 3000.0, (d, h, w))
    status = np.where(rng.random((d, h, w)) > 0.2, STATUS_OK, STATUS_NO_SIGNAL).astype(np.int8)
    status[:, 4, 5] = STATUS_NO_SIGNAL  # a pixel without any valid depth
    vol = SimpleNamespace(camera_size=(w, h), gain=gain)
    monkeypatch.setattr(derive, "tile_shape", lambda volume: (5, 5))
    g = np.where(status == STATUS_OK, gain, np.nan)
    tg = np.nan_to_num(np.nanmedian(np.where(np.isfinite(g).any(axis=0), g, 0.0), axis=0))
    ref = tg / ndimage.median_filter(tg, size=3).max()
    for step in (1, 3):
        nu, nv = derive.node_positions(w, step), derive.node_positions(h, step)
        got = derive._transmittance(vol, status, nu, nv)
        want = ref[nv][:, nu]
        np.testing.assert_array_equal(got, want)
        # the lens file stores the array's own layout: numpy's column-major one
        assert got.flags.f_contiguous == want.flags.f_contiguous
