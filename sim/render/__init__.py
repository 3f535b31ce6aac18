"""Rendering of fringe images: patterns, scenes, Embree tracing and images.

Public names are re-exported lazily: ``import sim.render`` loads no submodule (no embreex, no
numba) until a name is used.
"""

from sim._lazy import lazy_exports

_EXPORTS = {
    **dict.fromkeys(("PatternDescriptor", "PhaseShiftSet", "GrayCodeSet"), "fringe_patterns"),
    "PatternStack": "pattern_stack",
    **dict.fromkeys(("Pose", "SphereObject", "BallBarObject", "PlaneObject", "MeshObject", "Scene",
                     "ThinLensSpec", "MeasuredLensSpec", "SceneFile", "LoadedScene",
                     "load_scene_file"), "scene"),
    **dict.fromkeys(("TraceGeometry", "Transport", "trace_camera", "camera_rays",
                     "normalized_grid"), "trace"),
    **dict.fromkeys(("ProjectorResponse", "CameraResponse", "RenderSettings", "CameraImages",
                     "RenderResult", "project_patterns", "gather", "gather_into",
                     "camera_response", "render", "render_camera", "render_views", "write_png",
                     "write_pngs", "write_zarr"), "images"),
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
