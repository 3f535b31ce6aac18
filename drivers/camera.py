"""Camera over OpenCV ``cv2.VideoCapture``: device index, file path, image sequence or URL.

Frames are converted to monochrome (uint8 or uint16, as delivered). Every capture has a
deadline: the read runs in a daemon worker thread and the caller stops waiting at the deadline,
so a backend that blocks cannot hang the station.

Exposure and auto-exposure use backend-specific units (from the OpenCV backends' sources):
V4L2 exposure is in 100 us steps with auto-exposure 1 = manual; DirectShow and Media
Foundation take log2(seconds) with 0.25 = manual. Other backends get no exposure settings.
Gain is passed through in the backend's units. :meth:`OpenCVCamera.describe` reports which
settings the backend accepted.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from concurrent import futures
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from typing import Any, Callable

import cv2
import numpy as np

from drivers.errors import CameraError, CameraTimeout, DeviceSettingError
from drivers.interfaces import Camera, Frame

__all__ = ["Camera", "CameraError", "CameraTimeout", "Frame", "OpenCVCamera", "VideoDevice",
           "list_video_devices"]

log = logging.getLogger(__name__)

SYSFS_VIDEO = "/sys/class/video4linux"


@dataclass(frozen=True)
class _ExposureUnits:
    """How one backend spells exposure: ms -> device value, and the manual auto-exposure value."""

    to_device: Callable[[float], float]
    from_device: Callable[[float], float]
    auto_off: float


_EXPOSURE_UNITS = {
    "V4L2": _ExposureUnits(lambda ms: ms * 10.0, lambda v: v / 10.0, 1.0),
    "DSHOW": _ExposureUnits(lambda ms: math.log2(ms / 1000.0), lambda v: 1000.0 * 2.0**v, 0.25),
    "MSMF": _ExposureUnits(lambda ms: math.log2(ms / 1000.0), lambda v: 1000.0 * 2.0**v, 0.25),
}


def _api(backend: int | str | None) -> tuple[int, str]:
    """OpenCV API preference and its name, from ``cv2.CAP_*`` value or name ('V4L2', 'FFMPEG')."""
    if backend is None:
        return cv2.CAP_ANY, "CAP_ANY"
    if isinstance(backend, str):
        name = "CAP_" + backend.upper().removeprefix("CAP_")
        if not hasattr(cv2, name):
            raise CameraError(f"unknown OpenCV backend {backend!r} (no cv2.{name})")
        return getattr(cv2, name), name
    return int(backend), f"backend {int(backend)}"


def _to_mono(image: np.ndarray, source: str) -> np.ndarray:
    """(rows, cols) uint8/uint16 from what the backend delivered (gray, BGR or BGRA)."""
    if image.dtype not in (np.uint8, np.uint16):
        raise CameraError(f"camera {source}: unsupported frame dtype {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    elif image.ndim == 3 and image.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        image = cv2.cvtColor(image, code)
    if image.ndim != 2:
        raise CameraError(f"camera {source}: unsupported frame shape {image.shape}")
    return image


@dataclass(frozen=True)
class VideoDevice:
    """A Linux video device (V4L2) that OpenCV can open by its index."""

    index: int  # the N of /dev/videoN: OpenCV's device index (source = N)
    path: str  # /dev/videoN
    name: str  # the driver's card name, e.g. 'Integrated Camera: Integrated C'


def list_video_devices(sysfs: str | os.PathLike | None = None) -> list[VideoDevice]:
    """V4L2 devices from sysfs (``SYSFS_VIDEO`` when None), by index, without opening any
    (cheap; [] off Linux). A webcam often has a second node for metadata that OpenCV cannot
    read: try the lowest index first."""
    sysfs = SYSFS_VIDEO if sysfs is None else sysfs
    found = []
    try:
        entries = os.listdir(sysfs)
    except OSError:
        return []
    for entry in entries:
        if not (entry.startswith("video") and entry[5:].isdigit()):
            continue
        try:
            with open(os.path.join(sysfs, entry, "name"), encoding="utf-8", errors="replace") as f:
                name = f.read().strip()
        except OSError:
            name = ""
        found.append(VideoDevice(int(entry[5:]), f"/dev/{entry}", name))
    return sorted(found, key=lambda d: d.index)


def _read_into(capture: Any, future: Future) -> None:
    """Worker: one ``capture.read()``; its result or exception goes to ``future``."""
    try:
        ok, image = capture.read()
    except Exception as exc:  # handed to the caller's thread and re-raised there
        future.set_exception(exc)
        return
    future.set_result((ok, image, time.monotonic()))


class OpenCVCamera(Camera):
    """A camera behind ``cv2.VideoCapture``.

    Parameters
    ----------
    source : int, str or path
        Device index, video file, image sequence pattern (``img_%03d.png``) or stream URL.
    exposure_ms : float, optional
        Exposure to set (ms); auto-exposure is turned off first. Where the backend refuses or
        its units are unknown, nothing is set and :meth:`describe` says so.
    gain : float, optional
        Gain in the backend's units.
    timeout_s : float
        Default capture deadline, seconds.
    backend : int or str, optional
        OpenCV API preference (``cv2.CAP_V4L2`` or ``"V4L2"``); any backend when None.
    capture : object, optional
        An already opened object with ``VideoCapture``'s methods, used instead of opening
        ``source`` (for tests and special sources).
    """

    def __init__(self, source: int | str | os.PathLike, *, exposure_ms: float | None = None,
                 gain: float | None = None, timeout_s: float = 2.0, backend: int | str | None = None,
                 capture: Any = None) -> None:
        self._source = os.fspath(source) if isinstance(source, os.PathLike) else source
        self._name = repr(self._source)
        if exposure_ms is not None:
            self._check_exposure(exposure_ms)
        api, api_name = _api(backend)
        self._cap = cv2.VideoCapture(self._source, api) if capture is None else capture
        if not self._cap.isOpened():
            raise CameraError(f"cannot open camera {self._name} with OpenCV {api_name}")
        self._backend = self._cap.getBackendName()
        self._units = _EXPOSURE_UNITS.get(self._backend)
        self.timeout_s = timeout_s
        self._frame_id = 0
        self._pending: Future | None = None
        self._exposure_ms = math.nan
        self._dtype: np.dtype | None = None
        self._size = (int(self._cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
                      int(self._cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        self._accepted: dict[str, bool] = {}
        self._closed = False
        if exposure_ms is not None:
            self._set_exposure(exposure_ms)
        if gain is not None:
            self._accepted["gain"] = bool(self._cap.set(cv2.CAP_PROP_GAIN, float(gain)))

    def _check_exposure(self, exposure_ms: float) -> None:
        if not exposure_ms > 0:
            raise DeviceSettingError(f"camera {self._name}: exposure must be > 0 ms, "
                                     f"got {exposure_ms}")

    def _set_exposure(self, exposure_ms: float) -> bool:
        """Turn auto-exposure off and set the exposure; True when the backend accepted both."""
        self._check_exposure(exposure_ms)
        if self._units is None:
            self._accepted["auto_exposure_off"] = self._accepted["exposure"] = False
            return False
        auto_off = bool(self._cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, self._units.auto_off))
        accepted = bool(self._cap.set(cv2.CAP_PROP_EXPOSURE, self._units.to_device(exposure_ms)))
        self._accepted["auto_exposure_off"], self._accepted["exposure"] = auto_off, accepted
        if accepted:
            self._exposure_ms = self._units.from_device(self._cap.get(cv2.CAP_PROP_EXPOSURE))
        log.debug("camera %s: exposure %g ms set (auto-exposure off accepted: %s, exposure "
                  "accepted: %s, read back %g ms)", self._name, exposure_ms, auto_off, accepted,
                  self._exposure_ms)
        return auto_off and accepted

    @property
    def exposure_ms(self) -> float:
        """Exposure (ms) as read back from the backend after setting it; NaN when never set."""
        return self._exposure_ms

    @exposure_ms.setter
    def exposure_ms(self, value: float) -> None:
        if not self._set_exposure(value):
            raise CameraError(
                f"camera {self._name} ({self._backend}) refused exposure {value} ms: "
                f"accepted {self._accepted}"
            )

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels: as the backend reports it, then as frames arrive."""
        return self._size

    @property
    def bit_depth(self) -> int:
        """Bits per pixel of the delivered frames: 16 for uint16 frames, else 8 (also before the
        first frame, as OpenCV delivers 8 bits unless a backend is told otherwise)."""
        return 16 if self._dtype == np.uint16 else 8

    def describe(self) -> dict:
        """Source, backend, size and which settings the backend accepted, for run metadata."""
        return {
            "type": type(self).__name__,
            "source": self._source,
            "backend": self._backend,
            "size": self._size,
            "exposure_ms": self._exposure_ms,
            "accepted": dict(self._accepted),
        }

    def capture(self, timeout: float | None = None) -> Frame:
        """One frame within ``timeout`` seconds (``timeout_s`` when None).

        A read still blocked from an earlier timed-out capture is waited for first (within the
        same deadline) and its frame discarded as stale.
        """
        if self._closed:
            raise CameraError(f"camera {self._name} is closed")
        timeout = self.timeout_s if timeout is None else timeout
        deadline = time.monotonic() + timeout
        if self._pending is not None:
            self._wait(self._pending, deadline, f"a read left over from an earlier timeout still "
                       f"blocks after {timeout:g} s")
            self._pending = None
        future: Future = Future()
        self._pending = future
        threading.Thread(target=_read_into, args=(self._cap, future), daemon=True,
                         name=f"camera read {self._name}").start()
        ok, image, stamp = self._wait(future, deadline, f"no frame within {timeout:g} s")
        self._pending = None
        if not ok or image is None:
            raise CameraError(
                f"camera {self._name} ({self._backend}) delivered no frame after {self._frame_id} "
                "frames: end of stream or device failure"
            )
        image = _to_mono(np.asarray(image), self._name)
        self._dtype = image.dtype
        self._size = (image.shape[1], image.shape[0])
        frame = Frame(image=image, timestamp=stamp, exposure_ms=self._exposure_ms,
                      frame_id=self._frame_id, meta={"backend": self._backend})
        log.debug("camera %s: frame %d captured (%d x %d %s)", self._name, self._frame_id,
                  image.shape[1], image.shape[0], image.dtype)
        self._frame_id += 1
        return frame

    def _wait(self, future: Future, deadline: float, problem: str) -> Any:
        """The read's result by ``deadline``; :class:`CameraTimeout` saying ``problem`` if late."""
        try:
            return future.result(timeout=max(0.0, deadline - time.monotonic()))
        except FutureTimeout:
            raise CameraTimeout(f"camera {self._name} ({self._backend}): {problem}") from None
        except cv2.error as exc:
            raise CameraError(f"camera {self._name} ({self._backend}): read failed: {exc}") from exc

    def close(self) -> None:
        """Release the capture; idempotent. A read still blocked in the worker gets ``timeout_s``
        to finish first (releasing under a running read is unsafe in some backends)."""
        if not self._closed:
            self._closed = True
            if self._pending is not None:
                futures.wait([self._pending], timeout=self.timeout_s)
            self._cap.release()
