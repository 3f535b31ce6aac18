"""`ltc check CONFIG` with `[camera] kind = "genicam"` on Aravis's fake GigE Vision camera:
with the fake stage and display (backend "fake"), and with the real drivers (backend "real":
ZaberStage on the fake controller's pty, GlfwDisplay under Xvfb)."""

from __future__ import annotations

import json
import re

from drivers.zaber_protocol import ACCEL_UNIT, SPEED_UNIT
from fakes.zaber import FakeZaberDevice, FakeZaberPty
from gv_fake import expected_pattern, running_fake_camera
from station.acquisition.config import example_text
from station.cli import main

ROI = (0, 0, 64, 48)


def genicam_section(serial: str) -> str:
    # exposure 10 ms: the fake's ramp is unscaled (0..254 in Mono8), so nothing saturates
    return (f'kind = "genicam"\nserial = "{serial}"\nexposure_ms = 10.0\nroi = {list(ROI)}\n'
            'pixel_format = "Mono8"\ntimeout_s = 2.0\n')


def with_camera(text: str, lines: str) -> str:
    head, rest = text.split("[camera]\n", 1)
    return f"{head}[camera]\n{lines}{rest[rest.index(chr(10) + '['):]}"


def check_report(config_text: str, tmp_path, capsys) -> tuple[int, dict]:
    path = tmp_path / "bench.toml"
    path.write_text(config_text)
    code = main(["check", str(path), "--json", "--out", str(tmp_path / "check")])
    return code, json.loads(capsys.readouterr().out)


def assert_camera_steps(report: dict) -> None:
    opened = report["steps"][0]
    assert opened["name"] == "open devices" and opened["ok"]
    assert opened["camera_size"] == [64, 48] and opened["camera_bit_depth"] == 8
    shots = [s for s in report["steps"] if re.match(r"(crosshair|checkerboard) at", s["name"])]
    assert len(shots) == 6 and all(s["ok"] and "warning" not in s for s in shots)
    # one software trigger per shown pattern: the device's frame ids follow one another
    ids = [s["frame_id"] for s in shots]
    assert ids == list(range(ids[0], ids[0] + 6))
    # each capture is the fake's diagonal ramp for its own frame id
    for s in shots:
        ramp = expected_pattern(s["frame_id"], *ROI[2:])
        assert (s["min"], s["max"], s["mean"]) == \
            (ramp.min(), ramp.max(), round(float(ramp.mean()), 2))
        assert s["saturated_fraction"] == 0


def test_check_with_the_fake_gige_camera_on_the_fake_bench_is_ok(tmp_path, capsys):
    with running_fake_camera("CHECK1") as fake:
        text = with_camera(example_text("fake"), genicam_section(fake.serial))
        code, report = check_report(text, tmp_path, capsys)
    assert code == 0 and report["ok"] is True and report["backend"] == "fake"
    assert_camera_steps(report)
    assert [p.read_bytes()[:4] for p in (tmp_path / "check").glob("check-*.png")] == [b"\x89PNG"]


def test_check_with_real_drivers_and_the_fake_gige_camera_is_ok(tmp_path, capsys, xvfb_display):
    um = 0.1
    device = FakeZaberDevice(limit_max=round(360_000 / um), position=0,
                             maxspeed=round(200.0 * 1000 / um * SPEED_UNIT),
                             accel=round(2000.0 * 1000 / um * ACCEL_UNIT))
    with FakeZaberPty(device) as pty, running_fake_camera("CHECK2") as fake:
        text = example_text("real").replace('port = "/dev/ttyUSB0"', f'port = "{pty.port}"')
        text = text.replace("microstep_um = 0.047625", f"microstep_um = {um}")
        text = text.replace("settle_s = 0.5", "settle_s = 0.0").replace("monitor = 1", "monitor = 0")
        text = with_camera(text, genicam_section(fake.serial))
        code, report = check_report(text, tmp_path, capsys)
    assert code == 0 and report["ok"] is True and report["backend"] == "real", report["steps"]
    assert_camera_steps(report)
    moves = [s for s in report["steps"] if s["name"].startswith("move to")]
    assert [s["target_mm"] for s in moves] == [100.0, 220.0, 300.0]
    assert all(abs(s["measured_mm"] - s["target_mm"]) <= 0.002 for s in moves)


def test_check_names_a_genicam_camera_that_is_not_there(tmp_path, capsys):
    text = with_camera(example_text("fake"), 'kind = "genicam"\ndevice_id = "Nobody-None-0"\n')
    code, report = check_report(text, tmp_path, capsys)
    assert code == 1 and report["ok"] is False
    opened = report["steps"][0]
    assert not opened["ok"] and "camera 'Nobody-None-0': cannot open" in opened["error"]
