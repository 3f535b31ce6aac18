"""Hardware interfaces and real device drivers: stage, pattern display, camera.

Submodules are imported on demand (``drivers.display`` needs an OpenGL stack); the
interfaces are re-exported here.
"""

from drivers.interfaces import Camera, DeviceError, Frame, PatternDisplay, ShownFrame, Stage

__all__ = ["Camera", "DeviceError", "Frame", "PatternDisplay", "ShownFrame", "Stage"]
