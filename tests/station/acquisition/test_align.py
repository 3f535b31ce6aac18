"""`ltc align`: the LCD centre's image at each depth and the tilt of the optical axis, against
the fake bench's configured tilt and against exact synthetic geometry."""

import json

import numpy as np
import pytest

from fakes.bench import BenchConfig, FakeBench
from station.acquisition.align import (
    AlignError,
    arm_image,
    cross,
    effective_focal_px,
    fit_arm,
    fit_axis,
    format_align,
    tilt_from_axis,
)
from station.acquisition.config import example_text
from station.cli import main

TILT_DEG = (0.5, -0.3)
OFFSET_MM = (1.0, -0.5)
# Tolerance on the reported tilt, degrees. The stage axis's vanishing point A comes from
# extrapolating p = A + B m over m in [0.57, 0.87]: with the arm centres good to ~0.01 px
# (fit RMS 0.014 px below) that puts ~0.03 px on A, 0.003 deg at f ~ 730 px; the effective
# focal length from d(1/m)/dz is good to ~1 % (0.005 deg of a 0.5 deg tilt); the remaining
# model error (second order in the tilt, and the vignetted pupil's centroid not moving exactly
# linearly with field angle) is below 0.002 deg on the noise-free bench. 0.02 deg covers
# these four times over and is 1/25 of the tilt: a nominal-focal-length estimate, which
# ignores the vignetting's scale change, is off by 0.07 deg and fails.
TILT_TOL_DEG = 0.02


def tilted_text(tilt=TILT_DEG, offset=OFFSET_MM) -> str:
    text = example_text("fake")
    for old, new in {"tilt_deg = [0.0, 0.0]": f"tilt_deg = {list(tilt)}\noffset_mm = {list(offset)}",
                     "timeout_s = 2.0": "timeout_s = 0.05"}.items():
        assert old in text
        text = text.replace(old, new, 1)
    return text


def test_arm_images_are_centred_on_the_lcd_centre():
    img, centre = arm_image((160, 120), "x")
    assert centre == 79.5 and img[:, 79:81].min() == 255 and img.sum() == 255 * 2 * 120
    img, centre = arm_image((161, 121), "y", shift_px=5)
    assert centre == 65.0 and img[64:67].min() == 255 and img.sum() == 255 * 3 * 161
    with pytest.raises(AlignError, match="crosshair shift 80 px puts the arm off the 160x120 LCD"):
        arm_image((160, 120), "x", 80)


def _blurred_line(a: float, b: float, shape=(48, 64), sigma=2.5, axis="x"):
    """A thin line coord = a + b t, blurred, on a dark background with a black level."""
    rows, cols = shape
    t, c = np.mgrid[:rows, :cols] if axis == "x" else np.mgrid[:cols, :rows]
    img = np.exp(-0.5 * ((c - (a + b * t)) / sigma) ** 2) * 1000.0
    return (img if axis == "x" else img.T) + 16.0


def test_fit_arm_and_cross_recover_exact_lines():
    v = _blurred_line(30.3, 0.02)
    h = _blurred_line(22.7, -0.015, axis="y")
    bg = np.full((48, 64), 16.0)
    a, b = fit_arm(v, bg, "x")
    c, d = fit_arm(h, bg, "y")
    # each row's centroid stops where the profile falls below 3 % of its peak: the cut tails
    # cost up to ~0.005 px, far below the arm's noise on a real frame
    assert (a, b) == pytest.approx((30.3, 0.02), abs=5e-3)
    assert (c, d) == pytest.approx((22.7, -0.015), abs=5e-3)
    u, w = cross((a, b), (c, d))
    assert u == pytest.approx(a + b * w, abs=1e-9) and w == pytest.approx(c + d * u, abs=1e-9)
    with pytest.raises(AlignError, match=r"the crosshair arm along x is not seen \(only 0 usable"):
        fit_arm(bg, bg, "x")


def test_fit_axis_and_effective_focal_length_on_a_pinhole():
    f, pitch, c = 700.0, 0.25, np.array([31.5, 23.5])
    t, b = np.array([0.004, -0.006]), np.array([-2.0, 1.5])  # tan tilt; offset, mm
    z = np.array([40.0, 70.0, 130.0, 160.0])
    dist = 150.0 + z
    m = f * pitch / dist
    p = c + f * (t + b / dist[:, None])
    axis, offset, rms = fit_axis(p, m)
    assert axis == pytest.approx(c + f * t, abs=1e-9) and offset * pitch == pytest.approx(b)
    assert rms == pytest.approx(0.0, abs=1e-9)
    assert effective_focal_px(z, m, pitch) == pytest.approx(f)
    assert fit_axis(p[:2], m[:2])[2] is None
    with pytest.raises(AlignError, match="need at least two depths with different magnifications"):
        fit_axis(p[:1], m[:1])
    with pytest.raises(AlignError, match=r"the image does not shrink as the stage moves away"):
        effective_focal_px(z, m[::-1], pitch)


@pytest.mark.parametrize("tilt", [(0.0, 0.0), (0.5, -0.3), (-1.2, 2.0)])
def test_tilt_from_axis_inverts_the_bench_rotation(tilt):
    bench = FakeBench(BenchConfig.small(tilt_deg=tilt))
    direction = bench.R_cam_to_lcd.T @ np.array([0.0, 0.0, 1.0])  # stage axis, camera frame
    f, c = 640.0, np.array([31.5, 23.5])
    vanishing = c + f * direction[:2] / direction[2]
    assert tilt_from_axis(vanishing, c, f) == pytest.approx(tilt, abs=1e-9)


@pytest.mark.slow
def test_ltc_align_reports_the_configured_tilt(tmp_path, capsys):
    cfg = tmp_path / "tilted.toml"
    cfg.write_text(tilted_text())
    assert main(["align", str(cfg), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    tilt = np.array(report["tilt_deg"])
    assert np.abs(tilt - TILT_DEG).max() <= TILT_TOL_DEG
    assert report["fit_rms_px"] < 0.05
    depths = report["depths"]
    assert [q["depth_mm"] for q in depths] == [40.0, 70.0, 130.0, 160.0]
    assert all(q["check_code_in_view"] for q in depths)
    mags = [q["magnification"] for q in depths]
    assert np.all(np.diff(mags) < 0)  # the LCD shrinks as the camera backs off
    # the LCD centre drifts across the image as the stage moves: offset and tilt together
    drift = np.array(depths[-1]["offset_px"]) - np.array(depths[0]["offset_px"])
    assert np.abs(drift).max() > 0.5
    text = format_align(report)
    assert "tilt of the optical axis: +0.4" in text and "check code in view" in text
    with capsys.disabled():
        print(f"\nltc align on a bench tilted {TILT_DEG} deg: reported {tilt.round(4).tolist()} deg "
              f"(error {np.abs(tilt - TILT_DEG).max():.4f}), fit RMS {report['fit_rms_px']} px, "
              f"effective focal length {report['effective_focal_px']} px")


def test_ltc_align_errors(tmp_path, capsys):
    cfg = tmp_path / "fake.toml"
    cfg.write_text(tilted_text())
    with pytest.raises(SystemExit) as usage:  # argparse refuses the value
        main(["align", str(cfg), "--shift", "0"])
    assert usage.value.code == 2
    assert "argument --shift: must be >= 1, got 0" in capsys.readouterr().err
    assert main(["align", str(cfg), "--shift", "70"]) == 1
    assert "crosshair shift 70 px puts the arm off the 160x120 LCD" in capsys.readouterr().err
