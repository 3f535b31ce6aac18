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

Stages, earliest first: ``station.acquisition`` -> ``station.ltc`` -> ``station.lens``.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_EXPORTS = {
    "Bench": "station.api",
    "open_bench": "station.api",
    "load_config": "station.api",
    "acquire": "station.api",
    "reconstruct_ltc": "station.api",
    "derive_lens": "station.api",
    "run_sequence": "station.sequence",
    "StationConfig": "station.acquisition.config",
    "ConfigError": "station.acquisition.config",
    "LensResult": "station.lens.derive",
    "StationError": "station.errors",
    "UsageError": "station.errors",
}
__all__ = sorted(_EXPORTS)

if TYPE_CHECKING:
    from station.acquisition.config import ConfigError, StationConfig
    from station.api import Bench, acquire, derive_lens, load_config, open_bench, reconstruct_ltc
    from station.errors import StationError, UsageError
    from station.lens.derive import LensResult
    from station.sequence import run_sequence


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'station' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
