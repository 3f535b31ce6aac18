"""sim.render.fringe_patterns: exact pattern values, order, descriptors, and decoding by sim.fpp.phase."""

import numpy as np
import pytest

from sim.fpp.phase import gray_bits, gray_to_index, wrapped_phase
from sim.render.fringe_patterns import GrayCodeSet, PhaseShiftSet

SIZE = (40, 24)  # projector (width, height)


def test_phase_shift_values_follow_the_convention():
    ps = PhaseShiftSet(periods_px=[8.0, 5.5], steps=3, offset=0.4, amplitude=0.3)
    imgs = ps.images(SIZE)
    assert imgs.shape == (6, 24, 40) and imgs.dtype == np.float32
    u = np.arange(40.0)
    for n, d in enumerate(ps.descriptors(SIZE)):
        assert (d.index, d.kind, d.direction) == (n, "phase", "u")
        want = 0.4 + 0.3 * np.cos(2 * np.pi * u / d.period_px - 2 * np.pi * d.shift / d.steps)
        np.testing.assert_allclose(imgs[n], np.broadcast_to(want, (24, 40)), atol=1e-7)
    assert [(d.period_px, d.shift) for d in ps.descriptors(SIZE)] == [
        (8.0, 0), (8.0, 1), (8.0, 2), (5.5, 0), (5.5, 1), (5.5, 2)]


def test_wrapped_phase_of_the_patterns_is_the_projector_coordinate():
    ps = PhaseShiftSet(periods_px=[7.0], steps=4, direction="both")
    imgs = ps.images(SIZE).astype(np.float64)
    pu = wrapped_phase(imgs[:4]).phase
    pv = wrapped_phase(imgs[4:]).phase
    u, v = np.meshgrid(np.arange(40.0), np.arange(24.0))
    np.testing.assert_allclose(np.angle(np.exp(1j * (pu - 2 * np.pi * u / 7))), 0, atol=1e-6)
    np.testing.assert_allclose(np.angle(np.exp(1j * (pv - 2 * np.pi * v / 7))), 0, atol=1e-6)
    assert [x.direction for x in ps.descriptors(SIZE)] == ["u"] * 4 + ["v"] * 4


def test_gray_code_decodes_to_the_stripe_index():
    gc = GrayCodeSet(period_px=8.0, steps=4, direction="both")
    imgs = gc.images(SIZE)
    desc = gc.descriptors(SIZE)
    assert len(imgs) == len(desc)
    for axis, extent in (("u", 40), ("v", 24)):
        sel = [d for d in desc if d.direction == axis]
        assert [d.kind for d in sel[:2]] == ["white", "black"]
        np.testing.assert_array_equal(imgs[sel[0].index], 1.0)
        np.testing.assert_array_equal(imgs[sel[1].index], 0.0)
        planes = np.stack([imgs[d.index] for d in sel if d.kind == "gray"])
        inverse = np.stack([imgs[d.index] for d in sel if d.kind == "gray_inverse"])
        np.testing.assert_array_equal(planes + inverse, 1.0)
        assert len(planes) == gc.n_bits(extent) == int(np.ceil(np.log2(np.ceil(extent / 4.0))))
        index = gray_to_index(gray_bits(planes, inverse=inverse))
        coord = np.meshgrid(np.arange(40.0), np.arange(24.0))[0 if axis == "u" else 1]
        np.testing.assert_array_equal(index, np.floor((coord + 0.5) / 4.0))
        phase = [d for d in sel if d.kind == "phase"]
        assert [d.shift for d in phase] == [0, 1, 2, 3] and phase[0].period_px == 8.0


def test_gray_code_options():
    gc = GrayCodeSet(period_px=16.0, stripe_width_px=5.0, steps=3, inverse=False, references=False)
    desc = gc.descriptors(SIZE)
    assert [d.kind for d in desc] == ["gray"] * gc.n_bits(40) + ["phase"] * 3
    assert gc.n_bits(40) == 3 and desc[0].stripe_width_px == 5.0
    np.testing.assert_array_equal(gc.stripe_index(np.array([-0.5, 4.49, 4.5, 39.0])), [0, 0, 1, 7])


@pytest.mark.parametrize("kw, match", [
    ({"periods_px": [8.0, 0.0]}, "periods_px must all be > 0"),
    ({"periods_px": [8.0], "offset": 0.7, "amplitude": 0.5}, r"must keep A \+- B in \[0, 1\]"),
])
def test_phase_shift_rejects_bad_definitions(kw, match):
    with pytest.raises(ValueError, match=match):
        PhaseShiftSet(**kw)


def test_images_reject_bad_projector_size():
    with pytest.raises(ValueError, match=r"projector_size must be \(width, height\) >= 1 pixel"):
        PhaseShiftSet(periods_px=[8.0]).images((0, 10))
