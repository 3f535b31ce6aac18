"""The synthetic bench's fast response against a brute-force integral of its own LTC."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import ndtr

from fakes.synthetic import SyntheticBench, SyntheticConfig, describe_image
from station.acquisition.patterns import StationPatternPlan

LCD = (3840, 2160)
PIXELS = [(0, 0), (2047, 1), (4095, 2)]  # (u, row in the crop): corner, centre column, edge


def brute_force(image: np.ndarray, bench: SyntheticBench, z_mm: float, u: int, r: int
                ) -> float:
    """T * sum over LCD pixels of luminance x the elliptical Gaussian integrated over the
    pixel (16 x 16 sub-cells; the Gaussian restricted to one axis is integrated exactly)."""
    f = bench.field(z_mm)
    mx, my = (f["mu_int"][:, r, u] + f["mu_frac"][:, r, u]).astype(np.float64)
    sxx, syy, sxy = (float(f[k][r, u]) for k in ("sxx", "syy", "sxy"))
    half = int(np.ceil(7 * np.sqrt(max(sxx, syy))))
    xs = np.arange(int(mx) - half, int(mx) + half + 1)
    ys = np.arange(int(my) - half, int(my) + half + 1)
    n = 16
    sub = (np.arange(n) + 0.5) / n - 0.5
    # y sampled at sub-cells; x given y is normal: mean mx + sxy/syy (y - my), var sxx - sxy^2/syy
    yy = (ys[:, None] + sub[None, :]).ravel()
    py = np.exp(-0.5 * (yy - my) ** 2 / syy) / np.sqrt(2 * np.pi * syy) / n
    cm = mx + sxy / syy * (yy - my)
    cs = np.sqrt(sxx - sxy**2 / syy)
    edges = np.append(xs - 0.5, xs[-1] + 0.5)
    px = np.diff(ndtr((edges[None, :] - cm[:, None]) / cs), axis=1)
    w = (py[:, None] * px).reshape(len(ys), n, len(xs)).sum(axis=1)
    lum = image[np.ix_(ys % image.shape[0], xs % image.shape[1])] / 255.0
    return float(f["t"][r, u]) * float((w * lum).sum())


def test_response_matches_a_brute_force_integral_of_the_ltc() -> None:
    bench = SyntheticBench(SyntheticConfig(), rows=(1082, 1085))
    plan = StationPatternPlan.for_lcd(LCD, 24, 4)
    # every localisation pattern (Gray code and phase-shift stripes), the four phase steps of
    # two low frequencies (k, l) (the high ones are blurred flat), and one more
    picks = list(range(25)) + [73, 74, 75, 76, 169, 170, 171, 172, 300, 600, 901, 1100]
    for z_mm in (60.0, 260.0):
        for i in picks:
            img = plan.image(i, LCD)
            kind, data = describe_image(img, 24)
            got = bench.response(kind, data, z_mm)
            for u, r in PIXELS:
                want = brute_force(img, bench, z_mm, u, r)
                assert abs(got[r, u] - want) < 1e-3, (z_mm, i, u, r, got[r, u], want)


def test_phase_steps_from_the_kept_transfer_equal_a_fresh_bench() -> None:
    plan = StationPatternPlan.for_lcd(LCD, 24, 4)
    warm = SyntheticBench(SyntheticConfig(), rows=(0, 4))
    for i in (29, 30, 31):
        kind, data = describe_image(plan.image(i, LCD), 24)
        a = warm.response(kind, data, 140.0)
    b = SyntheticBench(SyntheticConfig(), rows=(0, 4)).response(kind, data, 140.0)
    np.testing.assert_array_equal(a, b)


def test_frames_of_one_scene_have_noise_of_their_own_and_the_first_is_the_scenes() -> None:
    """The first frame of a scene is the scene's alone (a resumed run recaptures it); further
    frames of the unchanged scene (frames averaged per pattern) have noise of their own, with
    the variance of the first about the noise-free response."""
    from fakes.synthetic import SyntheticHardware, SyntheticSettings

    plan = StationPatternPlan.for_lcd(LCD, 24, 4)
    settings = SyntheticSettings(rows=(0, 4))

    def frames(n: int) -> list[np.ndarray]:
        with SyntheticHardware(settings, period=24, travel_mm=(0.0, 300.0)) as hw:
            hw.stage.move_to(140.0)
            hw.lcd.show(plan.image(30, LCD))
            return [hw.camera.capture().image.astype(np.float64) for _ in range(n)]

    many, again = frames(24), frames(1)
    np.testing.assert_array_equal(again[0], many[0])
    diffs = [np.mean(many[k] != many[k + 1]) for k in range(len(many) - 1)]
    assert min(diffs) > 0.5
    stack = np.stack(many)
    # independent frames: the variance of a difference of two is twice that of one
    var_one = stack.var(axis=0, ddof=1).mean()
    var_diff = np.var(stack[1:] - stack[:-1], axis=0, ddof=1).mean()
    assert var_diff == pytest.approx(2 * var_one, rel=0.1)
