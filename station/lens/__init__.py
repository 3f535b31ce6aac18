"""The measured lens: centroids -> principal rays -> optical centre -> focus plane
(``geometry``) -> aperture samples -> lens model file (``derive``).

Public names are re-exported lazily (PEP 562):
``from station.lens import derive_lens`` imports only the submodule
that defines it, so importing the package stays cheap.
"""

from __future__ import annotations

import importlib
from typing import Any

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


def __getattr__(name: str) -> Any:
    """Import ``name`` from its submodule on first use (then cached in this module)."""
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
