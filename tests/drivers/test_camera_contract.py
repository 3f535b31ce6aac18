"""One contract for every Camera implementation (drivers.interfaces.Camera).

Implementations: GenICamCamera on Aravis's fake GigE Vision camera (tests/support/gv_fake.py),
OpenCVCamera on a small lossless video written here with cv2.VideoWriter, and the fake bench
camera (fakes/camera.py) looking at the offscreen fake LCD.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import cv2
import numpy as np
import pytest

from drivers.camera import CameraError, CameraTimeout, OpenCVCamera
from drivers.display import OffscreenDisplay
from drivers.genicam import GenICamCamera
from drivers.interfaces import Camera, DeviceError, Frame
from fakes.bench import BenchConfig, FakeBench
from fakes.camera import FakeCamera, NoiseModel
from fakes.lcd import FakeLCD
from tests.support.gv_fake import running_fake_camera

VIDEO_SIZE, VIDEO_FRAMES = (64, 48), 6
_serials = itertools.count(1)


@dataclass
class Case:
    """A camera under test and what its implementation can do."""

    camera: Camera
    exposure_settable: bool  # False: setting exposure is refused with a CameraError
    make_it_time_out: Callable[[], None] | None  # arrange for the next capture to time out


@pytest.fixture
def genicam() -> Iterator[Case]:
    with running_fake_camera(f"CONTRACT{next(_serials)}") as fake:
        camera = GenICamCamera(fake.address, roi=(0, 0, 64, 48))

        def no_trigger() -> None:
            camera.trigger = "Line0"  # waits for a line pulse that never comes

        try:
            yield Case(camera, True, no_trigger)
        finally:
            camera.close()


@pytest.fixture
def opencv(tmp_path) -> Iterator[Case]:
    path = str(tmp_path / "contract.avi")
    writer = cv2.VideoWriter(path, cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*"FFV1"), 10.0,
                             VIDEO_SIZE, False)
    assert writer.isOpened()
    for i in range(VIDEO_FRAMES):
        writer.write(np.full(VIDEO_SIZE[::-1], 40 * i, np.uint8))
    writer.release()
    camera = OpenCVCamera(path, backend="FFMPEG")
    try:
        yield Case(camera, False, None)  # a file never blocks: no timeout to provoke
    finally:
        camera.close()


@pytest.fixture
def fake_bench() -> Iterator[Case]:
    config = BenchConfig.small(pupil_samples=16, subpixels=1)
    with FakeLCD(OffscreenDisplay(config.lcd_size)) as lcd:
        lcd.show(np.full(config.lcd_size[::-1], 200, np.uint8))
        camera = FakeCamera(FakeBench(config), lcd, lambda: 0.0, NoiseModel(), timeout_s=0.3)

        def fault() -> None:
            camera.faults.timeout = 1

        try:
            yield Case(camera, True, fault)
        finally:
            camera.close()


ALL = ["genicam", "opencv", "fake_bench"]
TIMES_OUT = ["genicam", "fake_bench"]


@pytest.fixture
def case(request) -> Case:
    return request.getfixturevalue(request.param)


def _check_frame(frame: Frame, camera: Camera) -> None:
    assert isinstance(frame, Frame)
    width, height = camera.size
    assert frame.image.shape == (height, width)
    assert frame.image.dtype == (np.uint8 if camera.bit_depth <= 8 else np.uint16)
    assert int(frame.image.max()) < 2**camera.bit_depth
    assert isinstance(frame.frame_id, int)
    assert isinstance(frame.timestamp, float) and math.isfinite(frame.timestamp)
    expected = camera.exposure_ms
    assert frame.exposure_ms == pytest.approx(expected, nan_ok=True)
    assert isinstance(frame.meta, dict)


@pytest.mark.parametrize("case", ALL, indirect=True)
def test_capture_returns_documented_frames(case):
    camera = case.camera
    frames = [camera.capture(timeout=2.0) for _ in range(3)]
    for frame in frames:
        _check_frame(frame, camera)
    ids = [f.frame_id for f in frames]
    assert all(b > a or (a == 0xFFFF and b == 1) for a, b in itertools.pairwise(ids))
    stamps = [f.timestamp for f in frames]
    assert all(b >= a for a, b in itertools.pairwise(stamps))
    assert camera.bit_depth in (8, 10, 12, 16)


@pytest.mark.parametrize("case", ALL, indirect=True)
def test_exposure_round_trips_or_is_refused_with_a_typed_error(case):
    camera = case.camera
    if case.exposure_settable:
        for ms in (5.0, 12.5):
            camera.exposure_ms = ms
            assert camera.exposure_ms == pytest.approx(ms)
            assert camera.capture(timeout=2.0).exposure_ms == pytest.approx(ms)
    else:
        before = camera.exposure_ms
        with pytest.raises(CameraError, match="refused exposure 12.5 ms"):
            camera.exposure_ms = 12.5
        assert camera.exposure_ms == pytest.approx(before, nan_ok=True)
    with pytest.raises(ValueError):  # a non-positive exposure is a ValueError everywhere
        camera.exposure_ms = 0.0


@pytest.mark.parametrize("case", TIMES_OUT, indirect=True)
def test_timeout_is_honoured(case):
    case.make_it_time_out()
    start = time.monotonic()
    with pytest.raises(CameraTimeout):
        case.camera.capture(timeout=0.3)
    assert time.monotonic() - start < 0.3 + 0.5


@pytest.mark.parametrize("case", ALL, indirect=True)
def test_close_is_idempotent(case):
    case.camera.capture(timeout=2.0)
    case.camera.close()
    case.camera.close()


@pytest.mark.parametrize("case", ["genicam", "opencv"], indirect=True)
def test_capture_after_close_is_a_camera_error(case):
    case.camera.close()
    with pytest.raises(CameraError, match="is closed"):
        case.camera.capture(timeout=0.5)


def test_error_hierarchy():
    from drivers import genicam

    for name in ("CameraNotFound", "CameraSettingError", "CameraFrameError", "CameraFrameDropped",
                 "CameraLost", "AravisUnavailable"):
        assert issubclass(getattr(genicam, name), CameraError)
    assert issubclass(CameraError, DeviceError) and issubclass(CameraTimeout, DeviceError)
    assert issubclass(genicam.CameraSettingError, ValueError)
