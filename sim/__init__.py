"""The virtual FPP scanner and the optical model it shares with the station.

Stages, earliest first: ``sim.optics`` (projection, lens models, the measured lens, rig,
sensor) -> ``sim.render`` (scene, Embree tracing, fringe patterns, rendering) -> ``sim.fpp``
(phase, unwrapping, stereo, triangulation, scanning) -> ``sim.metrology`` (spheres, ball
bars, cloud comparison) -> ``sim.scanner`` (the :class:`Scanner` facade). Names load lazily,
so ``import sim`` is cheap::

    import sim
    scanner = sim.Scanner.from_scene_file("examples/sphere_scene.toml")
    cloud = scanner.scan(scanner.render())
    print(scanner.measure(cloud, sphere_mm=50.8007))
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_EXPORTS = {
    "Scanner": "sim.scanner",
    "Rig": "sim.optics.rig",
    "DeviceCalibration": "sim.optics.rig",
    "PinholeLens": "sim.optics.lens",
    "GaussianLens": "sim.optics.lens",
    "AberratedLens": "sim.optics.lens",
    "LensModel": "sim.optics.lens",
    "MeasuredLens": "sim.optics.measured_lens",
    "load_lens": "sim.optics.measured_lens",
    "save_lens": "sim.optics.measured_lens",
    "Scene": "sim.render.scene",
    "load_scene_file": "sim.render.scene",
    "PhaseShiftSet": "sim.render.fringe_patterns",
    "GrayCodeSet": "sim.render.fringe_patterns",
    "RenderSettings": "sim.render.images",
    "RenderResult": "sim.render.images",
    "DecodeSettings": "sim.fpp.decode",
    "scan": "sim.fpp.decode",
    "PointCloud": "sim.fpp.cloud",
    "read_ply": "sim.fpp.cloud",
    "write_ply": "sim.fpp.cloud",
    "load_scan_input": "sim.fpp.scan_input",
    "fit_sphere": "sim.metrology.spheres",
    "find_spheres": "sim.metrology.spheres",
    "measure_ball_bar": "sim.metrology.spheres",
    "compare_clouds": "sim.metrology.compare",
}
__all__ = sorted(_EXPORTS)

if TYPE_CHECKING:
    from sim.fpp.cloud import PointCloud, read_ply, write_ply
    from sim.fpp.decode import DecodeSettings, scan
    from sim.fpp.scan_input import load_scan_input
    from sim.metrology.compare import compare_clouds
    from sim.metrology.spheres import find_spheres, fit_sphere, measure_ball_bar
    from sim.optics.lens import AberratedLens, GaussianLens, LensModel, PinholeLens
    from sim.optics.measured_lens import MeasuredLens, load_lens, save_lens
    from sim.optics.rig import DeviceCalibration, Rig
    from sim.render.fringe_patterns import GrayCodeSet, PhaseShiftSet
    from sim.render.images import RenderResult, RenderSettings
    from sim.render.scene import Scene, load_scene_file
    from sim.scanner import Scanner


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'sim' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
