"""The virtual FPP scanner and the optical model it shares with the station.

Stages, earliest first: ``sim.optics`` (projection, lens models, the measured lens, rig,
sensor) -> ``sim.render`` (scene, Embree tracing, fringe patterns, rendering) -> ``sim.fpp``
(phase, unwrapping, stereo, triangulation, scanning) -> ``sim.metrology`` (spheres, ball
bars, cloud comparison) -> ``sim.scanner`` (the :class:`Scanner` facade). Every error raised
on purpose derives from :class:`SimError` (``sim.errors``). Names load lazily, so ``import sim``
is cheap::

    import sim
    scanner = sim.Scanner.from_scene_file("examples/sphere_scene.toml")
    cloud = scanner.scan(scanner.render())
    print(scanner.measure(cloud, sphere_mm=50.8007))
"""

from __future__ import annotations

from sim._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "errors": "SimError SimInputError",
    "scanner": "Scanner SphereMeasurement BallBarMeasurement DistanceMeasurement",
    "optics.rig": "Rig DeviceCalibration",
    "optics.lens": "PinholeLens GaussianLens AberratedLens LensModel",
    "optics.measured_lens": "MeasuredLens",
    "optics.lens_file": "load_lens save_lens",
    "optics.lens_moments": "gaussian_equivalent",
    "render.scene": "Scene load_scene_file",
    "render.fringe_patterns": "PhaseShiftSet GrayCodeSet",
    "render.images": "RenderSettings RenderResult",
    "fpp.decode": "DecodeSettings scan",
    "fpp.cloud": "PointCloud read_ply write_ply",
    "fpp.scan_input": "load_scan_input",
    "metrology.spheres": "fit_sphere find_spheres measure_ball_bar",
    "metrology.compare": "compare_clouds",
    "calibration.calibrator": "calibrate CalibrationResult",
    "calibration.errors": "CalibrationError",
})
