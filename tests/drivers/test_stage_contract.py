"""One contract for every Stage implementation (drivers.interfaces.Stage), from docs/hardware.md's
driver rules: homing, moves that end within tolerance at the measured position, software limits
checked before anything moves, a position valid while moving, stop from another thread, a move
deadline that stops the axis, typed errors, and an idempotent close.

Implementations: ZaberStage on the fake Zaber controller served on a real pseudo-terminal, and
ZaberStage on the same fake through its in-process pyserial URL handler. Each case gives the
fake's carriage position (the physical truth) so the contract checks what really moved.
"""

from __future__ import annotations

import itertools
import json
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import pytest

from drivers.interfaces import DeviceError, Stage
from drivers.stage import ZaberStage
from drivers.stage_errors import StageError, StageLimitError, StageNotHomed, StageStopped, StageTimeout
from drivers.zaber_protocol import ACCEL_UNIT, SPEED_UNIT
from fakes.zaber import FakeZaberDevice, FakeZaberPty, register_url_handler, remove_url_device, url_device

UM = 0.1  # microstep, um
TRAVEL_MM = (0.0, 40.0)
TOLERANCE_MM = 0.0002  # 2 microsteps
START_MM = 10.0  # where the carriage is at power-up
TIMEOUT_S = 0.5  # one command's reply deadline (generous: the test machine is shared)
DEVICE = dict(limit_max=500_000, position=round(START_MM * 1000 / UM),
              maxspeed=round(50.0 * 1000 / UM * SPEED_UNIT),  # 50 mm/s, 2000 mm/s^2:
              accel=round(2000.0 * 1000 / UM * ACCEL_UNIT))  # 30 mm take about 0.6 s
SETTINGS = dict(microstep_um=UM, travel_mm=TRAVEL_MM, tolerance_um=TOLERANCE_MM * 1000,
                timeout_s=TIMEOUT_S, settle_s=0.0, poll_s=0.005, margin_s=0.3, no_progress_s=0.5)
_names = itertools.count(1)


@dataclass
class Case:
    """A stage under test and the physical truth behind it."""

    stage: Stage
    carriage_mm: Callable[[], float]  # where the carriage really is
    moving: Callable[[], bool]  # whether the carriage is really moving


def _case(stage: Stage, device: FakeZaberDevice) -> Case:
    return Case(stage, lambda: device.position * UM / 1000.0, lambda: device.busy)


@pytest.fixture
def zaber_pty() -> Iterator[Case]:
    device = FakeZaberDevice(**DEVICE)
    with FakeZaberPty(device) as server, ZaberStage(server.port, **SETTINGS) as stage:
        yield _case(stage, device)


@pytest.fixture
def zaber_url() -> Iterator[Case]:
    register_url_handler()
    name = f"contract-{next(_names)}"
    device = url_device(name, **DEVICE)
    try:
        with ZaberStage(f"fakezaber://{name}", **SETTINGS) as stage:
            yield _case(stage, device)
    finally:
        remove_url_device(name)


ALL = ["zaber_pty", "zaber_url"]


@pytest.fixture(params=ALL)
def case(request) -> Case:
    return request.getfixturevalue(request.param)


@pytest.fixture
def homed(case: Case) -> Case:
    case.stage.home()
    return case


def in_thread(fn: Callable[[], object]) -> tuple[threading.Thread, dict]:
    """Run ``fn`` in a thread; the dict gets 'result' or 'error', and 'ended' (monotonic)."""
    out: dict = {}

    def run() -> None:
        try:
            out["result"] = fn()
        except DeviceError as exc:
            out["error"] = exc
        out["ended"] = time.monotonic()

    thread = threading.Thread(target=run)
    thread.start()
    return thread, out


def wait_until_moving(case: Case, start_mm: float) -> None:
    deadline = time.monotonic() + 2.0
    while abs(case.carriage_mm() - start_mm) < 0.1:
        assert time.monotonic() < deadline, "the move never started"
        time.sleep(0.002)


def test_describe_and_limits(case: Case):
    stage = case.stage
    assert isinstance(stage, Stage)
    info = stage.describe()
    assert info["type"] == type(stage).__name__
    json.dumps(info)  # recordable in run metadata
    lo, hi = stage.limits_mm
    assert TRAVEL_MM[0] <= lo < hi <= TRAVEL_MM[1]  # never wider than the configured travel
    assert stage.position_mm == pytest.approx(case.carriage_mm(), abs=TOLERANCE_MM)


def test_moving_before_homing_is_refused_and_nothing_moves(case: Case):
    assert not case.stage.is_homed
    with pytest.raises(StageNotHomed):
        case.stage.move_to(20.0)
    assert case.carriage_mm() == pytest.approx(START_MM, abs=TOLERANCE_MM)


def test_home_then_moves_end_within_tolerance_where_measured(case: Case):
    case.stage.home()
    assert case.stage.is_homed and not case.moving()
    assert case.stage.position_mm == pytest.approx(case.carriage_mm(), abs=TOLERANCE_MM)
    for z in (12.5, 3.1234, 0.0):
        measured = case.stage.move_to(z)
        assert measured == pytest.approx(z, abs=TOLERANCE_MM)
        assert case.carriage_mm() == pytest.approx(z, abs=TOLERANCE_MM) and not case.moving()
        assert case.stage.position_mm == pytest.approx(measured, abs=TOLERANCE_MM)


def test_zero_length_move_completes_at_once(homed: Case):
    homed.stage.move_to(7.0)
    started = time.monotonic()
    assert homed.stage.move_to(7.0) == pytest.approx(7.0, abs=TOLERANCE_MM)
    assert time.monotonic() - started < 0.1


@pytest.mark.parametrize("z", [-0.001, 40.001, 1e6, math.nan, math.inf])
def test_targets_outside_the_limits_are_refused_before_anything_moves(homed: Case, z: float):
    homed.stage.move_to(5.0)
    with pytest.raises(StageLimitError):
        homed.stage.move_to(z)
    time.sleep(0.02)
    assert homed.carriage_mm() == pytest.approx(5.0, abs=TOLERANCE_MM) and not homed.moving()


def test_position_is_valid_while_moving(homed: Case):
    thread, out = in_thread(lambda: homed.stage.move_to(20.0))
    seen = []
    while thread.is_alive():
        seen.append((homed.stage.position_mm, homed.carriage_mm()))
        time.sleep(0.01)
    thread.join()
    assert out["result"] == pytest.approx(20.0, abs=TOLERANCE_MM)
    inside = [p for p, _ in seen if 0.0 < p < 20.0]
    assert len(inside) >= 5 and inside == sorted(inside)
    # each reading lies within what the carriage covers in one poll at 50 mm/s of the truth
    assert all(abs(p - c) < 1.0 for p, c in seen)


def test_stop_from_another_thread_ends_the_move_with_a_typed_error(homed: Case):
    thread, out = in_thread(lambda: homed.stage.move_to(30.0))
    wait_until_moving(homed, 0.0)
    stopped_at = time.monotonic()
    homed.stage.stop()
    thread.join()
    assert isinstance(out["error"], StageStopped)
    assert out["ended"] - stopped_at < 2 * TIMEOUT_S + 0.5
    time.sleep(0.1)  # decelerating from 50 mm/s at 2000 mm/s^2 takes 25 ms
    assert not homed.moving() and 0.0 < homed.carriage_mm() < 30.0
    assert homed.stage.move_to(30.0) == pytest.approx(30.0, abs=TOLERANCE_MM)  # usable again


def test_a_move_past_its_deadline_raises_and_stops_the_axis(homed: Case):
    started = time.monotonic()
    with pytest.raises(StageTimeout):
        homed.stage.move_to(40.0, timeout=0.05)
    assert time.monotonic() - started < 0.05 + 2 * TIMEOUT_S + 0.5
    time.sleep(0.1)
    assert not homed.moving() and homed.carriage_mm() < 40.0 - 1.0  # never continued


def test_close_is_idempotent_and_final(case: Case):
    case.stage.close()
    case.stage.close()
    with pytest.raises(StageError):
        _ = case.stage.position_mm
    with pytest.raises(StageError):
        case.stage.move_to(5.0)


def test_errors_are_device_errors():
    for error in (StageError, StageLimitError, StageNotHomed, StageStopped, StageTimeout):
        assert issubclass(error, DeviceError)
