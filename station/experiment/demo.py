"""``ltc demo``: the project's main job on the default fake benches, at a size that finishes in
minutes on 2 cores: per camera bench check, acquisition, LTC reconstruction and lens; then the
experiment (four scanners, spheres, ball bars, the CAD part) and its report."""

from __future__ import annotations

import datetime as _dt
import time
from pathlib import Path
from typing import Any

from station.experiment.run import ExperimentConfig, Log, run_experiment


def demo_config(**overrides: Any) -> ExperimentConfig:
    """The demo's experiment: the built-in defaults (``ExperimentConfig()``)."""
    return ExperimentConfig(**overrides)


def default_out() -> Path:
    """A new folder ``out/demo-<time>`` under the current directory."""
    return Path("out") / f"demo-{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}"


def run_demo(out: str | Path | None = None, *, config: ExperimentConfig | None = None,
             progress: bool = True, log: Log = print) -> dict[str, Any]:
    """Run the demo into ``out`` (default: ``default_out()``); returns the experiment's
    results with ``seconds.demo`` (wall clock)."""
    t0 = time.perf_counter()
    out = Path(out) if out is not None else default_out()
    log(f"ltc demo: the whole chain into {out}")
    results = run_experiment(config or demo_config(), out, progress=progress, log=log)
    results["seconds"]["demo"] = time.perf_counter() - t0
    return results
