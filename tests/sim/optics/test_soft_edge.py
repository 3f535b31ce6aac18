"""``AberratedLens(edge="soft")``: the same lens as the hard-edged one in the limit of many
samples, but its weights move continuously with the field, so few samples converge."""

import numpy as np

from sim.optics.lens import AberratedLens


def _lens(samples: int, edge: str) -> AberratedLens:
    return AberratedLens(pupil_diameter_mm=16.0, focus_distance_mm=760.0,
                         vignetting_shift_mm=30.0, samples=samples, edge=edge)


def _transmission_and_centroid(lens: AberratedLens, x_n: np.ndarray):
    b = lens.bundle(np.stack([x_n, np.zeros_like(x_n)], axis=1))
    w = b.weights.sum(axis=1)
    return w, (b.weights * b.origins[..., 0]).sum(axis=1) / w


def test_soft_edge_converges_to_the_exact_vignetted_pupil_with_few_samples():
    # exact: the pupil (radius 8) clipped by an equal circle shifted by 30 * 0.2 = 6 mm: the
    # lens-shaped overlap of two radius-8 circles 6 mm apart, centroid at 3 mm
    d, r = 6.0, 8.0
    area = 2 * r * r * np.arccos(d / (2 * r)) - d / 2 * np.sqrt(4 * r * r - d * d)
    w, cx = _transmission_and_centroid(_lens(256, "soft"), np.array([0.2]))
    assert abs(w[0] - area / (np.pi * r * r)) < 1e-3
    assert abs(cx[0] - d / 2) < 0.01  # mm on the aperture
    w_hard, cx_hard = _transmission_and_centroid(_lens(256, "hard"), np.array([0.2]))
    assert abs(cx_hard[0] - d / 2) > 5 * abs(cx[0] - d / 2)


def test_soft_edge_weights_vary_smoothly_with_the_field():
    x = np.linspace(0.0, 0.2, 201)
    rough = {e: np.abs(np.diff(_transmission_and_centroid(_lens(256, e), x)[1], 2)).max()
             for e in ("hard", "soft")}
    assert rough["soft"] < rough["hard"] / 20


def test_hard_edge_is_the_default_and_unchanged():
    lens = AberratedLens(pupil_diameter_mm=16.0, focus_distance_mm=760.0,
                         vignetting_shift_mm=30.0)
    assert lens.edge == "hard"
    w = lens.transmission(np.array([[0.2, 0.0]]), np.array([[0.0, 0.0], [7.9, 0.0], [-2.1, 0]]))
    assert w.tolist() == [[1.0, 1.0, 0.0]]
