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

from typing import TYPE_CHECKING

from sim._lazy import lazy_exports

_EXPORTS = {
    "Scanner": "scanner",
    "Rig": "optics.rig",
    "DeviceCalibration": "optics.rig",
    "PinholeLens": "optics.lens",
    "GaussianLens": "optics.lens",
    "AberratedLens": "optics.lens",
    "LensModel": "optics.lens",
    "MeasuredLens": "optics.measured_lens",
    "load_lens": "optics.measured_lens",
    "save_lens": "optics.measured_lens",
    "Scene": "render.scene",
    "load_scene_file": "render.scene",
    "PhaseShiftSet": "render.fringe_patterns",
    "GrayCodeSet": "render.fringe_patterns",
    "RenderSettings": "render.images",
    "RenderResult": "render.images",
    "DecodeSettings": "fpp.decode",
    "scan": "fpp.decode",
    "PointCloud": "fpp.cloud",
    "read_ply": "fpp.cloud",
    "write_ply": "fpp.cloud",
    "load_scan_input": "fpp.scan_input",
    "fit_sphere": "metrology.spheres",
    "find_spheres": "metrology.spheres",
    "measure_ball_bar": "metrology.spheres",
    "compare_clouds": "metrology.compare",
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


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
