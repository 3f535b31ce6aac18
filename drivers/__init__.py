"""Hardware interfaces and real device drivers: stage, pattern display, camera.

Submodules are imported on demand (``drivers.display`` needs an OpenGL stack); the
interfaces and the errors are re-exported here. Every hardware error derives from
:class:`DeviceError`; each driver logs every exchange with its device (commands and replies,
display swaps, captures, feature writes) at DEBUG level on its module's logger
(``logging.getLogger("drivers.stage")``, ...).
"""

from drivers.errors import (
    CameraError,
    CameraTimeout,
    DeviceError,
    DeviceSettingError,
    DisplayError,
)
from drivers.interfaces import Camera, Frame, PatternDisplay, ShownFrame, Stage
from drivers.stage_errors import StageError

__all__ = ["Camera", "CameraError", "CameraTimeout", "DeviceError", "DeviceSettingError",
           "DisplayError", "Frame", "PatternDisplay", "ShownFrame", "Stage", "StageError"]
