"""OpenCVCamera through real OpenCV backends (FFmpeg video, image sequences) and injected captures."""

from __future__ import annotations

import math
import threading
import time
from itertools import pairwise

import cv2
import numpy as np
import pytest

from drivers.camera import CameraError, CameraTimeout, OpenCVCamera

ROWS, COLS, N_FRAMES = 48, 64, 5


@pytest.fixture
def frames() -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    return [rng.integers(0, 256, (ROWS, COLS), dtype=np.uint8) for _ in range(N_FRAMES)]


@pytest.fixture
def ffv1_video(tmp_path, frames) -> str:
    """A lossless FFV1 video of ``frames``, written with OpenCV's FFmpeg backend."""
    path = str(tmp_path / "frames.avi")
    fourcc = cv2.VideoWriter_fourcc(*"FFV1")
    writer = cv2.VideoWriter(path, cv2.CAP_FFMPEG, fourcc, 10.0, (COLS, ROWS), False)
    assert writer.isOpened()
    for frame in frames:
        writer.write(frame)
    writer.release()
    return path


def read_all(camera: OpenCVCamera, n: int) -> list:
    return [camera.capture(timeout=2.0) for _ in range(n)]


def test_ffv1_video_frames_match_exactly(ffv1_video, frames):
    with OpenCVCamera(ffv1_video, backend="FFMPEG") as camera:
        assert camera.size == (COLS, ROWS)
        got = read_all(camera, N_FRAMES)
        assert camera.describe()["backend"] == "FFMPEG"
        assert camera.bit_depth == 8
        message = r"camera '.*frames.avi' \(FFMPEG\) delivered no frame after 5 frames: end of stream"
        with pytest.raises(CameraError, match=message):
            camera.capture()
    for frame, expected in zip(got, frames, strict=True):
        assert frame.image.dtype == np.uint8 and frame.image.shape == (ROWS, COLS)
        np.testing.assert_array_equal(frame.image, expected)
    assert [f.frame_id for f in got] == list(range(N_FRAMES))
    stamps = [f.timestamp for f in got]
    assert all(a < b for a, b in pairwise(stamps))
    assert all(math.isnan(f.exposure_ms) for f in got)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_png_sequence_frames_match_exactly(tmp_path, frames, dtype):
    scale = 257 if dtype == np.uint16 else 1
    written = [f.astype(dtype) * dtype(scale) for f in frames]
    for i, frame in enumerate(written):
        assert cv2.imwrite(str(tmp_path / f"img_{i:03d}.png"), frame)
    with OpenCVCamera(str(tmp_path / "img_%03d.png"), backend=cv2.CAP_IMAGES) as camera:
        got = read_all(camera, N_FRAMES)
        assert camera.bit_depth == (16 if dtype == np.uint16 else 8)
        with pytest.raises(CameraError, match="delivered no frame after 5 frames"):
            camera.capture()
    for frame, expected in zip(got, written, strict=True):
        assert frame.image.dtype == dtype
        np.testing.assert_array_equal(frame.image, expected)


def test_settings_refused_by_a_file_backend_are_reported(ffv1_video):
    with OpenCVCamera(ffv1_video, backend="FFMPEG", exposure_ms=10.0, gain=2.0) as camera:
        info = camera.describe()
        assert info["accepted"] == {"auto_exposure_off": False, "exposure": False, "gain": False}
        assert math.isnan(camera.exposure_ms)
        message = r"camera '.*frames.avi' \(FFMPEG\) refused exposure 5.0 ms"
        with pytest.raises(CameraError, match=message):
            camera.exposure_ms = 5.0
        with pytest.raises(ValueError, match="exposure must be > 0 ms, got 0"):
            camera.exposure_ms = 0


def test_unopenable_source_names_source_and_backend(tmp_path):
    with pytest.raises(CameraError, match=r"cannot open camera '.*missing.avi' with OpenCV CAP_FFMPEG"):
        OpenCVCamera(str(tmp_path / "missing.avi"), backend="FFMPEG")
    with pytest.raises(CameraError, match=r"cannot open camera '.*missing.avi' with OpenCV CAP_ANY"):
        OpenCVCamera(tmp_path / "missing.avi")


def test_bad_exposure_is_refused_before_opening(tmp_path):
    with pytest.raises(ValueError, match=r"camera '.*missing.avi': exposure must be > 0 ms, got -1"):
        OpenCVCamera(str(tmp_path / "missing.avi"), exposure_ms=-1)


def test_unknown_backend_name_is_refused():
    with pytest.raises(CameraError, match=r"unknown OpenCV backend 'NOPE' \(no cv2.CAP_NOPE\)"):
        OpenCVCamera(0, backend="NOPE")


class FakeCapture:
    """Stands in for cv2.VideoCapture: hands out ``images``; ``read`` may block or raise."""

    def __init__(self, images, backend="V4L2", block: threading.Event | None = None, error=None):
        self.images = list(images)
        self.backend = backend
        self.block = block
        self.error = error
        self.props: dict[int, float] = {}
        self.released = False

    def isOpened(self):
        return True

    def getBackendName(self):
        return self.backend

    def get(self, prop):
        return self.props.get(prop, 0.0)

    def set(self, prop, value):
        self.props[prop] = value
        return True

    def read(self):
        if self.block is not None:
            self.block.wait()
        if self.error is not None:
            raise self.error
        return (True, self.images.pop(0)) if self.images else (False, None)

    def release(self):
        self.released = True


@pytest.mark.parametrize(
    ("backend", "auto_off", "device_exposure"),
    [("V4L2", 1.0, 200.0), ("DSHOW", 0.25, math.log2(0.02)), ("MSMF", 0.25, math.log2(0.02))],
)
def test_exposure_and_gain_in_backend_units(backend, auto_off, device_exposure):
    fake = FakeCapture([], backend=backend)
    camera = OpenCVCamera("cam0", exposure_ms=20.0, gain=3.0, capture=fake)
    assert fake.props[cv2.CAP_PROP_AUTO_EXPOSURE] == auto_off
    assert fake.props[cv2.CAP_PROP_EXPOSURE] == pytest.approx(device_exposure)
    assert fake.props[cv2.CAP_PROP_GAIN] == 3.0
    assert camera.exposure_ms == pytest.approx(20.0)
    assert camera.describe()["accepted"] == {"auto_exposure_off": True, "exposure": True, "gain": True}
    camera.exposure_ms = 8.0
    assert camera.exposure_ms == pytest.approx(8.0)


def test_frames_carry_exposure_and_colour_becomes_mono():
    bgr = np.random.default_rng(1).integers(0, 256, (ROWS, COLS, 3), dtype=np.uint8)
    bgra = np.dstack([bgr, np.full((ROWS, COLS), 255, np.uint8)])
    camera = OpenCVCamera("cam0", exposure_ms=10.0, capture=FakeCapture([bgr, bgra, bgr[:, :, :1]]))
    frames = read_all(camera, 3)
    expected = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    np.testing.assert_array_equal(frames[0].image, expected)
    np.testing.assert_array_equal(frames[1].image, expected)
    np.testing.assert_array_equal(frames[2].image, bgr[:, :, 0])
    assert [f.exposure_ms for f in frames] == [pytest.approx(10.0)] * 3
    assert camera.size == (COLS, ROWS)


@pytest.mark.parametrize(
    ("image", "message"),
    [(np.zeros((4, 4), np.float32), "unsupported frame dtype float32"),
     (np.zeros((4, 4, 2), np.uint8), r"unsupported frame shape \(4, 4, 2\)")],
)
def test_unsupported_frames_are_refused(image, message):
    camera = OpenCVCamera("cam0", capture=FakeCapture([image]))
    with pytest.raises(CameraError, match=f"camera 'cam0': {message}"):
        camera.capture()


def test_backend_error_during_read_names_the_camera():
    camera = OpenCVCamera("cam0", capture=FakeCapture([], error=cv2.error("boom")))
    with pytest.raises(CameraError, match=r"camera 'cam0' \(V4L2\): read failed: boom"):
        camera.capture()


def test_timeout_is_honoured_when_the_backend_blocks():
    gate = threading.Event()
    images = [np.full((ROWS, COLS), v, np.uint8) for v in (1, 2)]
    fake = FakeCapture(images, block=gate)
    camera = OpenCVCamera("/dev/video7", capture=fake, timeout_s=0.3)
    try:
        start = time.monotonic()
        with pytest.raises(CameraTimeout, match=r"camera '/dev/video7' \(V4L2\): no frame within 0.3 s"):
            camera.capture()
        assert time.monotonic() - start < 0.3 + 0.5
        start = time.monotonic()
        message = "a read left over from an earlier timeout still blocks after 0.2 s"
        with pytest.raises(CameraTimeout, match=message):
            camera.capture(timeout=0.2)
        assert time.monotonic() - start < 0.2 + 0.5
    finally:
        gate.set()
    frame = camera.capture()  # the stale frame 1 is discarded
    assert frame.image[0, 0] == 2 and frame.frame_id == 0
    camera.close()
    assert fake.released
    with pytest.raises(CameraError, match="camera '/dev/video7' is closed"):
        camera.capture()


def test_close_waits_for_a_blocked_read_at_most_timeout_s():
    gate = threading.Event()
    fake = FakeCapture([], block=gate)
    camera = OpenCVCamera("cam0", capture=fake, timeout_s=0.2)
    with pytest.raises(CameraTimeout):
        camera.capture()
    start = time.monotonic()
    camera.close()
    assert 0.15 < time.monotonic() - start < 0.7
    assert fake.released
    gate.set()
