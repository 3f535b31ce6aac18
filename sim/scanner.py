"""The virtual scanner as one object for scripts: a rig, one lens per camera, a pattern set.

    import sim

    scanner = sim.Scanner.from_scene_file("examples/sphere_scene.toml")
    images = scanner.render()                     # RenderResult: images + truth maps per camera
    cloud = scanner.scan(images)                  # PointCloud, stereo (camera=i: with projector)
    report = scanner.measure(cloud, sphere_mm=50.8007)   # SphereMeasurement, mm

    lens = sim.MeasuredLens.load("lens.npz")      # the station's measured lens
    measured = scanner.with_lenses([lens, lens])  # same rig, scene and patterns, other lenses

Each method is a thin composition of ``sim.render``, ``sim.fpp`` and ``sim.metrology``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from sim.errors import SimInputError
from sim.fpp.cloud import PointCloud
from sim.fpp.decode import DecodeSettings
from sim.fpp.decode import scan as _scan
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
    # the scene's Embree geometry once built (``geometry``), shared by ``with_lenses`` copies
    _geometry: TraceGeometry | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if len(self.lenses) != len(self.rig.cameras):
            raise SimInputError(f"{self.where}: {len(self.lenses)} lenses for "
                             f"{len(self.rig.cameras)} rig cameras; give one per camera")
        object.__setattr__(self, "lenses", tuple(self.lenses))
        from sim.optics.measured_lens import lens_camera_mismatch

        for i, (lens, cam) in enumerate(zip(self.lenses, self.rig.cameras, strict=True)):
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
        geom = self._geometry
        if geom is None:
            geom = self.scene.trace_geometry(where=self.where)
            object.__setattr__(self, "_geometry", geom)
        return geom

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
                reference: str | Path | PointCloud | None = None,
                align: bool = True) -> Measurement:
        """Measure a cloud: ``sphere_mm`` (nominal diameter; ``0``: the best-supported sphere of
        any size), ``ballbar_mm`` (ball diameter, nominal length or None), or ``reference`` (a
        CAD mesh file, or another cloud). Returns a ``SphereMeasurement``,
        ``BallBarMeasurement`` or ``DistanceMeasurement`` (lengths mm; ``.to_json()``)."""
        pts = cloud.points
        if sphere_mm is not None:
            return SphereMeasurement.from_json(_measure.measure_sphere(pts, sphere_mm or None)[0])
        if ballbar_mm is not None:
            return BallBarMeasurement.from_json(_measure.measure_ballbar(pts, *ballbar_mm)[0])
        if isinstance(reference, PointCloud):
            return DistanceMeasurement.from_json(
                _measure.measure_against_cloud(pts, reference, align)[0])
        if reference is not None:
            return DistanceMeasurement.from_json(
                _measure.measure_against_mesh(pts, reference, align)[0])
        raise SimInputError("measure: give sphere_mm, ballbar_mm or reference")


def _known(cls: type, data: dict[str, Any]) -> dict[str, Any]:
    names = {f.name for f in fields(cls)}
    return {k: v for k, v in data.items() if k in names}


def _present(d: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in d.items() if v is not None}


@dataclass(frozen=True)
class SphereMeasurement:
    """A sphere fitted to a cloud: centre (3,) and diameter mm, the fit's RMS and peak-to-valley
    residuals mm, the points it was fitted to and its inliers; ``diameter_error_mm`` against
    the nominal diameter when one was given."""

    centre_mm: list[float]
    diameter_mm: float
    fit_rms_mm: float
    fit_pv_mm: float
    points: int
    inliers: int
    diameter_error_mm: float | None = None

    def to_json(self) -> dict[str, Any]:
        """``ltc measure --sphere``'s JSON fields (``kind`` "sphere")."""
        return {"kind": "sphere", **_present(asdict(self))}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> SphereMeasurement:
        return cls(**_known(cls, data))


@dataclass(frozen=True)
class BallBarMeasurement:
    """A ball bar: the two balls' centre distance mm and their fits; ``length_error_mm``
    against the nominal length when one was given."""

    length_mm: float
    spheres: list[SphereMeasurement]
    length_error_mm: float | None = None

    def to_json(self) -> dict[str, Any]:
        """``ltc measure --ballbar``'s JSON fields (``kind`` "ballbar")."""
        out: dict[str, Any] = {"kind": "ballbar", "length_mm": self.length_mm,
                               "spheres": [_present(asdict(s)) for s in self.spheres]}
        if self.length_error_mm is not None:
            out["length_error_mm"] = self.length_error_mm
        return out

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> BallBarMeasurement:
        return cls(length_mm=data["length_mm"],
                   spheres=[SphereMeasurement.from_json(s) for s in data["spheres"]],
                   length_error_mm=data.get("length_error_mm"))


@dataclass(frozen=True)
class DistanceMeasurement:
    """Signed distances of a cloud's points to a CAD mesh (``kind`` "reference", positive
    outside) or to another cloud (``kind`` "against"): count, mean, RMSE, std, min and max
    mm; with ICP alignment its iterations and the transform applied (``R`` 3x3, ``t_mm``)."""

    kind: Literal["reference", "against"]
    points: int
    mean_mm: float
    rmse_mm: float
    std_mm: float
    min_mm: float
    max_mm: float
    reference: str | None = None
    icp_iterations: int | None = None
    R: list[list[float]] | None = None
    t_mm: list[float] | None = None

    def to_json(self) -> dict[str, Any]:
        """``ltc measure --reference`` / ``--against``'s JSON fields."""
        return _present(asdict(self))

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> DistanceMeasurement:
        return cls(**_known(cls, data))


Measurement = SphereMeasurement | BallBarMeasurement | DistanceMeasurement
