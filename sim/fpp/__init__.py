"""Fringe projection profilometry: phase, unwrapping, decoding, stereo and point clouds.

Public names are re-exported lazily: ``import sim.fpp`` loads no submodule until a name is
used.
"""

from sim._lazy import lazy_exports

_EXPORTS = {
    **dict.fromkeys(("WrappedPhase", "wrapped_phase", "quality_mask", "unwrap_with_reference",
                     "unwrap_hierarchical", "unwrap_heterodyne", "unwrap_gray_code",
                     "absolute_phase_to_projector", "fringe_order_error", "gray_to_index",
                     "gray_bits", "beat"), "phase"),
    **dict.fromkeys(("DecodeSettings", "DecodedView", "decode_view", "scan"), "decode"),
    **dict.fromkeys(("ScanInputError", "load_scan_input"), "scan_input"),
    **dict.fromkeys(("PointCloud", "Rectification", "stereo_cloud", "camera_projector_cloud",
                     "stereo_rectification", "triangulate", "grid_normals", "relative_pose",
                     "local_phase_model", "phase_noise_px"),
                    "stereo"),
    **dict.fromkeys(("read_ply", "write_ply"), "cloud"),
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
