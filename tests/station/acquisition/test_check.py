"""`ltc check`: the whole fake bench end to end, and honest failure reports."""

import json
from pathlib import Path

import pytest

from station.acquisition.config import example_text
from station.cli import main


@pytest.mark.slow
def test_check_fake_json_is_ok_and_writes_contact_sheet(tmp_path, capsys):
    assert main(["check", "--fake", "--json", "--out", str(tmp_path)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["ok"] is True
    names = [s["name"] for s in report["steps"]]
    assert names[:2] == ["open devices", "home stage"]
    assert sum(n.startswith("crosshair") for n in names) == 3
    moves = [s for s in report["steps"] if s["name"].startswith("move to")]
    assert all(abs(s["measured_mm"] - s["target_mm"]) <= 0.001 for s in moves)
    png = Path(report["contact_sheet"])
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_check_reports_a_camera_that_sees_nothing(tmp_path, capsys):
    cfg = tmp_path / "dark.toml"
    cfg.write_text(example_text("fake").replace("[fake.noise]", "[fake.noise]\nwhite_fraction = 0.001"))
    assert main(["check", str(cfg), "--json", "--out", str(tmp_path)]) == 1
    report = json.loads(capsys.readouterr().out)
    assert report["ok"] is False
    bad = [s for s in report["steps"] if not s["ok"]]
    assert bad and all("pattern not seen" in s["warning"] for s in bad)


def test_check_reports_a_missing_stage_port(tmp_path, capsys):
    cfg = tmp_path / "real.toml"
    text = example_text("real").replace('port = "/dev/ttyUSB0"', f'port = "{tmp_path}/nope"')
    cfg.write_text(text)
    assert main(["check", str(cfg), "--out", str(tmp_path)]) == 1
    out = capsys.readouterr().out
    assert "FAILED" in out and "open devices" in out and "nope" in out


def test_check_needs_config_or_fake(capsys, tmp_path):
    assert main(["check"]) == 2
    assert "either a CONFIG.toml or --fake" in capsys.readouterr().err
    assert main(["check", str(tmp_path / "none.toml")]) == 1
    assert "cannot read config" in capsys.readouterr().err


@pytest.mark.slow
def test_check_runs_again_in_the_same_folder_and_reports_the_white_level(tmp_path, capsys):
    """The exposure-tuning loop: a second run in the same --out needs no --force and keeps the
    first contact sheet; the white level scales with the light the fake camera gets."""
    out = tmp_path / "check"
    assert main(["check", "--fake", "--out", str(out)]) == 0
    first = capsys.readouterr().out
    assert "white level: " in first and "% of full scale" in first
    cfg = tmp_path / "half.toml"
    cfg.write_text(example_text("fake").replace("[fake.noise]",
                                                "[fake.noise]\nwhite_fraction = 0.425"))
    assert main(["check", "--fake", "--json", "--out", str(out)]) == 0
    bright = json.loads(capsys.readouterr().out)
    assert main(["check", str(cfg), "--json", "--out", str(out)]) == 0
    dim = json.loads(capsys.readouterr().out)
    sheets = sorted(out.glob("check-*.png"))
    assert len(sheets) == 3 and all(p.read_bytes()[:4] == b"\x89PNG" for p in sheets)
    black = 16.0 / 4095  # the fake camera's black level, a fraction of 12-bit full scale
    (b_lo, b_hi), (d_lo, d_hi) = bright["white_level"], dim["white_level"]
    assert 0.6 < b_lo <= b_hi < 0.9  # full white at 0.85 of the well, less the vignetting
    for b, d in ((b_lo, d_lo), (b_hi, d_hi)):
        assert abs((d - black) / (b - black) - 0.5) < 0.03
