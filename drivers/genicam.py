"""GenICam cameras (GigE Vision, USB3 Vision) through Aravis 0.8 and PyGObject.

Two acquisition modes: ``trigger="software"`` (default; :meth:`GenICamCamera.capture` fires
``TriggerSoftware`` and waits for that one frame: one frame per displayed pattern), a hardware
trigger line (``trigger="Line0"``: capture waits for the frame the line triggers), and
``trigger=None`` (free run: capture returns the stream's next frame, in order; :meth:`flush`
discards frames queued so far).

Every frame is checked: an Aravis buffer whose status is not ``SUCCESS`` (missing packets,
timeout, size mismatch...) raises :class:`CameraFrameError`, a gap in the device's frame ids
raises :class:`CameraFrameDropped`, no frame by the deadline raises
:class:`~drivers.errors.CameraTimeout`, and a camera that stopped answering raises
:class:`CameraLost`. A bad frame is never returned. Frames carry the device's frame id and
timestamp (seconds on the device's clock; the host's ``time.monotonic()`` at arrival is in
``meta``). Frame images are read-only views of the copy PyGObject makes of each buffer.

Control calls (settings, trigger, stop) run on one worker thread and are waited for with a
deadline, because Aravis retries an unanswered GigE Vision command for about 2.5 s and leaving
a vanished camera's control channel takes about 5 s: the caller gets its error on time and the
release finishes in the background.

Units: exposure in ms (the device's ``ExposureTime``/``ExposureTimeAbs`` is in us), gain in the
device's units (``Gain`` in dB, or ``GainRaw``), timeouts in seconds, ROI in pixels.

Needs Debian's ``gir1.2-aravis-0.8`` and PyGObject (the ``genicam`` extra; see
``scripts/setup.sh``).
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import logging
import threading
import time
from typing import Any, Callable, TypeVar

import numpy as np

from drivers.aravis import (
    PROBE_TIMEOUT_S,
    CameraInfo,
    _aravis,
    _glib_error,
    _gvcp_answers,
    list_cameras,
)
from drivers.errors import (
    AravisUnavailable,
    CameraError,
    CameraFrameDropped,
    CameraFrameError,
    CameraLost,
    CameraNotFound,
    CameraSettingError,
    CameraTimeout,
    DeviceSettingError,
)
from drivers.interfaces import Camera, Frame

__all__ = [
    "AravisUnavailable", "CameraFrameDropped", "CameraFrameError", "CameraInfo", "CameraLost",
    "CameraNotFound", "CameraSettingError", "GenICamCamera", "PIXEL_FORMATS", "list_cameras",
]

log = logging.getLogger(__name__)

T = TypeVar("T")

# Mono formats we deliver: GenICam name -> (numpy dtype, bits per pixel in the frame).
PIXEL_FORMATS: dict[str, tuple[np.dtype, int]] = {
    "Mono8": (np.dtype(np.uint8), 8),
    "Mono10": (np.dtype("<u2"), 10),
    "Mono12": (np.dtype("<u2"), 12),
    "Mono16": (np.dtype("<u2"), 16),
}


class GenICamCamera(Camera):
    """A GenICam camera through Aravis.

    Parameters
    ----------
    device_id : str, optional
        Aravis device id (``Vendor-Model-Serial``, as :func:`list_cameras` reports it), or the
        camera's IP address. Exactly one of ``device_id`` and ``serial`` is given.
    serial : str, optional
        Serial number; resolved through :func:`list_cameras`.
    exposure_ms, gain : float, optional
        Set on opening (auto exposure and auto gain are turned off where the camera has them).
    pixel_format : str
        ``Mono8``, ``Mono10``, ``Mono12`` or ``Mono16`` (unpacked).
    roi : (x, y, width, height), optional
        Region of interest in sensor pixels; the whole sensor when None.
    trigger : str or None
        ``"software"`` (default), a ``TriggerSource`` line name such as ``"Line0"``, or None for
        free run.
    frame_rate_hz : float, optional
        Free-run frame rate, where the camera has ``AcquisitionFrameRate``.
    timeout_s : float
        Default capture deadline, seconds.
    control_timeout_s : float
        Deadline for one control call (a setting, trigger or stop), seconds.
    n_buffers : int
        Stream buffers pushed once when acquisition starts and re-queued after each copy.
    """

    def __init__(self, device_id: str | None = None, *, serial: str | None = None,
                 exposure_ms: float | None = None, gain: float | None = None,
                 pixel_format: str = "Mono8", roi: tuple[int, int, int, int] | None = None,
                 trigger: str | None = "software", frame_rate_hz: float | None = None,
                 timeout_s: float = 2.0, control_timeout_s: float = 3.0,
                 n_buffers: int = 8) -> None:
        if (device_id is None) == (serial is None):
            raise DeviceSettingError("GenICamCamera: give exactly one of device_id and serial")
        self._arv = _aravis()
        self._gerror = _glib_error()
        self.timeout_s = timeout_s
        self.control_timeout_s = control_timeout_s
        self.n_buffers = n_buffers
        self._name = repr(device_id) if serial is None else f"serial {serial!r}"
        self._closed = False
        self._lost = False
        self._camera: Any = None
        self._stream: Any = None
        self._acquiring = False
        self._last_id: int | None = None
        self._executor = cf.ThreadPoolExecutor(max_workers=1, thread_name_prefix="genicam")
        self._lost_event = threading.Event()
        try:
            if serial is not None:
                device_id = self._resolve_serial(serial)
            try:
                self._camera = self._arv.Camera.new(device_id)
            except self._gerror as exc:
                raise CameraNotFound(f"camera {self._name}: cannot open: {exc.message}") from None
            self._device = self._camera.get_device()
            self._device_id = device_id
            self._serial = self._camera.get_device_serial_number() or ""
            self._name = f"{self._camera.get_vendor_name()} {self._camera.get_model_name()} " \
                         f"{self._serial!r}"
            self._address = ""
            if self._camera.is_gv_device():
                self._address = self._device.get_device_address().get_address().to_string()
            self._device.connect("control-lost", lambda *_: self._lost_event.set())
            self._configure(exposure_ms, gain, pixel_format, roi, trigger, frame_rate_hz)
        except BaseException:
            self.close()
            raise

    # -- opening and settings -------------------------------------------------------------

    def _resolve_serial(self, serial: str) -> str:
        cameras = list_cameras()
        for info in cameras:
            if info.serial == serial:
                return info.device_id
        seen = ", ".join(f"{c.device_id} (serial {c.serial!r})" for c in cameras) or "none"
        raise CameraNotFound(f"no camera with serial {serial!r}; found: {seen}")

    def _configure(self, exposure_ms: float | None, gain: float | None, pixel_format: str,
                   roi: tuple[int, int, int, int] | None, trigger: str | None,
                   frame_rate_hz: float | None) -> None:
        cam = self._camera
        if cam.is_exposure_auto_available():
            self._control(lambda: cam.set_exposure_time_auto(self._arv.Auto.OFF), "ExposureAuto Off")
        if cam.is_gain_auto_available():
            self._control(lambda: cam.set_gain_auto(self._arv.Auto.OFF), "GainAuto Off")
        self._control(lambda: cam.set_acquisition_mode(self._arv.AcquisitionMode.CONTINUOUS),
                      "AcquisitionMode Continuous")
        self.pixel_format = pixel_format
        if roi is not None:
            self.roi = roi
        if frame_rate_hz is not None:  # before the trigger: Aravis turns triggers off here
            self._control(lambda: cam.set_frame_rate(frame_rate_hz),
                          f"AcquisitionFrameRate {frame_rate_hz} Hz")
        self.trigger = trigger
        self._frame_exposure_ms = self.exposure_ms
        if exposure_ms is not None:
            self.exposure_ms = exposure_ms
        if gain is not None:
            self.gain = gain

    @property
    def name(self) -> str:
        """Vendor, model and serial number, as used in error messages."""
        return self._name

    @property
    def exposure_ms(self) -> float:
        """Exposure (ms), read back from the device."""
        return self._control(self._camera.get_exposure_time, "read exposure") / 1000.0

    @exposure_ms.setter
    def exposure_ms(self, value: float) -> None:
        low, high = self._control(self._camera.get_exposure_time_bounds, "read exposure bounds")
        if not low <= value * 1000.0 <= high:
            raise CameraSettingError(
                f"camera {self._name}: exposure {value} ms is outside the device's "
                f"{low / 1000.0:g}..{high / 1000.0:g} ms")
        self._control(lambda: self._camera.set_exposure_time(value * 1000.0),
                      f"set exposure {value} ms")
        self._frame_exposure_ms = self.exposure_ms

    @property
    def gain(self) -> float:
        """Gain in the device's units (``Gain``, usually dB, else ``GainRaw``)."""
        return self._control(self._camera.get_gain, "read gain")

    @gain.setter
    def gain(self, value: float) -> None:
        low, high = self._control(self._camera.get_gain_bounds, "read gain bounds")
        if not low <= value <= high:
            raise CameraSettingError(
                f"camera {self._name}: gain {value} is outside the device's {low:g}..{high:g}")
        self._control(lambda: self._camera.set_gain(value), f"set gain {value}")

    @property
    def pixel_format(self) -> str:
        """GenICam pixel format name (``Mono8``, ``Mono12``, ...)."""
        return self._format

    @pixel_format.setter
    def pixel_format(self, value: str) -> None:
        if value not in PIXEL_FORMATS:
            raise CameraSettingError(
                f"camera {self._name}: pixel format {value!r} is not supported by this driver "
                f"(supported: {', '.join(PIXEL_FORMATS)})")
        available = self._control(self._camera.dup_available_pixel_formats_as_strings,
                                  "read PixelFormat entries")
        if value not in available:
            raise CameraSettingError(
                f"camera {self._name}: pixel format {value!r} is not offered by the device "
                f"(it offers: {', '.join(available)})")
        with self._stopped():
            self._control(lambda: self._camera.set_pixel_format_from_string(value),
                          f"set PixelFormat {value}")
            got = self._control(self._camera.get_pixel_format_as_string, "read PixelFormat")
            if got != value:
                raise CameraSettingError(
                    f"camera {self._name}: pixel format {value!r} set, device reports {got!r}")
            self._format = value
            self._dtype, self._bits = PIXEL_FORMATS[value]

    @property
    def bit_depth(self) -> int:
        """Bits per pixel of the delivered frames (8, 10, 12 or 16)."""
        return self._bits

    @property
    def roi(self) -> tuple[int, int, int, int]:
        """Region of interest (x, y, width, height) in sensor pixels, read back from the device."""
        r = self._control(self._camera.get_region, "read region")
        return (r.x, r.y, r.width, r.height)

    @roi.setter
    def roi(self, value: tuple[int, int, int, int]) -> None:
        x, y, width, height = (int(v) for v in value)
        cam = self._camera

        def limits() -> tuple:
            return (cam.get_sensor_size(), cam.get_x_offset_bounds(), cam.get_y_offset_bounds(),
                    cam.get_width_bounds(), cam.get_height_bounds(),
                    cam.get_x_offset_increment(), cam.get_y_offset_increment(),
                    cam.get_width_increment(), cam.get_height_increment())

        sensor, xb, yb, wb, hb, xinc, yinc, winc, hinc = self._control(limits, "read ROI limits")
        problems = []
        for label, v, (lo, hi), inc in (("width", width, wb, winc), ("height", height, hb, hinc)):
            if not lo <= v <= hi:
                problems.append(f"{label} {v} outside {lo}..{hi}")
            elif (v - lo) % max(inc, 1):
                problems.append(f"{label} {v} not {lo} + a multiple of {inc}")
        for label, v, lo, inc in (("x", x, xb[0], xinc), ("y", y, yb[0], yinc)):
            if v < lo:
                problems.append(f"{label} {v} below {lo}")
            elif (v - lo) % max(inc, 1):
                problems.append(f"{label} {v} not {lo} + a multiple of {inc}")
        if x + width > sensor[0] or y + height > sensor[1]:
            problems.append(f"region ends at ({x + width}, {y + height}), beyond the "
                            f"{sensor[0]} x {sensor[1]} sensor")
        if problems:
            raise CameraSettingError(f"camera {self._name}: ROI {(x, y, width, height)} refused: "
                                     + "; ".join(problems))
        with self._stopped():
            self._control(lambda: cam.set_region(x, y, width, height),
                          f"set region {(x, y, width, height)}")
            got = self.roi
            if got != (x, y, width, height):
                raise CameraSettingError(f"camera {self._name}: ROI {(x, y, width, height)} set, "
                                         f"device reports {got}")

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the delivered frames, in pixels."""
        _, _, width, height = self.roi
        return (width, height)

    @property
    def trigger(self) -> str | None:
        """``"software"``, a hardware line name, or None (free run)."""
        return self._trigger

    @trigger.setter
    def trigger(self, value: str | None) -> None:
        cam = self._camera
        with self._stopped():
            if value is None:
                self._control(cam.clear_triggers, "TriggerMode Off")
            else:
                source = "Software" if value == "software" else value
                sources = self._control(
                    lambda: self._device.dup_available_enumeration_feature_values_as_strings(
                        "TriggerSource"), "read TriggerSource entries")
                if source not in sources:
                    raise CameraSettingError(
                        f"camera {self._name}: trigger source {value!r} is not offered by the "
                        f"device (it offers: {', '.join(sources)})")
                self._control(lambda: cam.set_trigger(source), f"trigger on {source}")
            self._trigger = value

    def describe(self) -> dict:
        """Identity and settings, for run metadata."""
        return {
            "type": type(self).__name__, "name": self._name, "serial": self._serial,
            "device_id": self._device_id, "address": self._address,
            "pixel_format": self._format, "bit_depth": self._bits, "roi": self.roi,
            "exposure_ms": self.exposure_ms, "gain": self.gain, "trigger": self._trigger,
        }

    # -- acquisition ----------------------------------------------------------------------

    def start(self) -> None:
        """Create the stream, push ``n_buffers`` buffers and start acquisition (capture does this
        on its first call)."""
        self._check_open()
        if self._acquiring:
            return
        payload = self._control(self._camera.get_payload, "read PayloadSize")
        stream = self._control(lambda: self._camera.create_stream(None, None), "create stream")
        if stream is None:
            raise CameraError(f"camera {self._name}: Aravis created no stream")
        self._stream = stream
        for _ in range(self.n_buffers):
            stream.push_buffer(self._arv.Buffer.new_allocate(payload))
        self._last_id = None
        self._control(self._camera.start_acquisition, "AcquisitionStart")
        self._acquiring = True

    def stop(self) -> None:
        """Stop acquisition and release the stream and its buffers."""
        if self._acquiring and not self._lost:
            self._acquiring = False
            self._control(self._camera.stop_acquisition, "AcquisitionStop")
        self._acquiring = False
        self._stream = None

    @contextlib.contextmanager
    def _stopped(self):
        """Acquisition stopped for a setting that changes the payload; restarted afterwards."""
        was = self._acquiring
        self.stop()
        yield
        if was:
            self.start()

    def flush(self) -> int:
        """Discard frames already queued (free run: the next capture is a fresh frame); returns
        how many were discarded."""
        self._check_open()
        n = 0
        if self._stream is not None:
            while (buffer := self._stream.try_pop_buffer()) is not None:
                self._stream.push_buffer(buffer)
                n += 1
        self._last_id = None
        return n

    def capture(self, timeout: float | None = None) -> Frame:
        """One frame within ``timeout`` seconds (``timeout_s`` when None). In software-trigger
        mode, fires the trigger and returns the frame it produced; frames queued before the
        trigger (late arrivals from an earlier timeout) are discarded."""
        self._check_open()
        timeout = self.timeout_s if timeout is None else timeout
        deadline = time.monotonic() + timeout
        try:
            if not self._acquiring:
                self.start()
            if self._trigger == "software":
                self.flush()
                self._control(self._camera.software_trigger, "TriggerSoftware", deadline)
            return self._next_frame(deadline, timeout)
        except (CameraError, CameraTimeout):
            if self._lost:
                self.close()  # nothing more can come from a vanished camera
            raise

    def _next_frame(self, deadline: float, timeout: float) -> Frame:
        while True:
            remaining_us = int((deadline - time.monotonic()) * 1e6)
            buffer = self._stream.timeout_pop_buffer(max(remaining_us, 0)) \
                if remaining_us > 0 else self._stream.try_pop_buffer()
            if buffer is None:
                self._raise_no_frame(f"no frame within {timeout:g} s")
            arrived = time.monotonic()
            try:
                frame = self._to_frame(buffer, arrived)
                log.debug("camera %s: frame %d captured (%d x %d %s)", self._name,
                          frame.frame_id, frame.image.shape[1], frame.image.shape[0],
                          self._format)
                return frame
            finally:
                self._stream.push_buffer(buffer)

    def _to_frame(self, buffer: Any, arrived: float) -> Frame:
        status = buffer.get_status()
        frame_id = int(buffer.get_frame_id())
        if status != self._arv.BufferStatus.SUCCESS:
            name = status.value_nick.upper().replace("-", "_")
            raise CameraFrameError(
                f"camera {self._name}: frame {frame_id} arrived with buffer status {name}",
                name, frame_id)
        last, self._last_id = self._last_id, frame_id
        if last is not None and not (frame_id == last + 1 or (last == 0xFFFF and frame_id == 1)):
            expected = 1 if last == 0xFFFF else last + 1
            raise CameraFrameDropped(
                f"camera {self._name}: frame id {frame_id} after {last}: frames "
                f"{expected}..{frame_id - 1} were lost", expected, frame_id)
        width, height = buffer.get_image_width(), buffer.get_image_height()
        data = buffer.get_image_data()
        if len(data) != width * height * self._dtype.itemsize:
            raise CameraFrameError(
                f"camera {self._name}: frame {frame_id} has {len(data)} bytes for {width} x "
                f"{height} {self._format}", "SIZE_MISMATCH", frame_id)
        # a read-only view of the one copy PyGObject made (copy it to modify it in place)
        image = np.frombuffer(data, self._dtype).reshape(height, width)
        if image.dtype.byteorder not in ("=", "|") and not image.dtype.isnative:
            image = image.astype(image.dtype.newbyteorder("="))
        return Frame(image=image, timestamp=buffer.get_timestamp() * 1e-9,
                     exposure_ms=self._frame_exposure_ms, frame_id=frame_id,
                     meta={"host_time": arrived,
                           "system_timestamp_ns": int(buffer.get_system_timestamp())})

    def _raise_no_frame(self, problem: str) -> None:
        if self._check_alive():
            raise CameraTimeout(f"camera {self._name}: {problem}")
        raise CameraLost(f"camera {self._name}: {problem}, and the camera no longer answers "
                         f"at {self._address or 'its address'}")

    def _check_alive(self) -> bool:
        """False (and the camera marked lost) when it stopped answering."""
        alive = not self._lost_event.is_set()
        if alive and self._address:
            alive = _gvcp_answers(self._address, PROBE_TIMEOUT_S)
        if not alive:
            self._lost = True
        return alive

    # -- control calls with deadlines -----------------------------------------------------

    def _control(self, call: Callable[[], T], what: str, deadline: float | None = None) -> T:
        """Run one Aravis control ``call`` on the worker thread, waiting until ``deadline``
        (``control_timeout_s`` from now when None). Aravis errors become :class:`CameraError`."""
        if self._lost:
            raise CameraLost(f"camera {self._name}: {what}: the camera was lost earlier")
        if deadline is None:
            deadline = time.monotonic() + self.control_timeout_s
        log.debug("camera %s: %s", self._name, what)
        future = self._executor.submit(call)
        try:
            return future.result(timeout=max(0.0, deadline - time.monotonic()))
        except cf.TimeoutError:
            self._raise_no_frame(f"{what} not acknowledged in time")
        except self._gerror as exc:
            if not self._check_alive():
                raise CameraLost(f"camera {self._name}: {what} failed ({exc.message}); the "
                                 "camera no longer answers") from None
            raise CameraSettingError(f"camera {self._name}: {what} failed: {exc.message}") \
                from None
        raise AssertionError("unreachable")

    def _check_open(self) -> None:
        if self._closed:
            raise CameraError(f"camera {self._name} is closed")

    def close(self) -> None:
        """Stop acquisition and release stream and device; idempotent. For a lost camera the
        release (Aravis waits for the vanished device) finishes on the worker thread."""
        if self._closed:
            return
        self._closed = True
        if self._acquiring and not self._lost:
            with contextlib.suppress(CameraError, CameraTimeout):
                self._control(self._camera.stop_acquisition, "AcquisitionStop")
        self._acquiring = False
        held = [self._stream, self._camera]
        self._stream = self._camera = self._device = None
        # the last references go on the worker, which then exits: a live camera is released at
        # once, a lost one after Aravis's own retries, without holding up the caller
        self._executor.submit(held.clear)
        self._executor.shutdown(wait=not self._lost)

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.close()
