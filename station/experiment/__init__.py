"""The reference paper's experiment and the demo: station measurement of each camera's lens,
four virtual scanners (real, measured LTC, Gaussian, pinhole), spheres, ball bars and a CAD
part, comparisons and a report (``run``, ``report``); ``ltc demo`` (``demo``).

Public names are re-exported lazily (PEP 562): importing the package stays cheap.
"""

from __future__ import annotations

from sim._lazy import lazy_exports

_WHERE = {
    "ExperimentConfig": "run",
    "LensSpec": "run",
    "load_experiment_config": "run",
    "paper_size_config": "run",
    "run_experiment": "run",
    "demo_config": "demo",
    "run_demo": "demo",
}

__getattr__, __dir__ = lazy_exports(__name__, _WHERE, globals())
__all__ = sorted(_WHERE)
