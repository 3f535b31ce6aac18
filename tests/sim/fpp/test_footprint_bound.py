"""The pixel-footprint correction is a small second-order shift; where its 3 x 3 models span a
step between two rows (which a quadratic across three rows fits exactly, so the model-residual
check cannot see it) it would move a pixel by several projector pixels: there the pixel keeps
its measured coordinate, and everywhere else the correction is the analytic one."""

from __future__ import annotations

import numpy as np

from sim.fpp.decode import MAX_FOOTPRINT_SHIFT, DecodeSettings, decode_view
from sim.render.fringe_patterns import PhaseShiftSet

PATTERNS = PhaseShiftSet(periods_px=[256.0, 32.0, 8.0], steps=4, direction="u")
VAR = 1.0 / 12.0
CURV = 0.004  # projector px per camera px^2 along u


def images_of(coord: np.ndarray) -> np.ndarray:
    """Noise-free phase-shift images (n, H, W) of a projector-u map (H, W), A = B = 0.4."""
    out = []
    for d in PATTERNS.descriptors((256, 64)):
        out.append(0.4 + 0.4 * np.cos(2 * np.pi * coord / d.period_px - d.phase_rad))
    return np.stack(out)


def test_a_step_between_rows_is_not_corrected_and_smooth_pixels_are():
    h, w = 40, 60
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    coord = 40.0 + 1.5 * u + 0.5 * CURV * (u - 30) ** 2 + 30.0 * (v >= 20)
    view = decode_view(images_of(coord), PATTERNS, (256, 64),
                       DecodeSettings(pixel_variance_px2=VAR))
    got = view.coord["u"]
    plain = decode_view(images_of(coord), PATTERNS, (256, 64),
                        DecodeSettings(pixel_variance_px2=0.0)).coord["u"]
    inner = np.s_[2:-2, 2:-2]
    smooth = np.ones((h, w), bool)
    smooth[18:22] = False  # the rows whose 3 x 3 spans the step
    # smooth pixels: the measured coordinate minus var * (half the trace of the curvature)
    expect = plain - VAR * CURV / 2
    assert np.allclose(got[inner][smooth[inner]], expect[inner][smooth[inner]], atol=1e-6)
    # the rows beside the step keep the measured coordinate (the model there would have moved
    # them by var * 30 px: 2.5 px, more than MAX_FOOTPRINT_SHIFT of the finest period)
    beside = got[19:21, 2:-2]
    assert np.isfinite(beside).all()
    assert np.array_equal(beside, plain[19:21, 2:-2])
    assert VAR * 30.0 > MAX_FOOTPRINT_SHIFT * 8.0
