"""The fake LCD panel: a real pattern display (usually ``OffscreenDisplay``) whose drawn
framebuffer is turned into emitted luminance by the panel's response curve.

Fault switch: ``repeat_previous`` makes the next ``show()`` leave the previous image (and its
frame code) on screen while reporting success, as a display that misses a refresh does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from drivers.interfaces import PatternDisplay, ShownFrame


class PanelResponse(BaseModel):
    """Emitted luminance of a grey level g in [0, 255]: ``black + (1 - black) (g/255)^gamma``."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    gamma: float = Field(1.0, gt=0, description="display gamma (1: linear, 2.2: uncorrected)")
    black_level: float = Field(0.0, ge=0, lt=1, description="luminance of grey 0, fraction of white")

    def luminance(self, grey: np.ndarray) -> np.ndarray:
        """Relative luminance (same shape, float32 in [0, 1]) of uint8 grey levels."""
        g = np.asarray(grey, dtype=np.float32) / 255.0
        return (self.black_level + (1.0 - self.black_level) * g**self.gamma).astype(np.float32)


@dataclass
class LcdFaults:
    """Switches a test sets at any time."""

    repeat_previous: int = 0  # the next n show() calls leave the previous image on screen


class FakeLCD(PatternDisplay):
    """A ``PatternDisplay`` that remembers what is physically on screen as luminance."""

    def __init__(self, display: PatternDisplay, response: PanelResponse | None = None) -> None:
        if not hasattr(display, "read_back"):
            raise TypeError(
                f"FakeLCD needs a display with read_back(), got {type(display).__name__}"
            )
        self._display = display
        self.response = response or PanelResponse()
        self.faults = LcdFaults()
        w, h = display.size
        self._luminance = self.response.luminance(np.zeros((h, w), np.uint8))
        self._last: tuple[np.ndarray, int | None] | None = None
        self._count = 0

    @property
    def size(self) -> tuple[int, int]:
        return self._display.size

    def set_lut(self, lut: np.ndarray | None) -> None:
        self._display.set_lut(lut)

    def show(self, image: np.ndarray, frame_code: int | None = None) -> ShownFrame:
        """Show ``image``; under a fault, keep the previous one but report this one."""
        request = (np.asarray(image), frame_code)
        if self.faults.repeat_previous > 0 and self._last is not None:
            self.faults.repeat_previous -= 1
            request = self._last
        shown = self._display.show(request[0], frame_code=request[1])
        self._last = request
        self._luminance = self.response.luminance(self._display.read_back()[..., 0])
        index, self._count = self._count, self._count + 1
        return ShownFrame(index=index, swap_time=shown.swap_time, frame_code=frame_code)

    def luminance(self) -> np.ndarray:
        """Relative luminance now on screen, (height, width) float32 in [0, 1]."""
        return self._luminance

    def close(self) -> None:
        self._display.close()
