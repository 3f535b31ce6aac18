"""`ltc gamma`: the display response measured on the fake panel, and the inverse LUT it writes."""

import json

import numpy as np
import pytest

from station.acquisition.backend import load_lut, open_hardware
from station.acquisition.config import example_text, parse_config
from station.acquisition.gamma import (
    GammaError,
    capture_after,
    fit_inverse_lut,
    grey_levels,
    isotonic,
    measure_lut,
    relative_response,
    save_lut,
)
from station.cli import main

TRUE_INVERSE = 255.0 * (np.arange(256) / 255.0) ** (1 / 2.2)  # float inverse of gamma 2.2


def fake_text(gamma: float = 2.2) -> str:
    text = example_text("fake")
    for old, new in {"gamma = 1.0 ": f"gamma = {gamma} ", "pupil_samples = 200 ": "pupil_samples = 24 ",
                     "subpixels = 2": "subpixels = 1", "timeout_s = 2.0": "timeout_s = 0.05"}.items():
        assert old in text
        text = text.replace(old, new, 1)
    return text


def test_grey_levels_span_the_range():
    levels = grey_levels(65)
    assert len(levels) == 65 and levels[0] == 0 and levels[-1] == 255
    assert np.all(np.diff(levels) > 0) and np.diff(levels).max() <= 4
    with pytest.raises(ValueError, match="levels must be 64..256 grey levels, got 63"):
        grey_levels(63)


def test_isotonic_is_the_least_squares_monotone_fit():
    assert isotonic([1.0, 3.0, 2.0, 4.0]).tolist() == [1.0, 2.5, 2.5, 4.0]
    assert isotonic([3.0, 2.0, 1.0]).tolist() == [2.0, 2.0, 2.0]
    y = np.linspace(0, 1, 9)
    assert isotonic(y).tolist() == y.tolist()


@pytest.mark.parametrize("gamma", [1.0, 1.8, 2.2, 2.6])
def test_inverse_lut_from_exact_samples_is_the_rounded_true_inverse(gamma):
    levels = grey_levels(65)
    lut = fit_inverse_lut(levels, (levels / 255.0) ** gamma)
    true = 255.0 * (np.arange(256) / 255.0) ** (1 / gamma)
    # PCHIP between 4-level samples: within half a level of the float inverse, plus rounding
    assert np.abs(lut - true).max() <= 1.0
    assert np.mean(lut == np.rint(true)) > 0.9 and lut[0] == 0 and lut[255] == 255


def test_relative_response_pools_good_pixels_and_skips_odd_ones():
    rng = np.random.default_rng(0)
    levels = grey_levels(64)
    y = (levels / 255.0) ** 2.2
    gain = rng.uniform(2000, 3000, (20, 30))  # vignetting: every pixel its own gain
    frames = 16 + y[:, None, None] * gain + rng.normal(0, 1.0, (len(levels), 20, 30))
    frames[:, :3, :3] = rng.uniform(16, 3000, (len(levels), 3, 3))  # a code flickering there
    frames[:, 5:8, 0] = 16.0  # dead pixels
    got, pixels = relative_response(frames, levels)
    assert np.abs(got - y).max() < 2e-4
    assert pixels == 20 * 30 - 9 - 3
    with pytest.raises(GammaError, match="levels must include 0 and 255, got 4..255"):
        relative_response(frames[1:], levels[1:])
    with pytest.raises(GammaError, match="the camera sees no difference between black and white"):
        relative_response(np.full_like(frames, 16.0), levels)
    noisy = 16 + rng.uniform(0, 3000, frames.shape)
    with pytest.raises(GammaError, match=r"only \d pixels give a consistent response"):
        relative_response(noisy, levels)


def test_lut_files_round_trip_through_the_config_loader(tmp_path):
    lut = np.rint(TRUE_INVERSE).astype(np.uint8)
    for name in ("lut.npy", "lut.txt"):
        np.testing.assert_array_equal(load_lut(save_lut(tmp_path / name, lut)), lut)


def test_ltc_gamma_on_a_gamma_22_panel_writes_the_inverse_that_linearises_it(tmp_path, capsys):
    cfg = tmp_path / "fake.toml"
    cfg.write_text(fake_text(2.2))
    out = tmp_path / "lut.npy"
    assert main(["gamma", str(cfg), "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    lut = load_lut(out)
    assert summary["gamma_fit"] == pytest.approx(2.2, abs=0.01) and len(summary["levels"]) == 65
    err = np.abs(lut.astype(float) - TRUE_INVERSE)
    assert err.max() <= 1.0  # within one grey level of the true inverse everywhere
    # the display through that LUT: its measured response is linear. The LUT's integer steps
    # limit it: at the top, one drive level moves the output by up to gamma / 255 = 0.0086,
    # so rounding leaves up to 0.0043 (1.1 output levels), plus a little camera noise
    config = parse_config(cfg.read_text())
    with open_hardware(config, lut=lut) as hw:
        levels = grey_levels(86)
        frames = []
        for g in levels:
            shown = hw.display.show(np.full((120, 160), int(g), np.uint8))
            frames.append(capture_after(hw, shown.swap_time, config))
    linear, _ = relative_response(np.stack(frames), levels)
    deviation = np.abs(linear - levels / 255.0)
    assert deviation.max() <= 0.005
    with capsys.disabled():
        print(f"\nltc gamma on a gamma-2.2 panel: LUT max error {err.max():.2f} levels (mean "
              f"{err.mean():.2f}); response through it linear within {deviation.max():.4f} "
              f"({255 * deviation.max():.2f} levels)")


def test_a_linear_panel_gets_the_identity(tmp_path):
    config = parse_config(fake_text(1.0))
    summary = measure_lut(config)
    assert np.abs(np.array(summary["lut"]) - np.arange(256)).max() <= 1


def test_gamma_reports_a_camera_that_gives_no_frames(capsys, tmp_path):
    config = parse_config(fake_text(2.2))
    with open_hardware(config) as hw:
        hw.camera.faults.timeout = 100
        with pytest.raises(GammaError, match=r"no fresh camera frame in 4 attempts: FakeCamera: "
                                             r"no frame within 0.050 s"):
            measure_lut(config, hw=hw)
    cfg = tmp_path / "fake.toml"
    cfg.write_text(fake_text())
    with pytest.raises(SystemExit) as usage:  # argparse refuses the value
        main(["gamma", str(cfg), "--out", str(tmp_path / "lut.npy"), "--levels", "32"])
    assert usage.value.code == 2
    assert "argument --levels: must be >= 64, got 32" in capsys.readouterr().err
