"""Optics of the virtual scanner: projection, lens models, measured lenses, rigs, sensor.

Public names are re-exported lazily: ``import sim.optics`` loads no submodule (no numba) until
a name is used.
"""

from sim._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "lens": "RayBundle LensModel PinholeLens AberratedLens GaussianLens sunflower_disk hit_plane",
    "measured_lens": "MeasuredLens LensFileError",
    "lens_file": "save_lens load_lens load_lens_for LensFileWriter read_lens_nodes",
    "lens_moments": "centre_moments gaussian_equivalent smoothed_lens sample_moments sym_sqrtm "
                    "match_moments",
    "plane_ltc": "subpixel_offsets",
    "projection": "pixel_to_normalized normalized_to_pixel project_points camera_to_world "
                  "directions_to_world",
    "rig": "DeviceCalibration Rig look_at default_rig small_rig format_validation_error",
    "sensor": "Sensor",
})
