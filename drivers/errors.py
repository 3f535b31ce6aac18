"""The hardware errors: :class:`DeviceError`, the root of every driver error, and the camera and
display errors every camera or display driver raises. The stage's are in
:mod:`drivers.stage_errors`.

Every message names the device (port, serial number, index) and what failed.
"""

from __future__ import annotations

__all__ = [
    "AravisUnavailable", "CameraError", "CameraFrameDropped", "CameraFrameError", "CameraLost",
    "CameraNotFound", "CameraSettingError", "CameraTimeout", "DeviceError", "DeviceSettingError",
    "DisplayError",
]


class DeviceError(RuntimeError):
    """Base class of every hardware error; the message names the device."""


class DeviceSettingError(DeviceError, ValueError):
    """A driver argument or setting outside what the driver or the device accepts; the message
    names the setting, the value and the range."""


class CameraError(DeviceError):
    """The camera could not be opened, refused a setting, or delivered no frame."""


class CameraTimeout(CameraError):
    """No frame arrived before the deadline."""


class AravisUnavailable(CameraError):
    """Aravis 0.8 or PyGObject is not installed; the message names the packages."""


class CameraNotFound(CameraError):
    """No camera with the requested id or serial number answered."""


class CameraSettingError(CameraError, ValueError):
    """The camera refused a setting, or the value is outside what the device allows."""


class CameraFrameError(CameraError):
    """A frame arrived incomplete or damaged (Aravis buffer status other than SUCCESS)."""

    def __init__(self, message: str, status: str = "", frame_id: int | None = None) -> None:
        super().__init__(message)
        self.status = status
        self.frame_id = frame_id


class CameraFrameDropped(CameraFrameError):
    """The device's frame ids skipped: frames were produced and lost."""

    def __init__(self, message: str, expected: int, got: int) -> None:
        super().__init__(message, "DROPPED", got)
        self.expected = expected


class CameraLost(CameraError):
    """The camera stopped answering (unplugged, powered off, or its control was lost)."""


class DisplayError(DeviceError):
    """The display could not be opened or used."""
