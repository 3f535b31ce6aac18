"""Metrology of point clouds: spheres and ball bars, cloud-to-cloud comparison and ICP.

Public names are re-exported lazily: ``import sim.metrology`` loads no submodule until a name
is used.
"""

from sim._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "spheres": "SphereFit BallBar fit_sphere fit_sphere_algebraic find_spheres "
               "find_sphere_unknown sphere_shell measure_ball_bar",
    "compare": "RigidTransform CloudComparison icp compare_clouds estimate_normals "
               "signed_distance_to_cloud mesh_signed_distance distance_colormap_png "
               "PixelComparison compare_by_pixel",
})
