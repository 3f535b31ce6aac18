"""The reference paper's experiment and the demo: station measurement of each camera's lens,
four virtual scanners (real, measured LTC, Gaussian, pinhole), spheres, ball bars and a CAD
part, comparisons and a report (``run``, ``report``); ``ltc demo`` (``demo``)."""

from __future__ import annotations

from sim._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "config": "ExperimentConfig LensSpec load_experiment_config paper_size_config",
    "rows": "DistanceStats ModelNumbers PoseValidation PositionRow",
    "run": "run_experiment",
    "demo": "demo_config run_demo",
})
