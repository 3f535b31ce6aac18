"""sim.render.pattern_stack: every pattern in its cheapest exact form, and back bit for bit."""

import numpy as np
import pytest

from sim.render.fringe_patterns import GrayCodeSet, PhaseShiftSet
from sim.render.pattern_stack import ALONG_U, ALONG_V, FULL, PatternStack

SIZE = (37, 21)  # projector (width, height)


def test_fringe_and_gray_code_sets_become_profiles_and_come_back_bit_for_bit():
    sets = [PhaseShiftSet(periods_px=[5.0, 37.0], steps=4, direction="both"),
            GrayCodeSet(period_px=8.0, direction="both")]
    for ps in sets:
        imgs = ps.images(SIZE)
        stack = PatternStack.from_images(imgs)
        want = [ALONG_U if d.direction == "u" else ALONG_V for d in ps.descriptors(SIZE)]
        # white and black references are constant: kept as rows whatever their direction
        want = [ALONG_U if d.kind in ("white", "black") else f
                for d, f in zip(ps.descriptors(SIZE), want, strict=True)]
        assert list(stack.form) == want
        assert stack.full.shape == (0, 21, 37)
        assert stack.rows.shape[1:] == (37,) and stack.cols.shape[1:] == (21,)
        back = stack.images()
        assert back.dtype == np.float32 and back.shape == imgs.shape
        assert np.array_equal(back, imgs)
        assert len(stack) == len(imgs) and stack.size == SIZE


def test_any_difference_keeps_the_full_image():
    rng = np.random.default_rng(1)
    base = np.broadcast_to(rng.random((1, 1, 37)), (4, 21, 37)).astype(np.float32)
    base[1, 20, 36] += 1e-6  # last pixel of a row pattern differs
    base[2, 0, 0] = np.nan  # NaN equals nothing
    base[3] = rng.random((21, 37))
    stack = PatternStack.from_images(base)
    assert list(stack.form) == [ALONG_U, FULL, FULL, FULL]
    assert list(stack.slot) == [0, 0, 1, 2]
    assert np.array_equal(stack.images(), base, equal_nan=True)
    assert all(np.isnan(stack.value_range()))


def test_single_row_or_column_projectors_and_empty_stacks():
    row = np.arange(6, dtype=np.float32).reshape(1, 1, 6) / 6
    col = np.arange(5, dtype=np.float32).reshape(1, 5, 1) / 5
    assert list(PatternStack.from_images(row).form) == [ALONG_U]
    assert list(PatternStack.from_images(col).form) == [ALONG_V]  # one column, rows differ
    assert np.array_equal(PatternStack.from_images(col).images(), col)
    empty = PatternStack.from_images(np.zeros((0, 4, 3), np.float32))
    assert len(empty) == 0 and empty.size == (3, 4) and empty.images().shape == (0, 4, 3)
    assert empty.value_range() == (0.0, 0.0)
    with pytest.raises(ValueError, match=r"pattern images must be \(n, H, W\), got shape \(4, 3\)"):
        PatternStack.from_images(np.zeros((4, 3)))


def test_map_applies_to_each_form_as_a_2d_image():
    imgs = PhaseShiftSet(periods_px=[9.0], steps=3, direction="both").images(SIZE)
    imgs = np.concatenate([imgs, np.full((1, 21, 37), 0.25, np.float32)])
    imgs[-1, 3, 4] = 0.75  # one 2-D pattern
    stack = PatternStack.from_images(imgs)
    shapes = []

    def square(p):
        shapes.append(p.shape)
        return p**2

    got = stack.map(square)
    assert sorted(set(shapes)) == [(1, 37), (21, 1), (21, 37)]
    assert np.array_equal(got.images(), imgs**2)
    assert got.value_range() == (float((imgs**2).min()), float((imgs**2).max()))
