"""Acquisition: config, devices, patterns, the run store and the acquisition run.

Public names are re-exported lazily (PEP 562):
``from station.acquisition import StationConfig`` imports only the submodule
that defines it, so importing the package stays cheap. The function
``acquire`` is not re-exported: its name is the submodule's
(``from station.acquisition.acquire import acquire``).
"""

from __future__ import annotations

from sim._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "config": "ConfigError StationConfig parse_config load_config example_config example_text",
    "backend": "Hardware open_hardware load_lut",
    "patterns": "FourierPatternSet LocalisationPatternSet StationPatternPlan apply_lut "
                "shown_luminance",
    "run_store": "RunStore RunStoreError FrameMeta",
    "acquire": "AcquisitionError",
    "gamma": "GammaError measure_lut",
    "align": "AlignError run_align",
    "check": "run_check",
})
