"""Every device exchange is logged at DEBUG on the driver module's logger: the Zaber stage's
commands and replies, as the fake controller saw and answered them."""

from __future__ import annotations

import logging

import pytest

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
