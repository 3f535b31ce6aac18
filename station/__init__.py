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
    station.generate_dataset("dataset.toml", "fringes.zarr", 1000)   # ltc dataset

Stages, earliest first: ``station.acquisition`` -> ``station.ltc`` -> ``station.lens``.
"""

from __future__ import annotations

from sim._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "api": "Bench open_bench load_config acquire reconstruct_ltc derive_lens lens_config verify_store",
    "sequence": "run_sequence SequenceSummary StepRecord",
    "experiment.run": "ExperimentConfig load_experiment_config run_experiment",
    "experiment.demo": "run_demo",
    "acquisition.config": "StationConfig ConfigError",
    "lens.derive": "LensResult",
    "lens.geometry": "LensFitConfig",
    "errors": "StationError StationInputError UsageError",
    "dataset": "DatasetReport generate_dataset",
})
