"""One clear line for what a user gets wrong or what is damaged: a bad option value is exit 2,
a file is named by its own name, and nothing is dropped silently."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.support.cli import call

ROOT = Path(__file__).resolve().parents[3]




@pytest.mark.parametrize("value", ["2", "-0.1", "1"])
def test_a_modulation_fraction_out_of_range_is_bad_usage(value, tmp_path, capsys):
    code, _, err = call(["scan", str(tmp_path), "--rig", "r.yaml", "--out", str(tmp_path / "c.ply"),
                         "--min-modulation-fraction", value], capsys)
    assert code == 2 and f"must be a fraction in [0, 1), got {value}" in err, err
    assert "pydantic" not in err and "validation error" not in err


def test_one_8_bit_png_among_16_bit_ones_is_named(tmp_path, capsys):
    for cam in ("camera_0", "camera_1"):
        (tmp_path / cam).mkdir()
        for i in range(4):
            im = np.full((12, 16), 1000 + 10 * i, np.uint16)
            cv2.imwrite(str(tmp_path / cam / f"pattern_{i:03d}.png"), im)
    odd = tmp_path / "camera_1" / "pattern_002.png"
    cv2.imwrite(str(odd), np.full((12, 16), 100, np.uint8))
    code, _, err = call(["scan", str(tmp_path), "--rig", str(ROOT / "examples" / "sphere_rig.yaml"),
                         "--out", str(tmp_path / "c.ply")], capsys)
    assert code == 1 and err == (f"ltc scan: error: {odd}: image holds 8-bit integers, "
                                 "pattern_000.png 16-bit integers: all images of a camera must "
                                 "have one bit depth\n"), err


def test_a_text_file_given_as_a_lens_is_not_called_pickled(tmp_path, capsys):
    from sim.optics.measured_lens import LensFileError, load_lens

    notes = tmp_path / "lens.npz"
    notes.write_text("focus 250 mm, f/2.4\n")
    with pytest.raises(LensFileError) as info:
        load_lens(notes)
    assert str(info.value) == (f"{notes}: not a readable measured-lens file: not a .npz "
                               "archive as `ltc lens` writes it")
    assert "pickle" not in str(info.value)


def test_a_damaged_position_row_is_reported_by_its_own_name(tmp_path):
    from station.errors import StationError
    from station.experiment.run import load_position

    (tmp_path / "S2.json").write_text('{"name": "S2", "models": ')  # cut short
    np.savez(tmp_path / "S2.npz", x=np.zeros(3))
    with pytest.raises(StationError) as info:
        load_position(tmp_path, "S2")
    message = str(info.value)
    assert message.startswith(f"{tmp_path / 'S2.json'}: unreadable (") and "S2.npz: " not in message


def test_measure_says_how_many_non_finite_points_it_dropped(tmp_path, capsys):
    rng = np.random.default_rng(0)
    v = rng.normal(size=(2000, 3))
    pts = 25.0 * v / np.linalg.norm(v, axis=1, keepdims=True) + [1.0, 2.0, 300.0]
    pts[[5, 50, 500]] = [[np.nan, 0, 0], [0, np.inf, 0], [0, 0, -np.inf]]
    ply = tmp_path / "c.ply"
    ply.write_text("ply\nformat ascii 1.0\nelement vertex 2000\nproperty float x\nproperty float "
                   "y\nproperty float z\nend_header\n"
                   + "".join(f"{x} {y} {z}\n" for x, y, z in pts))
    code, out, err = call(["measure", str(ply), "--sphere", "--json"], capsys)
    report = json.loads(out)
    assert code == 0 and report["non_finite_dropped"] == 3, err
    assert abs(report["diameter_mm"] - 50.0) < 1e-3 and report["points"] == 1997
    code, out, _ = call(["measure", str(ply), "--sphere"], capsys)
    assert out.splitlines()[-1] == f"(dropped 3 points of {ply} with non-finite coordinates)"
