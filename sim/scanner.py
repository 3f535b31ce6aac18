"""The virtual scanner as one object for scripts: a rig, one lens per camera, a pattern set.

    import sim

    scanner = sim.Scanner.from_scene_file("examples/sphere_scene.toml")
    images = scanner.render()                     # RenderResult: images + truth maps per camera
    cloud = scanner.scan(images)                  # PointCloud, stereo (camera=i: with projector)
    report = scanner.measure(cloud, sphere_mm=50.8007)   # dict: diameter, fit RMS, error

    lens = sim.MeasuredLens.load("lens.npz")      # the station's measured lens
    measured = scanner.with_lenses([lens, lens])  # same rig, scene and patterns, other lenses

Each method is a thin composition of ``sim.render``, ``sim.fpp`` and ``sim.metrology``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from sim.errors import SimInputError
from sim.fpp.cloud import PointCloud
from sim.fpp.decode import DecodeSettings, scan as _scan
from sim.metrology import measure as _measure
from sim.optics.lens import LensModel
from sim.optics.rig import Rig
from sim.render.fringe_patterns import PatternSet
from sim.render.images import RenderResult, RenderSettings, render_views
from sim.render.scene import Scene, load_scene_file
from sim.render.trace import TraceGeometry


@dataclass(frozen=True)
class Scanner:
    """A virtual FPP scanner looking at a scene.

    rig : calibrated cameras and projector; lenses : one lens model per rig camera (pinhole,
    thin, Gaussian, aberrated or measured); patterns : what the projector shows; scene : the
    objects; render_settings : projector and camera response; decode : phase decoding
    settings; seed : camera noise seed.
    """

    rig: Rig
    lenses: tuple[LensModel, ...]
    patterns: PatternSet
    scene: Scene
    render_settings: RenderSettings = RenderSettings()
    decode: DecodeSettings = DecodeSettings()
    seed: int = 0
    where: str = "scanner"

    def __post_init__(self) -> None:
        if len(self.lenses) != len(self.rig.cameras):
            raise SimInputError(f"{self.where}: {len(self.lenses)} lenses for "
                             f"{len(self.rig.cameras)} rig cameras; give one per camera")
        object.__setattr__(self, "lenses", tuple(self.lenses))
        object.__setattr__(self, "_geometry", None)
        from sim.optics.measured_lens import lens_camera_mismatch

        for i, (lens, cam) in enumerate(zip(self.lenses, self.rig.cameras)):
            why = lens_camera_mismatch(lens, cam)
            if why is not None:
                raise SimInputError(f"{self.where}: camera {i}: {why}")

    @classmethod
    def from_scene_file(cls, path: str | Path) -> Scanner:
        """The scanner a scene file describes (rig, lenses, patterns, objects, response)."""
        loaded = load_scene_file(path)
        c = loaded.config
        s = cls(loaded.rig, tuple(loaded.lenses), c.patterns, loaded.scene, c.render,
                seed=c.seed, where=str(loaded.source))
        object.__setattr__(s, "_geometry", loaded.geometry)
        return s

    def with_lenses(self, lenses: Sequence[LensModel]) -> Scanner:
        """The same scanner and scene with other lenses (the traced geometry is shared); a
        measured lens must have been measured on its rig camera (same size, K and
        distortion: ``sim.optics.measured_lens.lens_camera_mismatch``), else ValueError."""
        s = replace(self, lenses=tuple(lenses))
        object.__setattr__(s, "_geometry", self._geometry)
        return s

    @property
    def geometry(self) -> TraceGeometry:
        """The scene's Embree geometry, built on first use."""
        if self._geometry is None:
            object.__setattr__(self, "_geometry", self.scene.trace_geometry(where=self.where))
        return self._geometry

    def render(self, progress: bool = False, rng: np.random.Generator | None = None) -> RenderResult:
        """Fringe images of the pattern set on every camera, with truth maps (noise from
        ``rng``, default a generator seeded with ``seed``)."""
        images = self.patterns.images(self.rig.projector.size)
        rng = np.random.default_rng(self.seed) if rng is None else rng
        return render_views(self.geometry, self.rig, list(self.lenses), images,
                            self.render_settings, rng, progress=progress, where=self.where)

    def scan(self, images: RenderResult | Sequence[np.ndarray], camera: int | None = None,
             decode: DecodeSettings | None = None) -> PointCloud:
        """Point cloud (world frame, mm) from the cameras' image stacks (n, H, W) or a
        ``RenderResult``: stereo by default, ``camera=i`` against the projector."""
        if isinstance(images, RenderResult):
            images = [c.images for c in images.cameras]
        return _scan(list(images), self.patterns, self.rig, decode or self.decode, camera=camera)

    @staticmethod
    def measure(cloud: PointCloud, *, sphere_mm: float | None = None,
                ballbar_mm: tuple[float, float | None] | None = None,
                reference: str | Path | PointCloud | None = None, align: bool = True) -> dict:
        """Measure a cloud: ``sphere_mm`` (nominal diameter; ``0``: the best-supported sphere of
        any size), ``ballbar_mm`` (ball diameter, nominal length or None), or ``reference`` (a
        CAD mesh file, or another cloud). Returns the JSON-able report (lengths mm)."""
        pts = cloud.points
        if sphere_mm is not None:
            return _measure.measure_sphere(pts, sphere_mm or None)[0]
        if ballbar_mm is not None:
            return _measure.measure_ballbar(pts, *ballbar_mm)[0]
        if isinstance(reference, PointCloud):
            return _measure.measure_against_cloud(pts, reference, align)[0]
        if reference is not None:
            return _measure.measure_against_mesh(pts, reference, align)[0]
        raise SimInputError("measure: give sphere_mm, ballbar_mm or reference")
