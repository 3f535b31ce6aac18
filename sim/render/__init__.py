"""Rendering of fringe images: patterns, scenes, Embree tracing and images.

Public names are re-exported lazily: ``import sim.render`` loads no submodule (no embreex, no
numba) until a name is used.
"""

from sim._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "fringe_patterns": "PatternDescriptor PhaseShiftSet GrayCodeSet",
    "pattern_stack": "PatternStack",
    "board": "CalibrationBoard PlacedBoard apply_boards",
    "scene": "Pose SphereObject BallBarObject PlaneObject MeshObject BoardObject Scene "
             "ThinLensSpec "
             "MeasuredLensSpec SceneFile LoadedScene load_scene_file",
    "trace": "TraceGeometry Transport trace_camera camera_rays normalized_grid",
    "images": "ProjectorResponse CameraResponse RenderSettings CameraImages RenderResult "
              "project_patterns gather gather_into camera_response render render_camera "
              "render_views",
    "image_files": "write_png write_pngs write_zarr",
})
