"""Every device exchange is logged at DEBUG on the driver module's logger: the Zaber stage's
commands and replies (as the fake controller answered them), each frame shown, each capture."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest

from drivers.camera import OpenCVCamera
from drivers.display import OffscreenDisplay
from drivers.stage import ZaberStage
from fakes.zaber import FakeZaberDevice, FakeZaberPty

STAGE = dict(microstep_um=0.1, travel_mm=(0.0, 40.0), tolerance_um=0.1, timeout_s=0.2,
             settle_s=0.0, poll_s=0.005, margin_s=0.3, no_progress_s=0.15)


@pytest.fixture
def device() -> FakeZaberDevice:
    return FakeZaberDevice(limit_max=500_000, position=100_000, maxspeed=327_680, accel=16_384)


def test_a_zaber_move_logs_every_command_and_its_reply_at_debug(device, caplog):
    with caplog.at_level(logging.DEBUG, logger="drivers"), FakeZaberPty(device) as server, \
            ZaberStage(server.port, **STAGE) as stage:
        stage.home()
        caplog.clear()
        z = stage.move_to(12.5)
    records = [r for r in caplog.records if r.name in ("drivers.zaber_link", "drivers.stage")]
    assert records and all(r.levelno == logging.DEBUG for r in records)
    sent = [r.getMessage() for r in records if ": sent " in r.getMessage()]
    got = [r.getMessage() for r in records if ": got " in r.getMessage()]
    # the move command, in the device's units (0.1 um microsteps), with its reply
    move = [m for m in sent if " move abs 125000" in m]
    assert len(move) == 1 and move[0].startswith(f"{stage.port_name}: sent '/1 1 ")
    move_id = move[0].split("'")[1].split()[2]  # "/1 1 ID move abs 125000:CC"
    assert any(f"'@01 1 {move_id} OK " in m for m in got), got
    # every command had its reply logged, and the final position the driver returned was read
    assert len(got) >= len(sent) >= 3
    done = f"{stage.port_name}: move to 12.5 mm: done at 12.5 mm"
    assert done in [r.getMessage() for r in records]
    assert z == pytest.approx(12.5, abs=1e-4)
    assert any(f"{round(z * 1e4)}" in m for m in got)


def test_driver_loggers_are_silent_above_debug(device, caplog):
    with caplog.at_level(logging.INFO, logger="drivers"), FakeZaberPty(device) as server, \
            ZaberStage(server.port, **STAGE) as stage:
        stage.home()
        stage.move_to(1.0)
    assert not [r for r in caplog.records if r.name.startswith("drivers.")]


def test_each_frame_shown_is_logged_with_its_swap_time(xvfb_display, caplog):
    with caplog.at_level(logging.DEBUG, logger="drivers"), OffscreenDisplay((64, 48)) as display:
        shown = [display.show(np.full((48, 64), level, np.uint8)) for level in (0, 128, 255)]
    lines = [r.getMessage() for r in caplog.records if r.name == "drivers.display"]
    assert lines == [f"OffscreenDisplay: frame {s.index} shown (swap at {s.swap_time:.6f} s, "
                     "frame code None)" for s in shown]


def test_each_capture_is_logged_with_its_frame_number(tmp_path, caplog):
    for i in range(3):
        assert cv2.imwrite(str(tmp_path / f"img_{i:03d}.png"), np.full((12, 16), i, np.uint8))
    with caplog.at_level(logging.DEBUG, logger="drivers"), OpenCVCamera(
            str(tmp_path / "img_%03d.png"), backend=cv2.CAP_IMAGES) as camera:
        frames = [camera.capture() for _ in range(3)]
    lines = [r.getMessage() for r in caplog.records if r.name == "drivers.camera"]
    assert [f.frame_id for f in frames] == [0, 1, 2]
    assert [m.split(": ", 1)[1] for m in lines] == [
        f"frame {i} captured (16 x 12 uint8)" for i in range(3)]
