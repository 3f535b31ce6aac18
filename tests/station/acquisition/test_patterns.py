"""station.acquisition.patterns: Fourier and localisation pattern sets against their formulas, counts,
8-bit rounding through the inverse response LUT, JSON round trip."""

import json

import numpy as np
import pytest
from pydantic import ValidationError

from sim.fpp.phase import gray_to_index
from station.acquisition.patterns import (
    FourierPatternSet,
    LocalisationPatternSet,
    StationPatternPlan,
    apply_lut,
    half_plane_frequencies,
    shown_luminance,
)

LCD = (40, 28)


def test_pattern_counts_for_p24():
    assert FourierPatternSet(period=24, steps=4).count == 1152
    assert FourierPatternSet(period=24, steps=3).count == 866
    plan = StationPatternPlan.for_lcd((3840, 2160), 24, 4)
    assert len(plan) == 1152 + plan.localisation.count == len(plan.descriptors)


@pytest.mark.parametrize("p", [4, 5, 12, 16, 24])
def test_half_plane_holds_each_conjugate_pair_once(p):
    reg, sc = half_plane_frequencies(p)
    assert len(sc) == (4 if p % 2 == 0 else 1)
    assert 2 * len(reg) + len(sc) == p * p
    keys = {tuple(kl) for kl in reg} | {tuple(kl) for kl in sc}
    conj = {((-k) % p, (-l) % p) for k, l in reg}
    assert not conj & {tuple(kl) for kl in reg}  # no pair twice
    assert keys | conj == {(k, l) for k in range(p) for l in range(p)}
    for k, l in sc:
        assert ((-k) % p, (-l) % p) == (k, l)


@pytest.mark.parametrize("p, n", [(12, 4), (12, 3), (16, 3), (5, 3)])
def test_fourier_images_follow_the_formula_rounded(p, n):
    plan = StationPatternPlan.for_lcd(LCD, p, n)
    x, y = np.arange(LCD[0])[None, :], np.arange(LCD[1])[:, None]
    for d in plan.descriptors:
        if d.kind != "fourier":
            continue
        want = 0.5 + 0.5 * np.cos(2 * np.pi * (d.k * x + d.l * y) / p + d.phase_rad)
        img = plan.image(d.index, LCD)
        assert img.dtype == np.uint8 and img.shape == (LCD[1], LCD[0])
        # rounded, not truncated: never more than half a level away
        assert np.abs(img - 255 * want).max() <= 0.5 + 1e-9


def test_self_conjugate_terms_take_two_patterns_at_phases_0_and_pi():
    plan = StationPatternPlan.for_lcd(LCD, 8, 4)
    sc = plan.indices["self_conjugate"]
    assert sc.shape == (4, 2)
    got = {(plan.descriptors[i].k, plan.descriptors[i].l) for i in sc.ravel()}
    assert got == {(0, 0), (4, 0), (0, 4), (4, 4)}
    assert [plan.descriptors[i].phase_rad for i in sc[0]] == [0.0, np.pi]
    white, black = plan.image(sc[0, 0], LCD), plan.image(sc[0, 1], LCD)
    assert (white == 255).all() and (black == 0).all()
    nyq = plan.image(sc[1, 0], LCD).astype(int)  # (4, 0): alternating along x
    assert (nyq[:, 0::2] == 255).all() and (nyq[:, 1::2] == 0).all()


def test_rounding_is_to_nearest_not_truncation():
    v = np.array([0.0, 0.4 / 255, 0.6 / 255, 127.5 / 255, 254.6 / 255, 1.0])
    np.testing.assert_array_equal(apply_lut(v), [0, 0, 1, 128, 255, 255])
    # a LUT whose interpolated drive is 10.6 gives 11
    lut = np.linspace(0.0, 21.2, 3)  # luminance 0.5 -> 10.6
    assert apply_lut(np.array([0.5]), lut)[0] == 11


def test_lut_is_interpolated_and_applied_before_rounding():
    lut = 255.0 * np.linspace(0, 1, 4096) ** (1 / 2.2)
    v = np.linspace(0, 1, 1001)
    np.testing.assert_array_equal(apply_lut(v, lut), np.rint(255 * v ** (1 / 2.2)))
    lut256 = np.arange(256)[::-1].copy()
    with pytest.raises(ValueError, match="non-decreasing"):
        apply_lut(v, lut256)


@pytest.mark.parametrize(
    "lut, match",
    [(np.zeros((2, 2)), "1-D table"), (np.array([5.0]), "1-D table"),
     (np.array([0.0, 300.0]), r"\[0, 255\]"), (np.array([0.0, np.nan]), r"\[0, 255\]")],
)
def test_bad_lut_is_refused(lut, match):
    with pytest.raises(ValueError, match=match):
        apply_lut(np.array([0.5]), lut)


def test_shown_luminance_inverts_the_lut():
    lut = 255.0 * np.linspace(0, 1, 256) ** (1 / 2.2)
    g = np.arange(256)
    np.testing.assert_allclose(apply_lut(shown_luminance(g, lut), lut), g)
    np.testing.assert_allclose(shown_luminance(g), g / 255)


def test_image_with_lut_matches_lut_of_values():
    plan = StationPatternPlan.for_lcd(LCD, 8, 3)
    lut = 255.0 * np.linspace(0, 1, 256) ** (1 / 2.2)
    i = int(plan.indices["regular"][3, 1])
    tile = plan.values(i, LCD)
    img = plan.image(i, LCD, lut)
    np.testing.assert_array_equal(img[:8, :8], apply_lut(tile, lut))
    np.testing.assert_array_equal(img, np.tile(img[:8, :8], (4, 5))[: LCD[1], : LCD[0]])


def test_gray_code_numbers_half_period_stripes_along_both_axes():
    plan = StationPatternPlan.for_lcd(LCD, 8, 4)  # localisation period 16: stripes of 8
    idx = plan.indices
    for axis, size, n in (("x", LCD[0], 0), ("y", LCD[1], 1)):
        bits = np.stack([plan.image(i, LCD) for i in idx[f"gray_{axis}"]]) > 127
        line = bits[:, 0, :] if axis == "x" else bits[:, :, 0]
        np.testing.assert_array_equal(gray_to_index(line), np.arange(size) // 8)
        # stripes change by exactly one bit between neighbours
        assert (np.diff(line.astype(int), axis=1) != 0).sum(axis=0).max() == 1
        img = plan.image(idx[f"gray_{axis}"][0], LCD)
        assert (np.diff(img.astype(int), axis=n) == 0).all()  # constant along the other axis


def test_phase_patterns_shift_along_their_axis():
    plan = StationPatternPlan.for_lcd(LCD, 8, 4)
    for i, step in zip(plan.indices["phase_y"], range(4), strict=True):
        img = plan.image(i, LCD).astype(float)
        y = np.arange(LCD[1])
        want = 255 * (0.5 + 0.5 * np.cos(2 * np.pi * y / 16 - 2 * np.pi * step / 4))
        assert np.abs(img[:, 7] - want).max() <= 0.5 + 1e-9
        assert (img == img[:, :1]).all()


def test_indices_agree_with_descriptors():
    plan = StationPatternPlan.for_lcd(LCD, 6, 3)
    idx = plan.indices
    kinds = [d.kind for d in plan.descriptors]
    assert kinds[0] == "white" and kinds[1] == "black"
    for name in ("gray_x", "gray_y", "phase_x", "phase_y"):
        kind, axis = name.split("_")
        direction = {"x": "u", "y": "v"}[axis]
        assert all(plan.descriptors[i].kind == kind and plan.descriptors[i].direction == direction
                   for i in idx[name])
    reg, _ = plan.fourier.frequencies
    for (k, l), row in zip(reg, idx["regular"], strict=True):
        ds = [plan.descriptors[i] for i in row]
        assert [(d.k, d.l, d.shift, d.steps) for d in ds] == [(k, l, m, 3) for m in range(3)]
    n_used = sum(v.size for v in idx.values())
    assert n_used == len(plan)


def test_plan_round_trips_through_json():
    plan = StationPatternPlan.for_lcd((3840, 2160), 24, 3, amplitude=0.4,
                                      localisation_period=64)
    text = json.dumps(plan.model_dump(mode="json"))
    back = StationPatternPlan.model_validate(json.loads(text))
    assert back == plan and back.descriptors == plan.descriptors
    assert back.localisation.covers((3840, 2160))
    assert plan.localisation.bits_x == 7 and plan.localisation.bits_y == 7  # 120 and 68 stripes


def test_full_size_lcd_pattern_is_cheap_and_exact():
    plan = StationPatternPlan.for_lcd((3840, 2160), 24, 4)
    i = int(plan.indices["regular"][100, 2])
    d = plan.descriptors[i]
    img = plan.image(i, (3840, 2160))
    assert img.shape == (2160, 3840) and img.flags.c_contiguous
    r, c = 2000, 3777
    want = 0.5 + 0.5 * np.cos(2 * np.pi * (d.k * c + d.l * r) / 24 + d.phase_rad)
    assert abs(int(img[r, c]) - 255 * want) <= 0.5


def test_bad_definitions_name_the_field():
    with pytest.raises(ValidationError, match="period"):
        FourierPatternSet(period=3)
    with pytest.raises(ValidationError, match="steps"):
        FourierPatternSet(steps=2)
    with pytest.raises(ValidationError,
                       match=r"offset A=0.7 and amplitude B=0.5 must keep A \+- B in \[0, 1\]"):
        FourierPatternSet(offset=0.7, amplitude=0.5)
    with pytest.raises(ValidationError, match="localisation period must be even"):
        LocalisationPatternSet(period=15)
    with pytest.raises(ValidationError, match="extra"):
        StationPatternPlan.model_validate({"fourier": {"period": 8, "colour": 1}})


def test_bad_requests_are_refused():
    plan = StationPatternPlan.for_lcd(LCD, 8, 4)
    with pytest.raises(IndexError, match="out of range"):
        plan.image(len(plan), LCD)
    with pytest.raises(ValueError, match="larger than the localisation Gray code covers"):
        plan.image(0, (400, 28))
    with pytest.raises(ValueError, match="lcd_size must be positive"):
        plan.image(0, (0, 28))
