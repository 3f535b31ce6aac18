"""The measured lens: centroids -> principal rays -> optical centre -> focus plane
(``geometry``) -> aperture samples -> lens model file (``derive``). Names load lazily."""

from __future__ import annotations

from sim._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "centroids": "Centroids WindowStats compute_centroids window_stats",
    "rays": "PrincipalRays RayFitError fit_principal_rays",
    "centre": "OpticalCentre intersect_rays pinhole_centre",
    "geometry": "LensFitConfig LensFitError LensGeometry fit_geometry",
    "derive": "derive_lens",
    "result": "LensResult LensSummary",
    "figures": "write_figures",
})
