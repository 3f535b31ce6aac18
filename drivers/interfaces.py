"""Hardware interfaces shared by real drivers and fakes: stage, pattern display, camera.

Units: millimetres for positions, seconds for times, milliseconds for exposure.
Images follow OpenCV conventions: ``(rows, cols)`` arrays, row 0 at the top.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field

import numpy as np

from drivers.errors import DeviceError

__all__ = ["Camera", "DeviceError", "Frame", "PatternDisplay", "ShownFrame", "Stage"]


class Stage(abc.ABC):
    """A single-axis motorised translation stage, positions in millimetres."""

    @abc.abstractmethod
    def home(self) -> None:
        """Drive to the home reference and wait until the stage reports it is homed."""

    @abc.abstractmethod
    def move_to(self, z_mm: float, timeout: float | None = None) -> float:
        """Move to ``z_mm`` and wait until done; return the measured position (mm)."""

    @property
    @abc.abstractmethod
    def position_mm(self) -> float:
        """Measured position (mm), valid while moving."""

    @property
    @abc.abstractmethod
    def limits_mm(self) -> tuple[float, float]:
        """Allowed travel (low, high) in mm: the tighter of the device's and the configured limits."""

    @property
    @abc.abstractmethod
    def is_homed(self) -> bool:
        """True when the stage has a valid reference position."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Decelerate to a stop now."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the port; idempotent."""

    def describe(self) -> dict:
        """Identity and settings to record in run metadata (device id, firmware, limits)."""
        return {"type": type(self).__name__}

    def __enter__(self) -> "Stage":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass(frozen=True)
class ShownFrame:
    """What a display reports after a pattern went on screen."""

    index: int  # running count of show() calls on this display, from 0
    swap_time: float  # time.monotonic() just after swap + finish, seconds
    frame_code: int | None = None  # value encoded in the corner frame code, if drawn


class PatternDisplay(abc.ABC):
    """A display that shows 8-bit patterns 1:1, one LCD pixel per image pixel."""

    @property
    @abc.abstractmethod
    def size(self) -> tuple[int, int]:
        """(width, height) in display pixels."""

    @abc.abstractmethod
    def show(self, image: np.ndarray, frame_code: int | None = None) -> ShownFrame:
        """Show ``image`` ((height, width) or (height, width, 3) uint8), through the inverse
        response LUT; draw ``frame_code`` in the corner when given; return after it is on screen."""

    @abc.abstractmethod
    def set_lut(self, lut: np.ndarray | None) -> None:
        """Set the inverse response lookup table (256 uint8 values); None for identity."""

    @abc.abstractmethod
    def close(self) -> None:
        """Close the window or context; idempotent."""

    def __enter__(self) -> "PatternDisplay":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass(frozen=True)
class Frame:
    """One captured camera frame."""

    image: np.ndarray  # (rows, cols) uint8 or uint16, in the camera's bit depth
    timestamp: float  # seconds, time.monotonic() at capture unless the camera provides better
    exposure_ms: float
    frame_id: int  # the camera's running frame counter
    meta: dict = field(default_factory=dict)  # anything else the device reports


class Camera(abc.ABC):
    """A monochrome camera."""

    @abc.abstractmethod
    def capture(self, timeout: float | None = None) -> Frame:
        """Capture one frame within ``timeout`` seconds (the camera's default when None)."""

    @property
    @abc.abstractmethod
    def exposure_ms(self) -> float:
        """Exposure time in ms."""

    @exposure_ms.setter
    @abc.abstractmethod
    def exposure_ms(self, value: float) -> None: ...

    @property
    @abc.abstractmethod
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""

    @property
    @abc.abstractmethod
    def bit_depth(self) -> int:
        """Bits per pixel of the delivered frames (8, 10, 12 or 16)."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the device; idempotent."""

    def __enter__(self) -> "Camera":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
