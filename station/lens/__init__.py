"""The measured lens: centroids -> principal rays -> optical centre -> focus plane
(``geometry``) -> aperture samples -> lens model file (``derive``).

Public names are re-exported lazily (PEP 562):
``from station.lens import derive_lens`` imports only the submodule
that defines it, so importing the package stays cheap.
"""

from __future__ import annotations

from sim._lazy import lazy_exports


_WHERE = {
    "Centroids": "centroids",
    "WindowStats": "centroids",
    "compute_centroids": "centroids",
    "window_stats": "centroids",
    "PrincipalRays": "rays",
    "RayFitError": "rays",
    "fit_principal_rays": "rays",
    "OpticalCentre": "centre",
    "intersect_rays": "centre",
    "pinhole_centre": "centre",
    "LensFitConfig": "geometry",
    "LensFitError": "geometry",
    "LensGeometry": "geometry",
    "fit_geometry": "geometry",
    "LensResult": "derive",
    "derive_lens": "derive",
    "write_figures": "figures",
}

__all__ = sorted(_WHERE)


__getattr__, __dir__ = lazy_exports(__name__, _WHERE, globals())
