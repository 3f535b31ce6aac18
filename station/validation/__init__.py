"""Validating a twin against a real scanner's scans: the real-scan folder (``folder``),
locating the artefact and refining its pose by analysis by synthesis (``locate``), the twins
and the camera response (``twin``), the comparisons (``compare``), the run and its report
(``run``, ``report``); ``ltc validate``."""

from __future__ import annotations

from sim._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "folder": "RealScanError ScanFile ResponseSpec PositionFile SphereArtefact BallBarArtefact "
              "CadArtefact Pose RealScan RealPosition load_real_scan write_position "
              "write_scan_file",
    "locate": "ArtefactFit locate fit_near refine_pose Refinement",
    "twin": "build_twins estimate_response Response",
    "compare": "TwinComparison ImageStats compare_twin",
    "run": "validate validate_position ValidationResult PositionResult",
})
