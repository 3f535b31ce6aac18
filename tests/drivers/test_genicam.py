"""GenICamCamera against Aravis's fake GigE Vision camera on loopback.

Each test starts its own fake camera in a child process (tests/support/gv_fake.py) with its own serial
number; frames are checked against the fake's documented diagonal ramp.
"""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest

from drivers.camera import CameraError, CameraTimeout
from drivers.genicam import CameraLost, CameraNotFound, CameraSettingError, GenICamCamera, list_cameras
from tests.support.gv_fake import DEFAULT_SIZE, expected_pattern, running_fake_camera

_serials = itertools.count(1)


@pytest.fixture
def fake():
    with running_fake_camera(f"LTC{next(_serials):03d}") as camera:
        yield camera


def _next_id(frame_id: int) -> int:
    return 1 if frame_id == 0xFFFF else frame_id + 1


def test_list_cameras_finds_the_fake_with_its_identity(fake):
    found = [c for c in list_cameras() if c.serial == fake.serial]
    assert len(found) == 1
    info = found[0]
    assert (info.vendor, info.model, info.protocol, info.address) == \
        ("Aravis", "Fake", "GigEVision", "127.0.0.1")
    assert info.device_id == f"Aravis-Fake-{fake.serial}"


@pytest.mark.slow
def test_software_trigger_frames_are_the_fakes_ramp_with_consecutive_ids(fake):
    with GenICamCamera(serial=fake.serial, exposure_ms=10.0) as camera:
        assert camera.size == DEFAULT_SIZE and camera.bit_depth == 8
        frames = [camera.capture(timeout=2.0) for _ in range(5)]
    for frame in frames:
        assert frame.image.dtype == np.uint8 and frame.image.shape == DEFAULT_SIZE[::-1]
        assert not frame.image.flags.writeable  # a view of PyGObject's copy, not of a stream buffer
        np.testing.assert_array_equal(frame.image, expected_pattern(frame.frame_id, *DEFAULT_SIZE))
        assert frame.exposure_ms == pytest.approx(10.0)
    ids = [f.frame_id for f in frames]
    assert ids[1:] == [_next_id(i) for i in ids[:-1]]
    # device timestamps (s) increase, one trigger period or more apart; host times too
    stamps = [f.timestamp for f in frames]
    assert all(0 < b - a < 1.0 for a, b in itertools.pairwise(stamps))
    hosts = [f.meta["host_time"] for f in frames]
    assert all(a < b for a, b in itertools.pairwise(hosts))
    assert not np.array_equal(frames[0].image, frames[1].image)


def test_open_by_device_id_and_by_address(fake):
    with GenICamCamera(f"Aravis-Fake-{fake.serial}") as by_id:
        assert by_id.describe()["serial"] == fake.serial
    with GenICamCamera(fake.address) as by_address:
        assert by_address.name == f"Aravis Fake {fake.serial!r}"


@pytest.mark.slow
def test_free_run_delivers_every_frame_in_order(fake):
    with GenICamCamera(serial=fake.serial, trigger=None, frame_rate_hz=100.0) as camera:
        frames = [camera.capture(timeout=1.0) for _ in range(20)]
        assert camera.flush() >= 0
    ids = [f.frame_id for f in frames]
    assert ids[1:] == [_next_id(i) for i in ids[:-1]]
    for frame in frames[::5]:
        np.testing.assert_array_equal(frame.image, expected_pattern(frame.frame_id, *DEFAULT_SIZE))
    # 100 Hz free run: 19 periods of 10 ms between the first and last device timestamps. The
    # fake's frame thread can only run late on a loaded machine (0.28 s seen under the full
    # suite), never early; a timestamp in the wrong unit or the fake's default 25 Hz (0.76 s)
    # still fails
    assert 0.16 <= frames[-1].timestamp - frames[0].timestamp <= 0.45


@pytest.mark.slow
def test_exposure_and_gain_round_trip(fake):
    with GenICamCamera(serial=fake.serial) as camera:
        for ms in (0.5, 12.5, 40.0):
            camera.exposure_ms = ms
            assert camera.exposure_ms == pytest.approx(ms)
            assert camera.capture().exposure_ms == pytest.approx(ms)
        camera.exposure_ms = 10.0
        camera.gain = 1.0
        assert camera.gain == 1.0
        frame = camera.capture()
        # the fake scales its ramp by 1 + gain + log10(exposure_us / 10000) = 2
        np.testing.assert_array_equal(
            frame.image, expected_pattern(frame.frame_id, *DEFAULT_SIZE, gain=1.0))


@pytest.mark.slow
def test_mono16_and_roi(fake):
    with GenICamCamera(serial=fake.serial) as camera:
        first = camera.capture()
        camera.pixel_format = "Mono16"
        camera.roi = (16, 8, 64, 40)
        assert camera.bit_depth == 16 and camera.size == (64, 40)
        assert camera.roi == (16, 8, 64, 40)
        frames = [camera.capture() for _ in range(2)]
        assert first.image.dtype == np.uint8
    for frame in frames:
        assert frame.image.dtype == np.uint16 and frame.image.shape == (40, 64)
        np.testing.assert_array_equal(frame.image, expected_pattern(frame.frame_id, 64, 40, 16))
    assert frames[1].frame_id == _next_id(frames[0].frame_id)


@pytest.mark.slow
def test_camera_that_vanishes_mid_stream_raises_camera_lost_in_time(fake):
    camera = GenICamCamera(serial=fake.serial, trigger=None, frame_rate_hz=50.0)
    for _ in range(3):
        camera.capture(timeout=1.0)
    fake.kill()
    time.sleep(0.1)
    camera.flush()  # frames that arrived before the kill
    start = time.monotonic()
    with pytest.raises(CameraLost, match=rf"camera Aravis Fake '{fake.serial}': no frame within "
                       r"0.5 s, and the camera no longer answers at 127.0.0.1"):
        camera.capture(timeout=0.5)
    assert time.monotonic() - start < 0.5 + 0.5
    start = time.monotonic()
    camera.close()  # already closed by the error: idempotent, and immediate
    camera.close()
    assert time.monotonic() - start < 0.5
    with pytest.raises(CameraError, match="is closed"):
        camera.capture()


@pytest.mark.slow
def test_triggered_camera_that_vanishes_raises_within_the_deadline(fake):
    camera = GenICamCamera(serial=fake.serial)
    camera.capture()
    fake.kill()
    start = time.monotonic()
    with pytest.raises(CameraLost, match=rf"camera Aravis Fake '{fake.serial}': TriggerSoftware"):
        camera.capture(timeout=0.5)  # Aravis alone would retry the trigger for 2.5 s
    assert time.monotonic() - start < 0.5 + 0.5
    camera.close()


@pytest.mark.slow
def test_no_trigger_pulse_times_out_within_the_deadline(fake):
    with GenICamCamera(serial=fake.serial, trigger="Line0") as camera:
        start = time.monotonic()
        with pytest.raises(CameraTimeout, match=rf"camera Aravis Fake '{fake.serial}': no frame "
                           r"within 0.3 s$"):
            camera.capture(timeout=0.3)
        assert 0.3 <= time.monotonic() - start < 0.3 + 0.5
        camera.trigger = "software"  # the camera is still usable afterwards
        frame = camera.capture()
        np.testing.assert_array_equal(frame.image, expected_pattern(frame.frame_id, *DEFAULT_SIZE))


@pytest.mark.parametrize(("setting", "value", "message"), [
    ("pixel_format", "Mono12", r"pixel format 'Mono12' is not offered by the device \(it offers: "
     r".*Mono8, RGB8, Mono16\)"),
    ("pixel_format", "RGB8", r"pixel format 'RGB8' is not supported by this driver"),
    ("roi", (2000, 0, 100, 10), r"ROI \(2000, 0, 100, 10\) refused: region ends at \(2100, 10\), "
     r"beyond the 2048 x 2048 sensor"),
    ("roi", (0, 0, 0, 10), r"ROI \(0, 0, 0, 10\) refused: width 0 outside 1..2048"),
    ("roi", (-1, 0, 10, 10), r"ROI \(-1, 0, 10, 10\) refused: x -1 below 0"),
    ("exposure_ms", 20000.0, r"exposure 20000.0 ms is outside the device's 0.01..10000 ms"),
    ("gain", 11.0, r"gain 11.0 is outside the device's 0..10"),
    ("trigger", "Line7", r"trigger source 'Line7' is not offered by the device \(it offers: "
     r"Line0, Software\)"),
])
def test_unsupported_settings_are_typed_errors_naming_camera_and_value(fake, setting, value,
                                                                         message):
    with GenICamCamera(fake.address) as camera:  # by address: no 1 s discovery per case
        before = camera.capture()
        with pytest.raises(CameraSettingError, match=rf"camera Aravis Fake '{fake.serial}': "
                           + message):
            setattr(camera, setting, value)
        after = camera.capture()  # nothing changed
        assert after.image.shape == before.image.shape and after.image.dtype == np.uint8


@pytest.mark.slow
def test_unknown_camera_is_camera_not_found(fake):
    with pytest.raises(CameraNotFound, match=r"no camera with serial 'NOPE'; found: "
                       rf".*Aravis-Fake-{fake.serial} \(serial '{fake.serial}'\)"):
        GenICamCamera(serial="NOPE")
    with pytest.raises(CameraNotFound, match=r"camera 'Nobody-None-0': cannot open: Device "
                       r"'Nobody-None-0' not found"):
        GenICamCamera("Nobody-None-0")


def test_missing_pygobject_names_the_packages_to_install(monkeypatch):
    from drivers.genicam import AravisUnavailable

    monkeypatch.setitem(__import__("sys").modules, "gi", None)  # import gi -> ImportError
    with pytest.raises(AravisUnavailable, match=r"need PyGObject \(module 'gi'\): install "
                       r"Debian's gir1.2-aravis-0.8 .*libgirepository1.0-dev libcairo2-dev"):
        GenICamCamera("127.0.0.1")
