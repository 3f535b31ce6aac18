"""The station's Python API for lab scripts: one import, the whole measurement.

    import station

    config = station.load_config("bench.toml")
    with station.open_bench(config) as bench:          # real or fake, as the config says
        bench.stage.home()
        bench.stage.move_to(120.0)                       # mm
        bench.display.show(pattern)                      # uint8 (H, W), the LCD's size
        frame = bench.camera.capture()                   # drivers.Frame
    station.acquire(config, "run.zarr")                  # resumable: resume=True
    station.reconstruct_ltc("run.zarr", "ltc.zarr")
    result = station.derive_lens("ltc.zarr")            # LensResult, recommended settings
    result.lens.save("lens.npz")                         # sim.MeasuredLens; .load() reads it
    station.run_sequence(config, "night/")               # check .. lens, unattended, resumable

Every function here is a thin composition of the stage packages (``station.acquisition``,
``station.ltc``, ``station.lens``); the ``ltc`` commands call these same functions.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from station.errors import StationInputError, UsageError

if TYPE_CHECKING:
    from drivers.interfaces import Camera, PatternDisplay, Stage
    from station.acquisition.config import StationConfig
    from station.lens.derive import LensResult
    from station.lens.geometry import LensFitConfig
    from station.ltc.verify import StoreReport


def load_config(path: str | Path) -> StationConfig:
    """Read and validate a station config (TOML); errors name the file and field."""
    from station.acquisition.config import load_config as _load

    return _load(path)


def _config(config: StationConfig | str | Path) -> StationConfig:
    return config if not isinstance(config, (str, Path)) else load_config(config)


@dataclass
class Bench:
    """The opened stage, display and camera of one station config; closes all on exit."""

    config: StationConfig
    stage: Stage
    display: PatternDisplay
    camera: Camera
    _stack: contextlib.ExitStack = field(repr=False)

    def close(self) -> None:
        """Close every device (idempotent); a failed close never hides another's."""
        self._stack.close()

    def __enter__(self) -> Bench:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_bench(config: StationConfig | str | Path, *, lut: np.ndarray | None = None) -> Bench:
    """Open the bench a config describes (``backend = "fake"`` or real devices).

    lut : the display's inverse response LUT (256 uint8); default: ``display.lut_path``.
    Use it as a context manager, or call ``close()``.
    """
    from station.acquisition.backend import open_hardware

    cfg = _config(config)
    stack = contextlib.ExitStack()
    try:
        hw = stack.enter_context(open_hardware(cfg, lut=lut))
    except BaseException:
        stack.close()
        raise
    return Bench(cfg, hw.stage, hw.display, hw.camera, stack)


def acquire(config: StationConfig | str | Path, out: str | Path, *, resume: bool = False,
            progress: bool = True, force: bool = False) -> dict:
    """Show every Fourier and localisation pattern at every depth, capture, and write each
    frame durably to the run store ``out`` (zarr). A killed run continues with
    ``resume=True`` (with ``force=True`` when the killed run's writer lock must be taken
    over). Returns a JSON-able summary (frames, retries, seconds)."""
    from station.acquisition.acquire import acquire as _acquire

    return _acquire(_config(config), out, resume=resume, progress=progress, force=force)


def reconstruct_ltc(run: str | Path, out: str | Path, *, tile_px: int | None = None,
                    progress: bool = True, resume: bool = False, workers: int | None = None,
                    dask: bool = False, scheduler: str | None = None) -> dict:
    """Every camera pixel's LTC at every depth of a complete run store, written to a new
    LTC store ``out`` (zarr), tile by tile in bounded memory. Returns a summary.

    resume : finish the store a killed reconstruction left (bit-identical result).
    workers : worker processes (default every core; 1: this process); dask : on a local
    Dask cluster of ``workers`` processes; scheduler : on an existing Dask cluster's
    address. Every choice gives the same store, bit for bit."""
    from station.ltc.tiles import reconstruct

    return reconstruct(run, out, tile_px=tile_px, progress=progress, resume=resume,
                       workers=workers, dask=dask, scheduler=scheduler)


def lens_config(**fields: Any) -> LensFitConfig:
    """A ``LensFitConfig`` with ``fields`` (by name) over the recommended defaults; an unknown
    or invalid field is refused by name (``UsageError``)."""
    from pydantic import ValidationError

    from sim.validation import format_validation_error
    from station.lens.geometry import LensFitConfig

    try:
        return LensFitConfig(**fields)
    except ValidationError as exc:
        raise UsageError(format_validation_error("lens settings", exc)) from exc


def derive_lens(ltc: str | Path, config: LensFitConfig | None = None, *,
                rig: str | Path | None = None, rig_camera: str | None = None,
                figures: str | Path | None = None, progress: bool = True,
                out: str | Path | None = None, workers: int | None = 1, dask: bool = False,
                scheduler: str | None = None) -> LensResult:
    """The measured lens of an LTC store: principal rays, optical centre, focus, and K
    aperture samples per node pixel. ``result.lens`` is a :class:`sim.MeasuredLens`
    (``save(path)`` / ``MeasuredLens.load(path)``); ``result.summary()`` reports it.

    config : the derivation's settings (default ``LensFitConfig()``: the recommended ones;
        ``lens_config(**fields)`` builds one with its fields checked by name).
    rig, rig_camera : a rig file (``sim.Rig``) giving the camera matrix K, used instead of
        the store's ``camera_matrix``; figures : a folder for the PNG figures.
    out : write the lens file there while the nodes are derived (memory does not grow with
        the sensor; ``result.lens`` is then None and ``result.lens_path`` the file).
    workers : processes (default 1: this process; None: every core); dask : on a local
        Dask cluster of ``workers`` processes; scheduler : an existing Dask cluster's
        address. Every choice gives the same lens, bit for bit.
    """
    import contextlib

    from sim.storage.lock import StoreLock
    from station.compute import Engine
    from station.lens.derive import derive_lens as _derive
    from station.lens.figures import write_figures
    from station.lens.geometry import LensFitConfig
    from station.ltc.store import open_ltc_volume

    cfg = config if config is not None else LensFitConfig()
    with contextlib.ExitStack() as held:
        if out is not None:  # one writer per lens file: a second is refused, naming this one
            held.enter_context(StoreLock.for_file(out))
        volume = open_ltc_volume(ltc)
        K, dist = _rig_camera(rig, rig_camera, volume.camera_size)
        with Engine(workers, dask=dask, scheduler=scheduler) as engine:
            result = _derive(volume, cfg, K, dist, progress=progress, engine=engine, out=out)
    if figures is not None:
        result.figures = write_figures(volume, result, figures)
    return result


def verify_store(path: str | Path) -> StoreReport:
    """Check a run store, an LTC store or a lens file for damage without changing it:
    every checksummed byte is read; the report names each damaged frame, chunk or member
    (``report.ok`` False when any is damaged)."""
    from station.ltc.verify import verify_store as _verify

    return _verify(path)


def _rig_camera(rig: str | Path | None, name: str | None,
                size: tuple[int, int]) -> tuple[np.ndarray | None, np.ndarray | None]:
    """K and distortion of camera ``name`` (default: the first) of a rig file, checked
    against the LTC store's camera size."""
    if rig is None:
        return None, None
    from sim.optics.rig import Rig

    r = Rig.load(rig)
    cams = {c.name: c for c in r.cameras}
    name = name or r.cameras[0].name
    if name not in cams:
        raise StationInputError(f"{rig}: no camera named {name!r}; cameras are {list(cams)}")
    if tuple(cams[name].size) != tuple(size):
        raise StationInputError(f"{rig}: camera {name!r} is {tuple(cams[name].size)} pixels but the "
                         f"LTC store's camera is {tuple(size)}")
    return cams[name].K_array, cams[name].dist_array
