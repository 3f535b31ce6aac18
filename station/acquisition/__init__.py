"""Acquisition: config, devices, patterns, the run store and the acquisition run.

Public names are re-exported lazily (PEP 562):
``from station.acquisition import StationConfig`` imports only the submodule
that defines it, so importing the package stays cheap. The function
``acquire`` is not re-exported: its name is the submodule's
(``from station.acquisition.acquire import acquire``).
"""

from __future__ import annotations

from sim._lazy import lazy_exports


_WHERE = {
    "ConfigError": "config",
    "StationConfig": "config",
    "parse_config": "config",
    "load_config": "config",
    "example_config": "config",
    "example_text": "config",
    "Hardware": "backend",
    "open_hardware": "backend",
    "load_lut": "backend",
    "FourierPatternSet": "patterns",
    "LocalisationPatternSet": "patterns",
    "StationPatternPlan": "patterns",
    "apply_lut": "patterns",
    "shown_luminance": "patterns",
    "RunStore": "run_store",
    "RunStoreError": "run_store",
    "FrameMeta": "run_store",
    "AcquisitionError": "acquire",
    "GammaError": "gamma",
    "measure_lut": "gamma",
    "AlignError": "align",
    "run_align": "align",
    "run_check": "check",
}

__all__ = sorted(_WHERE)


__getattr__, __dir__ = lazy_exports(__name__, _WHERE, globals())
