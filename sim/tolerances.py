"""Numeric tolerances of the ``sim`` package, in one place (values, units and what each guards).

Modules import them from here; the names they had in those modules still resolve there. The
compiled kernels (``sim.render.trace_kernels``) keep their few literals: numba's on-disk cache
does not notice edits to another module.
"""

from __future__ import annotations

ROTATION_TOL = 1e-6
"""|R R^T - I| (elementwise, dimensionless) allowed of a rotation matrix in a rig or scene pose."""

LOOK_AT_PARALLEL_TOL = 1e-9
"""|y x z| (dimensionless) below which ``look_at``'s optical axis counts as parallel to world y."""

WEIGHT_SUM_TOL = 1e-6
"""|sum of a measured lens's ray weights - 1| allowed per pixel (dimensionless)."""

SHADOW_OFFSET_MM = 1e-3
"""Shadow rays start this far (mm) off the surface, along its normal."""

PROJECTOR_GUARD = 1.2
"""Projector distortion is trusted up to this multiple of the image's largest normalised radius."""

VERTEX_NORMAL_SAME_TOL = 1e-9
"""Vertex normals of a face within this (per component, unit vectors) count as one: a flat face."""

PATTERN_RANGE_TOL = 1e-12
"""Slack (pattern value, [0, 1]) of the check that a phase-shift set's A +- B stays in [0, 1]."""

EDGE_MARGIN_PX = 0.5
"""Decoded projector coordinates this close (px) to the outer pixel centres are dropped."""

STEREO_STEP = 1e-6
"""Finite-difference step (spline parameter, dimensionless) of the stereo cubic inversion."""

MODEL_RESIDUAL_FLOOR_PX = 0.01
"""Stereo: local phase models fitting better than this (RMS, projector px) are always used,
however small the camera's median residual (noise-free renders, flat backdrops)."""

ICP_RCOND = 1e-3
"""ICP: singular values below this fraction of the largest count as unconstrained."""

QUADRIC_RIDGE = 1e-12
"""Ridge (mm^4 scale of the normal equations) added to local quadric fits of a reference cloud."""

BALL_QUERY_SLACK_MM = 1e-9
"""Slack (mm) on the ball radius of the nearest-triangle candidate query."""

SPHERE_REJECT_FLOOR_MM = 1e-12
"""Smallest residual band (mm) of sphere-fit outlier rejection (noise-free data keeps all)."""

SPHERE_DEGENERATE_REL = 1e-9
"""Point quadruples whose determinant is below this fraction of (largest entry)^3 are flat."""
