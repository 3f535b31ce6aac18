"""The calibration's error: bad input refused with one line naming the pose and camera."""

from __future__ import annotations

from sim.errors import SimInputError


class CalibrationError(SimInputError):
    """A calibration capture or board cannot give a trustworthy rig; the message is one line
    that names the pose and camera (or device) and what to do."""
