"""ZaberStage against the fake controller over a real pty (and, for reconnects, the URL handler)."""

from __future__ import annotations

import itertools
import re
import threading
import time
from collections.abc import Callable, Iterator

import pytest
import serial

from drivers.interfaces import DeviceError
from drivers.stage import (
    Stage,
    StageBusy,
    StageConnectionLost,
    StageError,
    StageFault,
    StageLimitError,
    StageNotHomed,
    StagePositionUnknown,
    StageProtocolError,
    StageRejected,
    StageStopped,
    StageTimeout,
    ZaberStage,
)
from drivers.zaber_protocol import checksum_ok
from fakes.zaber import FakeZaberDevice, FakeZaberPty, register_url_handler, remove_url_device, url_device

UM = 0.1  # microstep, um: 10 000 microsteps per mm


def speed_settings(mm_s: float, mm_s2: float) -> dict[str, int]:
    """Device maxspeed/accel values for a speed (mm/s) and acceleration (mm/s^2)."""
    return {"maxspeed": round(mm_s * 1e4 * 1.6384), "accel": round(mm_s2 * 1e4 * 1.6384 / 1e4)}


FAST = dict(limit_max=500_000, position=100_000, **speed_settings(200.0, 10_000.0))  # 50 mm travel
SLOW = dict(limit_max=500_000, position=100_000, **speed_settings(50.0, 2_000.0))
TIMEOUT_S = 0.2
STAGE = dict(microstep_um=UM, travel_mm=(0.0, 40.0), tolerance_um=0.1, timeout_s=TIMEOUT_S,
             settle_s=0.0, poll_s=0.005, margin_s=0.3, no_progress_s=0.15)


@pytest.fixture
def device() -> FakeZaberDevice:
    return FakeZaberDevice(**FAST)


@pytest.fixture
def server(device: FakeZaberDevice) -> Iterator[FakeZaberPty]:
    with FakeZaberPty(device) as srv:
        yield srv


@pytest.fixture
def stage(server: FakeZaberPty) -> Iterator[ZaberStage]:
    with ZaberStage(server.port, **STAGE) as st:
        yield st


@pytest.fixture
def homed(stage: ZaberStage) -> ZaberStage:
    stage.home()
    return stage


@pytest.fixture
def url() -> Iterator[str]:
    register_url_handler()
    url_device("stage-test", **FAST)
    yield "fakezaber://stage-test"
    remove_url_device("stage-test")


def in_background(fn: Callable[[], object]) -> tuple[threading.Thread, dict]:
    """Run ``fn`` in a thread; the dict gets 'result' or 'error'."""
    out: dict = {}

    def run() -> None:
        try:
            out["result"] = fn()
        except StageError as exc:
            out["error"] = exc

    thread = threading.Thread(target=run)
    thread.start()
    return thread, out


def count(device: FakeZaberDevice, text: str) -> int:
    return sum(text in line for line in device.received)


# ----- opening, identity, limits ---------------------------------------------------------------
def test_open_reads_identity_and_limits(stage: ZaberStage, device: FakeZaberDevice) -> None:
    assert isinstance(stage, Stage) and issubclass(StageError, DeviceError)
    info = stage.describe()
    assert info["device_id"] == 50081 and info["firmware_version"] == "7.38"
    assert info["axis_count"] == 1 and info["port"] == stage.port_name
    assert info["device_limits_mm"] == (0.0, 50.0)
    assert stage.limits_mm == info["limits_mm"] == (0.0, 40.0)  # tighter of device and config
    assert info["maxspeed_mm_s"] == pytest.approx(200.0, rel=1e-4)
    assert info["accel_mm_s2"] == pytest.approx(10_000.0, rel=1e-3)
    assert info["settle_s"] == 0.0 and info["tolerance_um"] == 0.1
    assert all(checksum_ok(line) for line in device.received)  # every command carried :CC


def test_limits_are_the_intersection_with_the_device_limits(server: FakeZaberPty) -> None:
    server.device.settings.update({"limit.min": 10_000, "limit.max": 300_000})
    with ZaberStage(server.port, **STAGE) as stage:
        assert stage.limits_mm == (1.0, 30.0)
        assert stage.describe()["device_limits_mm"] == (1.0, 30.0)


def test_travel_that_misses_the_device_limits_is_refused(server: FakeZaberPty) -> None:
    with pytest.raises(StageLimitError, match=r"configured travel \(60.0, 70.0\) mm does not overlap "
                       r"the device limits \(0.0, 50.0\) mm .*got 0/500000 microsteps"):
        ZaberStage(server.port, **{**STAGE, "travel_mm": (60.0, 70.0)})


def test_device_that_cannot_move_is_refused(server: FakeZaberPty) -> None:
    server.device.settings["maxspeed"] = 0
    with pytest.raises(StageProtocolError, match=r"got 0 and 16384: the device cannot move"):
        ZaberStage(server.port, **STAGE)


def test_negative_acceleration_is_refused(server: FakeZaberPty) -> None:
    server.device.settings["accel"] = -5
    with pytest.raises(StageProtocolError, match=r"'get accel', got 3276800 and -5: the device cannot move"):
        ZaberStage(server.port, **STAGE)


def test_device_with_accel_zero_homes_and_moves(server: FakeZaberPty) -> None:
    """Zaber's accel 0 is "no ramp": accepted, and the move deadline has no ramp term."""
    server.device.settings.update({"maxspeed": round(200.0 * 1e4 * 1.6384), "accel": 0})
    with ZaberStage(server.port, **STAGE) as stage:
        assert stage.describe()["accel_mm_s2"] == 0.0
        # 40 mm at 200 mm/s: 0.2 s + 0.3 s margin, no 2 * speed/accel
        assert stage.move_deadline_s(40.0) == pytest.approx(0.2 + 0.3, rel=1e-4)
        assert stage.move_deadline_s(-10.0) == pytest.approx(0.05 + 0.3, rel=1e-4)
        stage.home()
        assert stage.is_homed and server.device.position == 0
        for z in (12.5, 40.0, 0.0, 3.1234, 39.9999):
            started = time.monotonic()
            assert stage.move_to(z) == pytest.approx(z, abs=1e-5)
            assert time.monotonic() - started < stage.move_deadline_s(40.0) + 2 * TIMEOUT_S
            assert server.device.position == round(z * 1e4) and not server.device.busy


def test_non_integer_setting_is_a_protocol_error(server: FakeZaberPty) -> None:
    server.device.settings["limit.max"] = "lots"
    with pytest.raises(StageProtocolError, match=r"sent '/1 1 \d\d get limit.max:..', "
                       r"got '@01 1 \d\d OK IDLE WR lots': expected an integer"):
        ZaberStage(server.port, **STAGE)


def test_missing_axis_is_rejected_on_open(server: FakeZaberPty) -> None:
    with pytest.raises(StageRejected, match=r"sent '/1 2 \d\d get limit.min:..', got "
                       r"'@01 2 \d\d RJ IDLE WR BADAXIS': rejected \(BADAXIS\)") as info:
        ZaberStage(server.port, **{**STAGE, "axis": 2})
    assert info.value.reason == "BADAXIS"


def test_unopenable_port() -> None:
    with pytest.raises(StageConnectionLost, match="/dev/no-such-zaber: cannot open the port"):
        ZaberStage("/dev/no-such-zaber", **STAGE)


@pytest.mark.parametrize(
    "change, match",
    [
        ({"microstep_um": 0.0}, "microstep_um must be > 0"),
        ({"tolerance_um": -1.0}, "tolerance_um must be > 0"),
        ({"timeout_s": 0.0}, "timeout_s, poll_s and no_progress_s must be > 0"),
        ({"settle_s": -0.1}, "settle_s and margin_s must be >= 0"),
        ({"travel_mm": (5.0, 5.0)}, r"travel_mm must be \(low, high\) with low < high"),
    ],
)
def test_bad_configuration(server: FakeZaberPty, change: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        ZaberStage(server.port, **{**STAGE, **change})
    assert server.device.received == []


def test_close_is_idempotent_and_final(server: FakeZaberPty) -> None:
    stage = ZaberStage(server.port, **STAGE)
    stage.close()
    stage.close()
    with pytest.raises(StageConnectionLost, match=r"stage is closed; not sent: '/1 1 \d\d get pos:..'"):
        _ = stage.position_mm


# ----- homing and moves ------------------------------------------------------------------------
def test_home_then_absolute_moves(stage: ZaberStage, device: FakeZaberDevice) -> None:
    assert not stage.is_homed
    assert stage.position_mm == pytest.approx(10.0)
    stage.home()
    assert stage.is_homed and device.homed and stage.position_mm == 0.0
    for z in (12.5, 40.0, 0.0, 3.1234):
        assert stage.move_to(z) == pytest.approx(z, abs=1e-4)
        assert device.position == round(z * 1e4) and not device.busy


def test_position_is_valid_while_moving(server: FakeZaberPty) -> None:
    server.device.settings.update(speed_settings(50.0, 2000.0))  # 20 mm in about 0.4 s
    with ZaberStage(server.port, **STAGE) as stage:
        stage.home()
        thread, out = in_background(lambda: stage.move_to(20.0))
        seen = []
        while thread.is_alive():
            seen.append(stage.position_mm)
            time.sleep(0.02)
        thread.join()
    assert out["result"] == pytest.approx(20.0)
    inside = [p for p in seen if 0.0 < p < 20.0]
    assert len(inside) >= 5 and inside == sorted(inside)


def test_move_before_homing_raises_not_homed(stage: ZaberStage) -> None:
    with pytest.raises(StageNotHomed, match=r"sent '/1 1 \d\d move abs 50000:..', got "
                       r"'@01 1 \d\d RJ IDLE WR BADDATA': .*call home\(\) first"):
        stage.move_to(5.0)


def test_zero_length_move_before_homing_is_not_a_shortcut(stage: ZaberStage) -> None:
    with pytest.raises(StageNotHomed):
        stage.move_to(10.0)  # the unhomed stage sits at 10 mm


@pytest.mark.parametrize("z", [-0.001, 40.0001, 45.0, float("nan"), float("inf")])
def test_targets_outside_the_travel_raise_before_any_byte_is_sent(
    homed: ZaberStage, device: FakeZaberDevice, z: float
) -> None:
    before = bytes(device.received_bytes)
    with pytest.raises(StageLimitError, match=re.escape(f"target {z} mm is outside the allowed travel "
                                                        "[0, 40] mm; nothing sent")):
        homed.move_to(z)
    assert bytes(device.received_bytes) == before
    assert homed.position_known and homed.last_position_mm == 0.0  # a refused move changes nothing


def test_unrepresentable_target_is_refused(server: FakeZaberPty) -> None:
    with ZaberStage(server.port, **{**STAGE, "tolerance_um": 0.01}) as stage:
        sent = len(server.device.received_bytes)
        with pytest.raises(StageLimitError, match=r"target 10.00004 mm is not representable: the "
                           r"nearest microstep \(100000\) is 0.04 um away, tolerance 0.01 um; nothing sent"):
            stage.move_to(10.00004)
        assert len(server.device.received_bytes) == sent


def test_device_side_rejection_is_typed(homed: ZaberStage, device: FakeZaberDevice) -> None:
    device.settings["limit.max"] = 100_000  # the device limit shrank after opening
    with pytest.raises(StageRejected, match=r"got '@01 1 \d\d RJ IDLE -- BADDATA': rejected \(BADDATA\)"):
        homed.move_to(20.0)


def test_zero_length_move_completes_at_once(homed: ZaberStage, device: FakeZaberDevice) -> None:
    homed.move_to(7.0)
    started = time.monotonic()
    assert homed.move_to(7.0) == pytest.approx(7.0)
    assert time.monotonic() - started < 0.1
    assert count(device, "move abs") == 1


def test_settle_time_is_waited_and_recorded(server: FakeZaberPty) -> None:
    with ZaberStage(server.port, **{**STAGE, "settle_s": 0.3}) as stage:
        stage.home()
        started = time.monotonic()
        stage.move_to(1.0)
        assert time.monotonic() - started >= 0.3
        assert stage.describe()["settle_s"] == 0.3


def test_stop_is_sent_to_the_axis(homed: ZaberStage, device: FakeZaberDevice) -> None:
    homed.stop()
    assert re.fullmatch(r"/1 1 \d\d stop:..", device.received[-1])


def run_thread(fn: Callable[[], object]) -> tuple[threading.Thread, dict]:
    """Like in_background, and also records when ``fn`` ended (time.monotonic) in 'ended'."""
    out: dict = {}

    def run() -> None:
        try:
            out["result"] = fn()
        except StageError as exc:
            out["error"] = exc
        out["ended"] = time.monotonic()

    thread = threading.Thread(target=run)
    thread.start()
    return thread, out


def wait_for_motion(device: FakeZaberDevice, min_steps: int = 1000) -> None:
    """Block until the fake's carriage has left 0 by ``min_steps`` (a move is under way)."""
    deadline = time.monotonic() + 2.0
    while device.position < min_steps:
        assert time.monotonic() < deadline, "the move never started"
        time.sleep(0.002)


def test_stop_from_another_thread_ends_a_move_with_stage_stopped(server: FakeZaberPty) -> None:
    server.device.settings.update(speed_settings(50.0, 2000.0))  # 30 mm take about 0.6 s
    with ZaberStage(server.port, **STAGE) as stage:
        stage.home()
        assert stage.position_known and stage.last_position_mm == 0.0
        started = time.monotonic()
        thread, out = run_thread(lambda: stage.move_to(30.0))
        wait_for_motion(server.device)
        stop_called = time.monotonic()
        stage.stop()
        thread.join()
        error = out["error"]
        assert isinstance(error, StageStopped)
        # promptly: the mover notices at its next poll, plus one stop command
        assert out["ended"] - stop_called <= STAGE["poll_s"] + 2 * TIMEOUT_S + 0.5
        assert out["ended"] - started <= stage.move_deadline_s(30.0) + 2 * TIMEOUT_S + 0.5
        assert re.search(rf"^{stage.port_name}: '/1 1 \d\d move abs 300000:..' \(target 30 mm\) was "
                         r"stopped by stop\(\) from another thread: .*device (BUSY|IDLE) at .* mm\); "
                         "axis stopped; position unknown", str(error))
        assert error.target_mm == 30.0 and 0.0 < error.position_mm < 30.0
        time.sleep(0.1)  # the deceleration from 50 mm/s at 2000 mm/s^2 takes 25 ms
        assert not server.device.busy and 0 < server.device.position < 300_000
        assert not stage.position_known
        with pytest.raises(StagePositionUnknown, match=rf"{stage.port_name}: rest position unknown: "
                           "move to 30 mm ended with StageStopped"):
            _ = stage.last_position_mm
        assert stage.move_to(30.0) == pytest.approx(30.0)  # the next move recovers
        assert stage.position_known and stage.last_position_mm == pytest.approx(30.0)
        assert server.device.position == 300_000


def test_stop_from_another_thread_ends_homing_with_stage_stopped(server: FakeZaberPty) -> None:
    server.device.settings.update(speed_settings(5.0, 2000.0))  # homing from 10 mm: 2 s
    with ZaberStage(server.port, **STAGE) as stage:
        thread, out = run_thread(stage.home)
        deadline = time.monotonic() + 2.0
        while server.device.position > 95_000:
            assert time.monotonic() < deadline
            time.sleep(0.002)
        stage.stop()
        thread.join()
        assert isinstance(out["error"], StageStopped) and out["error"].target_mm is None
        assert re.search(r"home:..' \(target home\) was stopped by stop\(\)", str(out["error"]))
        assert not server.device.homed and not stage.position_known


def test_second_move_from_another_thread_is_refused_with_stage_busy(server: FakeZaberPty) -> None:
    server.device.settings.update(speed_settings(50.0, 2000.0))
    with ZaberStage(server.port, **STAGE) as stage:
        stage.home()
        thread, out = run_thread(lambda: stage.move_to(30.0))
        wait_for_motion(server.device)
        sent = len(server.device.received)
        for second, what in ((lambda: stage.move_to(5.0), "move to 5 mm"), (stage.home, "home")):
            started = time.monotonic()
            with pytest.raises(StageBusy, match=rf"^{stage.port_name}: {what} refused: move to 30 mm "
                               r"is in progress \(started by another thread\); nothing sent$") as info:
                second()
            assert time.monotonic() - started < 0.05  # at once, not after the first move
            assert info.value.in_progress == "move to 30 mm"
        assert thread.is_alive()  # the first move was not disturbed ...
        new_lines = server.device.received[sent:]
        assert not any("move" in line or "home" in line or "stop" in line for line in new_lines)
        thread.join()
    assert out["result"] == pytest.approx(30.0)  # ... and completed correctly
    assert server.device.position == 300_000 and not server.device.busy
    assert count(server.device, "move abs") == 1 and count(server.device, "stop") == 0


def test_many_threads_polling_while_moving_never_interleave_bytes(server: FakeZaberPty) -> None:
    server.device.settings.update(speed_settings(50.0, 2000.0))
    with ZaberStage(server.port, **STAGE) as stage:
        stage.home()
        first = len(server.device.received)
        mover, out = run_thread(lambda: stage.move_to(30.0))
        seen: dict[int, list[float]] = {}
        errors: list[BaseException] = []

        def poll(n: int) -> None:
            seen[n] = []
            try:
                while mover.is_alive():
                    seen[n].append(stage.position_mm)
            except BaseException as exc:  # anything at all is a failure of this test
                errors.append(exc)

        pollers = [threading.Thread(target=poll, args=(n,)) for n in range(8)]
        for t in pollers:
            t.start()
        for t in pollers + [mover]:
            t.join()
        assert errors == [] and out["result"] == pytest.approx(30.0)
        for values in seen.values():
            assert len(values) >= 3 and values == sorted(values)  # a move only goes forward
            assert all(0.0 <= v <= 30.0 for v in values)
        lines = server.device.received[first:]
        assert len(lines) > 50
        ids = []
        for line in lines:  # every line the device got is one whole command ...
            match = re.fullmatch(r"/1 1 (\d\d) (get pos|move abs 300000):[0-9A-F]{2}", line)
            assert match and checksum_ok(line), line
            ids.append(int(match.group(1)))
        # ... and they arrived one at a time, in the order their message ids were given out
        assert all((b - a) % 100 == 1 for a, b in itertools.pairwise(ids))


# ----- fault switches --------------------------------------------------------------------------
def test_dropped_reply_to_a_query(stage: ZaberStage, device: FakeZaberDevice) -> None:
    device.faults.drop_replies = 1
    with pytest.raises(StageConnectionLost, match=r"sent '/1 1 \d\d get pos:..': no reply within 0.2 s"):
        _ = stage.position_mm
    assert stage.position_mm == pytest.approx(10.0)  # the next command works


def test_dropped_reply_to_a_move_reports_the_state_without_resending(
    homed: ZaberStage, device: FakeZaberDevice
) -> None:
    device.faults.drop_on = "move"
    with pytest.raises(StageConnectionLost, match=r"move abs 300000:..': no reply within 0.2 s; the "
                       r"motion command was not re-sent .*device (IDLE|BUSY) at .* mm") as info:
        homed.move_to(30.0)
    assert info.value.position_mm is not None and info.value.busy is not None
    assert count(device, "move abs") == 1
    assert homed.move_to(30.0) == pytest.approx(30.0)  # the caller decides: here, wait for it


def test_lost_reply_and_failed_state_query() -> None:
    state = {"dead": False}

    def die_at_move_reply(out: bytes) -> bytes:  # "OK BUSY -- 0" answers only the move here
        state["dead"] = state["dead"] or b" OK BUSY -- 0\r\n" in out
        return b"" if state["dead"] else out

    device = FakeZaberDevice(**FAST)
    with ZaberStage(TamperPort(device, die_at_move_reply), **STAGE) as stage:
        stage.home()
        with pytest.raises(StageConnectionLost, match=r"move abs 300000:..': no reply within 0.2 s; .* "
                           r"the state query failed too \(.*get pos:..': no reply within 0.2 s\)") as info:
            stage.move_to(30.0)
    assert info.value.position_mm is None and count(device, "move abs") == 1
    assert device.position == 300_000  # not stopped: the caller decides


def test_reply_delayed_past_the_timeout_is_discarded_later(stage: ZaberStage,
                                                           device: FakeZaberDevice) -> None:
    device.faults.delay_replies, device.faults.delay_s = 1, 0.3
    with pytest.raises(StageConnectionLost, match="limit.home.triggered:..': no reply within 0.2 s"):
        _ = stage.is_homed
    time.sleep(0.15)  # the late reply ("0") arrives now, before the next command's reply
    assert stage.position_mm == pytest.approx(10.0)
    assert stage.is_homed is False


def test_garbled_reply(stage: ZaberStage, device: FakeZaberDevice) -> None:
    device.faults.garble_replies = 1
    with pytest.raises(StageProtocolError, match=r"sent '/1 1 \d\d get pos:..', got b'@01 1 \d\d "
                       r"\\xcf\\xcb IDLE WR 100000\\r\\n': garbled reply \(not ASCII\)"):
        _ = stage.position_mm
    assert stage.position_mm == pytest.approx(10.0)


def test_bad_reply_checksum(stage: ZaberStage, device: FakeZaberDevice) -> None:
    device.faults.bad_checksum_replies = 1
    with pytest.raises(StageProtocolError, match=r"got '@01 1 \d\d OK IDLE WR 100000:..': reply fails "
                       "its checksum"):
        _ = stage.position_mm
    device.reply_checksums = True  # good checksums are verified and accepted
    assert stage.position_mm == pytest.approx(10.0)


def test_stall_mid_move_raises_fault(homed: ZaberStage, device: FakeZaberDevice) -> None:
    device.faults.stall_at = 0.5
    with pytest.raises(StageFault, match=r"got '@01 1 \d\d OK IDLE FS 150000': FS stalled; axis "
                       "stopped") as info:
        homed.move_to(30.0)
    assert info.value.warning == "FS"
    assert not homed.position_known  # the move did not complete
    with pytest.raises(StagePositionUnknown, match="move to 30 mm ended with StageFault"):
        _ = homed.last_position_mm
    assert homed.move_to(30.0) == pytest.approx(30.0)  # a new move clears the stall
    assert homed.position_known and homed.last_position_mm == pytest.approx(30.0)


def test_stall_at_once_is_reported_by_the_move_reply(homed: ZaberStage, device: FakeZaberDevice) -> None:
    device.faults.stall_at = 0.0
    with pytest.raises(StageFault, match=r"sent '/1 1 \d\d move abs 300000:..', got "
                       r"'@01 1 \d\d OK IDLE FS 0': FS stalled"):
        homed.move_to(30.0)


def test_stall_while_homing(stage: ZaberStage, device: FakeZaberDevice) -> None:
    device.faults.stall_at = 0.5
    with pytest.raises(StageFault, match="FS stalled; axis stopped"):
        stage.home()


def test_idle_for_one_poll_mid_move_is_not_mistaken_for_done(homed: ZaberStage,
                                                             device: FakeZaberDevice) -> None:
    device.faults.idle_glitch = True
    assert homed.move_to(35.0) == pytest.approx(35.0)
    assert device.position == 350_000 and device.faults.idle_glitch is False


def test_never_reaching_the_target_times_out_on_no_progress(homed: ZaberStage,
                                                            device: FakeZaberDevice) -> None:
    device.faults.stop_short = 500
    with pytest.raises(StageTimeout, match=r"'/1 1 \d\d move abs 200000:..' no progress for 0.15 s: "
                       r"last sent .*, got '@01 1 \d\d OK IDLE -- 199500' \(device IDLE at 19.95 mm, "
                       r"target 20 mm\); axis stopped"):
        homed.move_to(20.0)
    assert count(device, "stop") == 1


def test_homing_that_does_not_reference_raises_not_homed(stage: ZaberStage, device: FakeZaberDevice) -> None:
    device.faults.stop_short = 10
    with pytest.raises(StageNotHomed, match=r"homing ended but sent '/1 1 \d\d get limit.home.triggered:..',"
                       r" got '@01 1 \d\d OK IDLE WR 0': no reference position"):
        stage.home()


def test_move_deadline_stops_the_axis(homed: ZaberStage, device: FakeZaberDevice) -> None:
    started = time.monotonic()
    with pytest.raises(StageTimeout, match=r"not done within 0.03 s \(raise the timeout, or check "
                       r"maxspeed/accel\): .*; axis stopped"):
        homed.move_to(40.0, timeout=0.03)
    assert time.monotonic() - started < 0.03 + 2 * TIMEOUT_S + 0.5
    time.sleep(0.1)
    assert not device.busy and device.position < 400_000


def test_computed_timeout_covers_a_full_travel_move(homed: ZaberStage) -> None:
    # 40 mm at 200 mm/s: 0.2 s + 2 * 0.02 s + 0.3 s margin
    assert homed._motion_time(400_000) == pytest.approx(0.2 + 0.04 + 0.3, rel=1e-3)
    assert homed.move_deadline_s(40.0) == pytest.approx(0.2 + 0.04 + 0.3, rel=1e-3)
    assert homed.move_to(40.0) == pytest.approx(40.0)


def test_unsolicited_info_and_alert_lines_are_ignored(homed: ZaberStage, device: FakeZaberDevice) -> None:
    device.faults.info_lines, device.faults.alert_lines = 3, 2
    assert homed.move_to(25.0) == pytest.approx(25.0)
    device.faults.alert_lines = 1
    time.sleep(0.05)
    assert homed.position_mm == pytest.approx(25.0)


def test_vanished_pty_gives_connection_lost(stage: ZaberStage, server: FakeZaberPty) -> None:
    server.device.faults.vanish = True
    while not server.vanished:
        time.sleep(0.002)
    with pytest.raises(StageConnectionLost, match=rf"{stage.port_name}: .*(write failed|port failed).*"
                       "re-open failed"):
        _ = stage.position_mm


def test_pty_vanishing_after_a_move_command(homed: ZaberStage, device: FakeZaberDevice) -> None:
    device.faults.vanish_on = "move"
    with pytest.raises(StageConnectionLost, match=r"move abs 100000:..': port failed while waiting for "
                       r"the reply .*re-open failed.*device state unknown") as info:
        homed.move_to(10.0)
    assert info.value.position_mm is None and info.value.busy is None


@pytest.mark.slow
def test_silent_device_every_call_returns_within_its_deadline(stage: ZaberStage,
                                                              device: FakeZaberDevice) -> None:
    device.faults.silent = True
    one, two = TIMEOUT_S, 2 * TIMEOUT_S  # a lost motion reply is followed by one state query
    calls = [
        (lambda: stage.position_mm, one),
        (lambda: stage.is_homed, one),
        (stage.stop, one),
        (stage.home, two),
        (lambda: stage.move_to(5.0), one),
        (lambda: ZaberStage(stage.port_name, **STAGE), one),
    ]
    for call, deadline in calls:
        started = time.monotonic()
        with pytest.raises(StageConnectionLost, match="no reply within 0.2 s"):
            call()
        elapsed = time.monotonic() - started
        assert TIMEOUT_S <= elapsed <= deadline + 0.5


def test_device_going_silent_mid_move(server: FakeZaberPty) -> None:
    server.device.settings.update(speed_settings(50.0, 2000.0))
    with ZaberStage(server.port, **STAGE) as stage:
        stage.home()
        thread, out = in_background(lambda: stage.move_to(30.0))
        time.sleep(0.05)
        server.device.faults.silent = True
        started = time.monotonic()
        thread.join()
        assert time.monotonic() - started <= 2 * TIMEOUT_S + 0.5
    assert isinstance(out["error"], StageConnectionLost)
    assert re.search(r"get pos:..': no reply within 0.2 s; stopping the axis failed too \(.*stop:..': "
                     r"no reply", str(out["error"]))


def test_garbled_poll_stops_the_axis(server: FakeZaberPty) -> None:
    server.device.settings.update(speed_settings(50.0, 2000.0))
    with ZaberStage(server.port, **STAGE) as stage:
        stage.home()
        thread, out = in_background(lambda: stage.move_to(30.0))
        time.sleep(0.05)
        server.device.faults.garble_replies = 1
        thread.join()
        time.sleep(0.1)  # the deceleration takes 25 ms
        assert not server.device.busy and count(server.device, "stop") == 1
    assert isinstance(out["error"], StageProtocolError)
    assert re.search(r"garbled reply \(not ASCII\); axis stopped$", str(out["error"]))


# ----- reconnecting (URL handler: the device can be plugged back) -------------------------------
def test_failed_write_is_resent_once_after_reopening(url: str) -> None:
    device = url_device("stage-test")
    with ZaberStage(url, **STAGE) as stage:
        device.faults.vanish = True
        before = count(device, "get pos")
        assert stage.position_mm == pytest.approx(10.0)
        assert count(device, "get pos") == before + 1


def test_lost_reply_after_move_is_queried_after_reopening(url: str) -> None:
    device = url_device("stage-test")
    with ZaberStage(url, **STAGE) as stage:
        stage.home()
        device.faults.vanish_on = "move"
        with pytest.raises(StageConnectionLost, match=r"move abs 300000:..': port failed while waiting "
                           r"for the reply \(fakezaber://stage-test: device vanished\); re-opened; the "
                           r"motion command was not re-sent .*"
                           r"got '@01 1 \d\d OK BUSY -- \d+': device BUSY") as info:
            stage.move_to(30.0)
        assert info.value.busy is True and 0.0 <= info.value.position_mm <= 30.0
        assert count(device, "move abs") == 1
        assert stage.move_to(30.0) == pytest.approx(30.0)


def test_port_object_cannot_be_reopened(url: str) -> None:
    device = url_device("stage-test")
    port = serial.serial_for_url(url)
    with ZaberStage(port, **STAGE) as stage:
        device.faults.vanish = True
        with pytest.raises(StageConnectionLost, match=r"sent '/1 1 \d\d get pos:..': write failed "
                           r"\(fakezaber://stage-test: device vanished\); re-open failed: .*a port object "
                           "passed in cannot be re-opened"):
            _ = stage.position_mm


def test_write_failing_again_after_reopening(url: str, monkeypatch: pytest.MonkeyPatch) -> None:
    class BrokenPort:
        timeout = None

        def reset_input_buffer(self) -> None:
            pass

        def write(self, data: bytes) -> int:
            raise serial.SerialException("still broken")

        def close(self) -> None:
            pass

    device = url_device("stage-test")
    with ZaberStage(url, **STAGE) as stage:
        monkeypatch.setattr(serial, "serial_for_url", lambda *a, **k: BrokenPort())
        device.faults.vanish = True
        with pytest.raises(StageConnectionLost, match=r"get pos:..': write failed \(.*vanished\), and "
                           r"again after re-opening \(still broken\)"):
            _ = stage.position_mm


# ----- replies that are wrong in other ways (a port object that rewrites the fake's bytes) -----
class TamperPort:
    """A serial-like object in front of a FakeZaberDevice that rewrites its reply bytes."""

    port = "tamper://"

    def __init__(self, device: FakeZaberDevice, tamper: Callable[[bytes], bytes]) -> None:
        self.device, self.tamper = device, tamper
        self.timeout: float | None = None
        self._buf = bytearray()

    def write(self, data: bytes) -> int:
        self.device.feed(data)
        out = self.device.read_output()
        self._buf += self.tamper(out) if out else b""
        return len(data)

    def read(self, size: int = 1) -> bytes:
        if not self._buf:
            time.sleep(self.timeout or 0.0)
        data = bytes(self._buf[:size])
        del self._buf[:size]
        return data

    def close(self) -> None:
        pass


@pytest.mark.parametrize(
    "tamper, match",
    [
        (lambda b: b"ERROR 42\r\n", r"got 'ERROR 42': not a Zaber ASCII reply \(wrong port or baud rate\?\)"),
        (lambda b: b"x" * 3000, r"got 'xxxxx.*': not a Zaber ASCII reply"),
        (lambda b: b.replace(b" OK ", b" OX "), r"got '@01 0 \d\d OX IDLE WR 50081': garbled reply"),
        (lambda b: re.sub(rb"^(@\d\d \d) \d\d ", rb"\1 ", b), r"got '@01 0 OK IDLE WR 50081': reply "
         "carries no message id"),
        (lambda b: b.replace(b"50081", b"50_081"),
         r"got '@01 0 \d\d OK IDLE WR 50_081': expected an integer"),
        (lambda b: b.replace(b"50081", b"+50081"),
         r"got '@01 0 \d\d OK IDLE WR \+50081': expected an integer"),
        (lambda b: b.replace(b"@01", b"@02"), r"got '@02 0 \d\d OK IDLE WR 50081': reply from device 2 "
         "axis 0, expected device 1 axis 0"),
    ],
)
def test_wrong_replies_on_open(tamper: Callable[[bytes], bytes], match: str) -> None:
    port = TamperPort(FakeZaberDevice(**FAST), tamper)
    with pytest.raises(StageProtocolError, match=rf"tamper://: sent '/1 0 01 get deviceid:..', {match}"):
        ZaberStage(port, **STAGE)


def test_port_object_with_plain_replies_works() -> None:
    with ZaberStage(TamperPort(FakeZaberDevice(**FAST), lambda b: b), **STAGE) as stage:
        assert stage.position_mm == pytest.approx(10.0)
        assert stage.describe()["port"] == "tamper://"
