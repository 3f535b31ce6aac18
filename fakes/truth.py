"""Ground truth of a fake-bench run, for benchmarks and tests (never for the station itself).

A run's stored config (the run store's and the LTC store's ``config`` attribute) names the
fake bench it was taken on; the truth is that bench's optical centre and focus distance.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fakes.bench import FakeBench
from fakes.hardware import parse_fake_settings


def lens_truth(config: dict[str, Any]) -> dict[str, Any] | None:
    """The true lens of a fake-bench run from its stored config; None for a real bench.

    Returns ``optical_centre_mm`` (3,) station frame, mm, and ``focus_distance_mm`` (the
    bench's paraxial focus distance from the optical centre, mm).
    """
    if config.get("backend") != "fake" or config.get("fake", {}).get("model") == "synthetic":
        return None  # a real bench, or the synthetic one (its truth: per-pixel moments)
    bench = FakeBench(parse_fake_settings(config.get("fake", {})).bench_config())
    return {"optical_centre_mm": bench.optical_centre_station_mm().tolist(),
            "focus_distance_mm": bench.config.focus_distance_mm}


def optical_centre_error(summary: dict[str, Any], truth: dict[str, Any]) -> dict[str, Any]:
    """Measured minus true optical centre: ``optical_centre_error_mm`` (3,) and its norm
    ``optical_centre_error_norm_mm``, mm. summary : ``LensResult.summary()`` (or the ``ltc
    lens --json`` report); truth : from :func:`lens_truth`."""
    err = np.subtract(summary["optical_centre_mm"], truth["optical_centre_mm"])
    return {"optical_centre_error_mm": err.tolist(),
            "optical_centre_error_norm_mm": float(np.linalg.norm(err))}
