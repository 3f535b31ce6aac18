"""Optics of the virtual scanner: projection, lens models, measured lenses, rigs, sensor.

Public names are re-exported lazily: ``import sim.optics`` loads no submodule (no numba) until
a name is used.
"""

from sim._lazy import lazy_exports

_EXPORTS = {
    **dict.fromkeys(("RayBundle", "LensModel", "PinholeLens", "AberratedLens", "GaussianLens",
                     "sunflower_disk", "hit_plane"), "lens"),
    **dict.fromkeys(("MeasuredLens", "LensFileError", "save_lens", "load_lens"), "measured_lens"),
    "subpixel_offsets": "plane_ltc",  # (plane_ltc itself: a name of its submodule too)
    **dict.fromkeys(("pixel_to_normalized", "normalized_to_pixel", "project_points",
                     "camera_to_world", "directions_to_world"), "projection"),
    **dict.fromkeys(("DeviceCalibration", "Rig", "look_at", "default_rig", "small_rig",
                     "format_validation_error"), "rig"),
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
