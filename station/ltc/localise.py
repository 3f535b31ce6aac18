"""Decode the localisation patterns of a :class:`station.acquisition.patterns.StationPatternPlan`: map
every camera pixel to the LCD coordinates it sees (the coarse centre used for unfolding).

Per axis: the Gray code gives the half-period stripe ``m`` (pixels ``m Q/2 .. (m+1) Q/2 - 1``),
thresholded at the mean of the white and black frames; its centre
``u_c = (m + 1/2) Q/2 - 1/2`` snaps the phase-shift coordinate ``u_p = phi Q / (2 pi)``
to the right period: ``u = u_p + Q round((u_c - u_p) / Q)``. A stripe misread next to a
boundary (blur) is off by one stripe, which still leaves ``|u_c - u| < Q/2`` while the
blur radius stays below ``Q/4``. The result is the pixel's first-harmonic (circular) mean
position on the LCD at period Q, in LCD pixels, pixel centres at integers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.fpp.phase import gray_to_index, wrapped_phase
from station.acquisition.patterns import StationPatternPlan


@dataclass(frozen=True)
class LcdMap:
    """Where camera pixels look on the LCD, all (n,) or (n, 2) float64.

    xy : LCD (x, y) in LCD pixels (NaN where the pixel sees no contrast).
    contrast : white minus black response (ADU).
    modulation : phase-shift amplitude per axis (n, 2), ADU.
    """

    xy: np.ndarray
    contrast: np.ndarray
    modulation: np.ndarray


def decode_axis(
    gray: np.ndarray, phase: np.ndarray, threshold: np.ndarray, period: int
) -> tuple[np.ndarray, np.ndarray]:
    """One axis: Gray frames (b, n), phase frames (steps, n), threshold (n,) -> coordinate
    (n,) LCD pixels and phase modulation (n,) (same units as the frames)."""
    stripe = gray_to_index(np.asarray(gray) > threshold[None, :])
    wp = wrapped_phase(np.asarray(phase, dtype=np.float64)[:, :, None])
    u_p = wp.phase[:, 0] * period / (2 * np.pi)
    u_c = (stripe + 0.5) * (period / 2) - 0.5
    return u_p + period * np.round((u_c - u_p) / period), wp.modulation[:, 0]


def lcd_coordinates(frames: np.ndarray, plan: StationPatternPlan) -> LcdMap:
    """Decode the localisation frames of a plan.

    frames : (patterns, n) responses of n camera pixels to every pattern of ``plan``
    (only the localisation ones are read). Pixels with no white-black contrast get NaN.
    """
    frames = np.asarray(frames)
    if frames.ndim != 2 or frames.shape[0] != len(plan):
        raise ValueError(f"frames must be (patterns={len(plan)}, pixels), got {frames.shape}")
    idx = plan.indices
    white = frames[idx["white"][0]].astype(np.float64)
    black = frames[idx["black"][0]].astype(np.float64)
    threshold = 0.5 * (white + black)
    q = plan.localisation.period
    x, mx = decode_axis(frames[idx["gray_x"]], frames[idx["phase_x"]], threshold, q)
    y, my = decode_axis(frames[idx["gray_y"]], frames[idx["phase_y"]], threshold, q)
    contrast = white - black
    xy = np.stack([x, y], axis=1)
    xy[~(contrast > 0)] = np.nan
    return LcdMap(xy=xy, contrast=contrast, modulation=np.stack([mx, my], axis=1))
