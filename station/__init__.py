"""LTC measurement station: configs, benches, acquisition runs, LTC reconstruction, lens
derivation, the unattended sequence, and the ``ltc`` command line.

The Python API for lab scripts (``station.api``, ``station.sequence``; names load lazily, so
``import station`` is cheap)::

    import station
    config = station.load_config("bench.toml")
    with station.open_bench(config) as bench:
        bench.stage.move_to(120.0)
    station.acquire(config, "run.zarr")
    station.reconstruct_ltc("run.zarr", "ltc.zarr")
    station.derive_lens("ltc.zarr").lens.save("lens.npz")
    station.run_sequence(config, "night/")
    station.run_experiment(station.ExperimentConfig(), "exp/")   # the paper's experiment
    station.run_demo()                                          # ltc demo

Stages, earliest first: ``station.acquisition`` -> ``station.ltc`` -> ``station.lens``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from sim._lazy import lazy_exports

_EXPORTS = {
    "Bench": "api",
    "open_bench": "api",
    "load_config": "api",
    "acquire": "api",
    "reconstruct_ltc": "api",
    "derive_lens": "api",
    "run_sequence": "sequence",
    "ExperimentConfig": "experiment.run",
    "load_experiment_config": "experiment.run",
    "run_experiment": "experiment.run",
    "run_demo": "experiment.demo",
    "StationConfig": "acquisition.config",
    "ConfigError": "acquisition.config",
    "LensResult": "lens.derive",
    "StationError": "errors",
    "UsageError": "errors",
}
__all__ = sorted(_EXPORTS)

if TYPE_CHECKING:
    from station.acquisition.config import ConfigError, StationConfig
    from station.api import Bench, acquire, derive_lens, load_config, open_bench, reconstruct_ltc
    from station.errors import StationError, UsageError
    from station.lens.derive import LensResult
    from station.experiment.demo import run_demo
    from station.experiment.run import ExperimentConfig, load_experiment_config, run_experiment
    from station.sequence import run_sequence


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
