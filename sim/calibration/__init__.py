"""Calibration of a fringe projection scanner (two cameras and a projector) from board images
and fringes: board files and feature detection, the capture layout, projector features from the
unwrapped phase, Zhang's method and one joint bundle adjustment, the report, and virtual
captures rendered by the virtual scanner.

Public names are re-exported lazily (no OpenCV work until a name is used)::

    import sim.calibration as cal
    result = cal.calibrate("capture/", "board.toml")
    result.rig.save("rig.yaml")
"""

from sim._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "errors": "CalibrationError",
    "board": "load_board detect Features",
    "capture": "CalibrationPatterns Capture load_patterns",
    "projector": "projector_features local_homography sample",
    "calibrator": "calibrate CalibrationResult PoseResiduals",
    "report": "write_report",
    "virtual": "calibration_rig default_poses render_capture RenderedCapture",
})
