"""The stereo matcher's sub-pixel search and left-right check at their edge cases, against
constructed maps with known answers."""

from __future__ import annotations

import numpy as np

from sim.fpp.match import _lr_consistent, _refine, _Side
from sim.optics.rig import DeviceCalibration


def identity_side(coef: np.ndarray) -> _Side:
    """A search side whose rectified frame is its pixel grid (x = u, y = v)."""
    h, w = coef.shape[:2]
    k = np.array([[100.0, 0.0, (w - 1) / 2], [0.0, 100.0, (h - 1) / 2], [0.0, 0.0, 1.0]])
    cam = DeviceCalibration(name="c", K=k, dist=np.zeros(5), R=np.eye(3), T=np.zeros(3),
                            size=(w, h))
    p = np.concatenate([k, np.zeros((3, 1))], axis=1)
    return _Side(np.zeros((h, w)), cam, np.eye(3), p, (0, w - 1), coef, np.zeros((h, w)))


def test_refine_matches_in_the_step_between_two_pixel_models():
    # each pixel's model is u + e: e = -0.01 on even, +0.01 on odd columns, so between an
    # even column and the next the models step over (j + 0.49, j + 0.51): no root in either
    # cell; between an odd column and the next they overlap, with a root in each
    h, w = 5, 12
    coef = np.zeros((h, w, 6))
    u = np.arange(w)
    coef[..., 0] = u + np.where(u % 2 == 0, -0.01, 0.01)
    coef[..., 1] = 1.0
    side = identity_side(coef)
    q = np.array([4.5, 4.495, 6.505, 5.5, 5.505, 7.2])
    x, uv, ok, slope = _refine(side, q - 0.7, np.full(len(q), 2.0), q)
    assert ok.all()
    # in the step: the cell edge; elsewhere the exact root of the pixel's own model
    np.testing.assert_allclose(x[:3], [4.5, 4.5, 6.5], atol=1e-9)
    np.testing.assert_allclose(x[3:], [5.49, 5.495, 7.19], atol=1e-9)
    np.testing.assert_allclose(uv[:, 0], x, atol=1e-9)
    np.testing.assert_allclose(slope, 1.0)


def test_left_right_check_reaches_the_edge_of_the_other_matches():
    # the other direction's matches: an affine map, missing from column 6 on and at (3, 2)
    h, w = 8, 10
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    back = np.stack([3.0 + 1.1 * uu + 0.05 * vv, 2.0 - 0.03 * uu + 0.98 * vv], axis=-1)
    back[:, 6:] = np.nan
    back[2, 3] = np.nan
    uv = np.array([[2.4, 4.6], [5.3, 3.2], [3.5, 2.5], [5.9, 0.2], [6.5, 4.0], [5.3, 3.2]])
    truth = np.stack([3.0 + 1.1 * uv[:, 0] + 0.05 * uv[:, 1],
                      2.0 - 0.03 * uv[:, 0] + 0.98 * uv[:, 1]], axis=1)
    ref = truth + np.array([[0.0, 0.0]] * 5 + [[0.3, 0.0]])
    ok = _lr_consistent(uv, ref, back, 1e-9)
    # inside (bilinear), at the edge, around a hole, in a corner: confirmed; 1 px beyond
    # the edge (no match among the 4 around it) and a wrong match: not
    assert ok.tolist() == [True, True, True, True, False, False]
