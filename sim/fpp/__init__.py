"""Fringe projection profilometry: phase, unwrapping, decoding, stereo and point clouds.

Public names are re-exported lazily: ``import sim.fpp`` loads no submodule until a name is
used.
"""

from sim._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "phase": "WrappedPhase wrapped_phase quality_mask unwrap_with_reference unwrap_hierarchical "
             "unwrap_heterodyne unwrap_gray_code absolute_phase_to_projector fringe_order_error "
             "gray_to_index gray_bits beat",
    "decode": "DecodeSettings DecodedView decode_view scan",
    "scan_input": "ScanInputError load_scan_input",
    "rectify": "Rectification stereo_rectification relative_pose",
    "match": "local_phase_model phase_noise_px",
    "triangulation": "triangulate grid_normals camera_projector_cloud",
    "stereo": "stereo_cloud",
    "cloud": "PointCloud read_ply write_ply",
})
