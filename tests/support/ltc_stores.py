"""An LTC store of a fake bench's true LTC plus noise, for the lens tests (shared by the
engine and CLI tests)."""

from __future__ import annotations

import numpy as np

from fakes.bench import FakeBench
from station.ltc.store import (
    centred_origins,
    create_ltc_store,
    mark_depth_complete,
    windows_from_sparse,
)


def write_true_ltc_store(path, bench: FakeBench, depths_mm: list[float], *, period: int = 24,
                         noise: float = 6e-4, tile_px: int = 64, with_k: bool = True,
                         hole_px: tuple[int, int] | None = None, hole_depths: int = 0,
                         gain_jitter: float = 0.0):
    """Write the bench's true LTC at ``depths_mm`` in P x P windows plus Gaussian noise of std
    ``noise`` per weight (renormalised), gain 3000 (+ uniform ``gain_jitter``), every depth
    marked complete. ``hole_px`` (row, col): a pixel without signal at the first
    ``hole_depths`` depths. ``with_k``: record the bench's camera matrix. Returns ``path``."""
    c = bench.config
    w, h = c.camera_size
    p = period
    g = create_ltc_store(path, depths_mm=list(depths_mm), camera_size=c.camera_size, period=p,
                         pitch_mm=c.lcd_pitch_mm, lcd_size=c.lcd_size,
                         attrs={"camera_matrix": bench.K.tolist()} if with_k else None,
                         tile_px=tile_px)
    rng = np.random.default_rng(0)
    for i, z in enumerate(depths_mm):
        org = centred_origins(bench.true_centroids_lcd_px(z).reshape(-1, 2), p)
        win = windows_from_sparse(bench.true_ltc(z, normalise=True), c.lcd_size, p, org)
        win = win + rng.normal(0.0, noise, win.shape)
        win = (win / win.sum(axis=(1, 2), keepdims=True)).reshape(h, w, p, p)
        if hole_px is not None and i < hole_depths:
            win[hole_px] = np.nan
        g["ltc"][i] = win
        g["origin"][i] = org.reshape(h, w, 2)
        gain = np.full((h, w), 3000.0)
        if gain_jitter:
            gain = gain + rng.uniform(0, gain_jitter, (h, w))
        g["gain"][i] = gain
        g["noise"][i] = np.full((h, w), noise)
        mark_depth_complete(g, i, all_tiles=True)
    return path
