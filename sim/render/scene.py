"""Scene objects (meshes and exact artefacts), the scene file, and loading a scene to render.

Objects carry a pose ``X_world = R X_object + t`` (mm) and a diffuse albedo. Built-in artefacts
keep their exact geometry for ground truth: a sphere (``SphereObject``, centre ``pose.t``), a
ball bar (two spheres at ``(+-L/2, 0, 0)`` of the object frame) and a plane (``z = 0`` of the
object frame, centred). Spheres are traced as icospheres whose hits are moved onto the exact
sphere (``sim.render.trace``), so depth and normals carry no tessellation error; only silhouettes and
shadow edges move, by at most the chord error (sagitta) ``< 0.3 R / 4^subdivisions`` (1.8 um for
the 50.8 mm sphere at the default 6 subdivisions, 81920 triangles).

Scene file (TOML; paths relative to the file; example ``examples/sphere_scene.toml``)::

    rig = "rig.yaml"                 # sim.optics.rig file: OpenCV FileStorage YAML or JSON
    [[lenses]]                       # one per rig camera, in order; kind = pinhole | thin |
    kind = "pinhole"                 #   aberrated | gaussian | measured (path = lens file)
    [[objects]]                      # kind = sphere | ball_bar | plane | board (calibration
                                     #   board, sim.render.board) | mesh (path = PLY/STL/OBJ)
    kind = "sphere"
    pose = { t = [0.0, 0.0, 0.0] }
    [patterns]                       # sim.render.fringe_patterns: phase_shift | gray_code
    kind = "phase_shift"
    periods_px = [16.0]
    [render.projector]               # sim.render.images.ProjectorResponse
    [render.camera]                  # sim.render.images.CameraResponse
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import trimesh
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
)

from sim.errors import SimInputError
from sim.optics.lens import AberratedLens, GaussianLens, LensModel, PinholeLens
from sim.optics.rig import DeviceCalibration, Rig, _matrix
from sim.render.board import CalibrationBoard, PlacedBoard
from sim.render.fringe_patterns import PatternSet
from sim.render.images import RenderResult, RenderSettings, render_views, write_pngs, write_zarr
from sim.render.trace import TraceGeometry
from sim.storage.durable import durable_file
from sim.tolerances import ROTATION_TOL
from sim.validation import format_validation_error, read_toml

MESH_SUFFIXES = (".ply", ".stl", ".obj")


class Pose(BaseModel):
    """Rigid pose, object to world: ``X_world = R X_object + t``."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    R: list[list[float]] = Field([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]], description="3x3 rotation")
    t: list[float] = Field([0.0, 0.0, 0.0], description="translation, mm")

    @field_validator("R", mode="before")
    @classmethod
    def _rot(cls, v):
        R = np.asarray(_matrix(v, (3, 3), "R"))
        if not np.allclose(R @ R.T, np.eye(3), atol=ROTATION_TOL) or np.linalg.det(R) <= 0:
            raise SimInputError(f"R must be a proper rotation matrix, got {R.tolist()}")
        return R.tolist()

    @field_validator("t", mode="before")
    @classmethod
    def _t(cls, v):
        return _matrix(v, (3,), "t")

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Object points (n, 3) mm in world coordinates (n, 3)."""
        return np.asarray(points, dtype=np.float64) @ np.asarray(self.R).T + np.asarray(self.t)

    def rotate(self, vectors: np.ndarray) -> np.ndarray:
        return np.asarray(vectors, dtype=np.float64) @ np.asarray(self.R).T


class _Object(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    name: str = Field("", description="label for reports")
    albedo: float = Field(0.8, ge=0, le=1, description="diffuse reflectance")
    pose: Pose = Field(default_factory=Pose, description="object to world")


class SphereObject(_Object):
    """A sphere of exact diameter centred at ``pose.t``."""

    kind: Literal["sphere"] = "sphere"
    diameter_mm: float = Field(50.8007, gt=0, description="sphere diameter, mm")
    subdivisions: int = Field(6, ge=1, le=9, description="icosphere subdivisions (chord error above)")

    def spheres(self) -> np.ndarray:
        """Exact spheres (1, 4): world centre (mm) and radius (mm)."""
        return np.array([[*self.pose.t, self.diameter_mm / 2]])

    def _local(self) -> list[trimesh.Trimesh]:
        return [trimesh.creation.icosphere(self.subdivisions, radius=self.diameter_mm / 2)]


class BallBarObject(_Object):
    """Two spheres at ``(+-centre_distance / 2, 0, 0)`` of the object frame (no rod)."""

    kind: Literal["ball_bar"] = "ball_bar"
    diameter_mm: float = Field(38.1, gt=0, description="diameter of each ball, mm")
    centre_distance_mm: float = Field(209.8219, gt=0, description="distance of the ball centres, mm")
    subdivisions: int = Field(6, ge=1, le=9, description="icosphere subdivisions per ball")

    def spheres(self) -> np.ndarray:
        """Exact spheres (2, 4): world centres (mm) and radius (mm)."""
        half = self.centre_distance_mm / 2
        c = self.pose.apply(np.array([[-half, 0.0, 0.0], [half, 0.0, 0.0]]))
        return np.concatenate([c, np.full((2, 1), self.diameter_mm / 2)], axis=1)

    def _local(self) -> list[trimesh.Trimesh]:
        half = self.centre_distance_mm / 2
        balls = []
        for x in (-half, half):
            m = trimesh.creation.icosphere(self.subdivisions, radius=self.diameter_mm / 2)
            balls.append(m.apply_translation([x, 0.0, 0.0]))
        return balls


class PlaneObject(_Object):
    """A rectangle ``z = 0`` of the object frame, centred on its origin (two-sided)."""

    kind: Literal["plane"] = "plane"
    size_mm: tuple[float, float] = Field((400.0, 300.0), description="extent along object x and y, mm")

    def spheres(self) -> np.ndarray:
        return np.zeros((0, 4))

    def _local(self) -> list[trimesh.Trimesh]:
        w, h = self.size_mm
        if w <= 0 or h <= 0:
            raise SimInputError(f"field 'size_mm' must be > 0, got {self.size_mm}")
        v = np.array([[-w / 2, -h / 2, 0], [w / 2, -h / 2, 0], [w / 2, h / 2, 0], [-w / 2, h / 2, 0]])
        return [trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)]


class BoardObject(_Object):
    """A printed calibration board (``sim.render.board.CalibrationBoard``) in the ``z = 0``
    plane of the object frame, covering ``[0, width] x [0, height]`` mm: one quad whose hit
    points get the board's two-level albedo (``albedo`` is unused)."""

    kind: Literal["board"] = "board"
    board: CalibrationBoard = Field(description="the board's pattern and sizes")

    def spheres(self) -> np.ndarray:
        return np.zeros((0, 4))

    def _local(self) -> list[trimesh.Trimesh]:
        w, h = self.board.size_mm
        v = np.array([[0.0, 0.0, 0], [w, 0.0, 0], [w, h, 0], [0.0, h, 0]])
        return [trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)]


class MeshObject(_Object):
    """A mesh file (PLY, STL, OBJ), in ``scale`` mm per file unit; normals are interpolated
    across edges sharper than ``smooth_angle_deg`` no further (those stay sharp)."""

    kind: Literal["mesh"] = "mesh"
    path: Path = Field(description="mesh file (PLY, STL or OBJ); relative to the scene file")
    scale: float = Field(1.0, gt=0, description="mm per file unit")
    smooth_angle_deg: float = Field(30.0, ge=0, le=180, description="sharp-edge angle, degrees")

    def spheres(self) -> np.ndarray:
        return np.zeros((0, 4))

    def _local(self) -> list[trimesh.Trimesh]:
        if self.path.suffix.lower() not in MESH_SUFFIXES:
            raise SimInputError(f"field 'path': mesh file {self.path} must be PLY, STL or OBJ")
        if not self.path.is_file():
            raise FileNotFoundError(f"field 'path': mesh file {self.path} not found")
        mesh = load_mesh(self.path, where="field 'path': ")
        mesh.apply_scale(self.scale)
        mesh.merge_vertices()
        angle = np.radians(self.smooth_angle_deg)
        return [trimesh.graph.smooth_shade(mesh, angle=angle, facet_minarea=None)]


def load_mesh(path: Path, where: str = "") -> trimesh.Trimesh:
    """The triangle mesh of a PLY, STL (ASCII or binary) or OBJ file, unprocessed, in file
    units; errors (ValueError) start with ``where`` and name the file and the problem."""
    what = f"{where}mesh file {path}"
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # noqa: BLE001 - the parsers raise anything on a bad file
        detail = " ".join(str(exc).split())[:200] or type(exc).__name__
        raise SimInputError(f"{what} cannot be read as {path.suffix[1:].upper()}: "
                            f"{detail}") from exc
    if not isinstance(mesh, trimesh.Trimesh):
        raise SimInputError(f"{what} holds no triangle mesh")
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    if v.ndim != 2 or v.shape[1] != 3 or not np.all(np.isfinite(v)):
        bad = int(np.sum(~np.all(np.isfinite(v.reshape(len(v), -1)), axis=1)))
        raise SimInputError(f"{what} has {bad} non-finite vertices (NaN or infinite coordinates)")
    if len(f) == 0:
        raise SimInputError(f"{what} has no triangles ({len(v)} vertices in use)")
    if f.ndim != 2 or f.shape[1] != 3 or f.min() < 0 or f.max() >= len(v):
        raise SimInputError(f"{what} has faces that are not triangles of its {len(v)} vertices")
    return mesh


SceneObject = Annotated[SphereObject | BallBarObject | PlaneObject | MeshObject | BoardObject,
                        Field(discriminator="kind")]


class Scene(BaseModel):
    """The objects of one scene pose."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    objects: list[SceneObject] = Field(min_length=1, description="what is in front of the rig")

    def trace_geometry(self, where: str = "scene") -> TraceGeometry:
        """All objects as one ``TraceGeometry`` in world coordinates; errors name ``where``
        and the object (``objects[i]``)."""
        verts, faces, normals, albedo, obj, face_sph = [], [], [], [], [], []
        spheres: list[np.ndarray] = []  # rows (cx, cy, cz, r) mm
        nv = 0
        for i, o in enumerate(self.objects):
            try:
                parts = o._local()
            except FileNotFoundError as exc:
                raise FileNotFoundError(f"{where}: objects[{i}] ({o.kind} '{o.name}'): {exc}") from exc
            except SimInputError as exc:
                raise SimInputError(f"{where}: objects[{i}] ({o.kind} '{o.name}'): {exc}") from exc
            for j, m in enumerate(parts):
                verts.append(o.pose.apply(m.vertices))
                normals.append(o.pose.rotate(m.vertex_normals))
                faces.append(np.asarray(m.faces) + nv)
                nv += len(m.vertices)
                nf = len(m.faces)
                albedo.append(np.full(nf, 1.0 if isinstance(o, BoardObject) else o.albedo))
                obj.append(np.full(nf, i, np.int32))
                is_sphere = o.kind in ("sphere", "ball_bar")
                face_sph.append(np.full(nf, len(spheres) + j if is_sphere else -1, np.int64))
            spheres.extend(o.spheres())
        boards = tuple(PlacedBoard(i, o.board, np.asarray(o.pose.R), np.asarray(o.pose.t))
                       for i, o in enumerate(self.objects) if isinstance(o, BoardObject))
        try:
            geom = self._geometry(verts, faces, normals, albedo, obj, face_sph, spheres)
            return replace(geom, boards=boards) if boards else geom
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from exc

    @staticmethod
    def _geometry(verts, faces, normals, albedo, obj, face_sph, spheres) -> TraceGeometry:
        return TraceGeometry(np.concatenate(verts), np.concatenate(faces), np.concatenate(normals),
                             np.concatenate(albedo), np.concatenate(obj),
                             np.asarray(spheres, dtype=np.float64).reshape(-1, 4),
                             np.concatenate(face_sph))


class ThinLensSpec(BaseModel):
    """Ideal thin lens: ``AberratedLens`` without vignetting or aberrations."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: Literal["thin"] = "thin"
    pupil_diameter_mm: float = Field(gt=0, description="entrance pupil diameter, mm")
    focus_distance_mm: float = Field(gt=0, description="distance of the plane in focus, mm")
    samples: int = Field(64, ge=1, description="aperture samples per pixel")

    def lens(self) -> AberratedLens:
        return AberratedLens(pupil_diameter_mm=self.pupil_diameter_mm,
                             focus_distance_mm=self.focus_distance_mm, samples=self.samples)


class MeasuredLensSpec(BaseModel):
    """A measured lens model file, read by ``sim.optics.measured_lens.load_lens``."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: Literal["measured"] = "measured"
    path: Path = Field(description="lens model file; relative to the scene file")


LENS_KINDS = {"pinhole": PinholeLens, "thin": ThinLensSpec, "aberrated": AberratedLens,
              "gaussian": GaussianLens, "measured": MeasuredLensSpec}


class SceneFile(BaseModel):
    """Contents of a scene TOML file (see the module docstring)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    rig: Path = Field(description="rig file (sim.optics.rig: OpenCV FileStorage YAML or JSON)")
    lenses: list[Any] = Field(min_length=1, description="one lens model table per rig camera")
    objects: list[SceneObject] = Field(min_length=1, description="scene objects")
    patterns: PatternSet = Field(description="the projected pattern set")
    render: RenderSettings = Field(default_factory=RenderSettings, description="projector and camera")
    seed: int = Field(0, ge=0, description="seed of the camera noise generator (>= 0)")

    @field_validator("lenses", mode="before")
    @classmethod
    def _lenses(cls, v):
        out = []
        for i, spec in enumerate(v if isinstance(v, list) else []):
            kind = spec.get("kind") if isinstance(spec, dict) else None
            if not isinstance(kind, str) or kind not in LENS_KINDS:
                raise SimInputError(f"lenses[{i}]: unknown lens kind {kind!r}, "
                                 f"expected one of {', '.join(LENS_KINDS)}")
            try:
                out.append(LENS_KINDS[kind].model_validate(spec))
            except ValidationError as exc:
                raise SimInputError(format_validation_error(f"lenses[{i}]", exc)) from exc
        return out if isinstance(v, list) else v


def _resolve(base: Path, p: Path) -> Path:
    return p if p.is_absolute() else base / p


def _build_lens(spec, base: Path, source: Path, index: int, camera: DeviceCalibration) -> LensModel:
    if isinstance(spec, ThinLensSpec):
        return spec.lens()
    if isinstance(spec, MeasuredLensSpec):
        where = f"{source}: field 'lenses[{index}].path'"
        path = _resolve(base, spec.path)
        if not path.is_file():
            raise FileNotFoundError(f"{where}: lens file {path} not found")
        from sim.optics.lens_file import load_lens_for  # imported only when a scene uses it

        try:
            return load_lens_for(path, camera)
        except SimInputError as exc:
            raise SimInputError(f"{where}: {exc}") from exc
    return spec


@dataclass
class LoadedScene:
    """A scene file with its rig, lenses and geometry loaded, ready to render."""

    source: Path
    config: SceneFile
    rig: Rig
    lenses: list[LensModel]
    scene: Scene
    geometry: TraceGeometry

    def input_files(self) -> list[Path]:
        """Every file the scene reads: the scene file, its rig, measured lenses and meshes."""
        base = self.source.parent
        files = [self.source, _resolve(base, self.config.rig)]
        files += [_resolve(base, s.path) for s in self.config.lenses
                  if isinstance(s, MeasuredLensSpec)]
        files += [o.path for o in self.scene.objects if isinstance(o, MeshObject)]
        return files

    def render(self, progress: bool = False) -> RenderResult:
        """Render the scene's pattern set on every camera (noise seeded by ``config.seed``)."""
        imgs = self.config.patterns.images(self.rig.projector.size)
        return render_views(self.geometry, self.rig, self.lenses, imgs, self.config.render,
                            np.random.default_rng(self.config.seed), progress=progress,
                            where=str(self.source))

    def save(self, result: RenderResult, out: str | Path, radiance: bool = False, *,
             final: str | Path | None = None) -> dict:
        """Write a rendering into the new folder ``out`` (docs/formats.md, "ltc render
        folder"): 8/16-bit PNGs per camera (unless unquantised), ``render.zarr`` with the
        images and truth maps, ``summary.json``. ``final``: the path the folder will have
        once renamed into place (recorded in the summary; default ``out``). Returns the
        summary."""
        out = Path(out)
        out.mkdir(parents=True)
        cam = self.config.render.camera
        png_dirs = [str(out / f"camera_{i}") if cam.quantize else None
                    for i in range(len(result.cameras))]
        for c, d in zip(result.cameras, png_dirs, strict=True):
            if d is not None:
                write_pngs(d, c.images, cam.bit_depth)
        recorded = Path(final) if final is not None else out
        summary = self._summary(result, recorded,
                                [d and str(recorded / Path(d).name) for d in png_dirs])
        descriptors = self.config.patterns.descriptors(self.rig.projector.size)
        attrs = {"summary": summary, "scene": self.config.model_dump(mode="json"),
                 "rig": self.rig.model_dump(mode="json"),
                 "patterns": [d.model_dump(mode="json") for d in descriptors],
                 "png_note": "12-bit images are stored unscaled (0..4095) in 16-bit PNG"}
        write_zarr(out / "render.zarr", result, attrs, radiance=radiance)
        with durable_file(out / "summary.json") as f:
            f.write(json.dumps(summary, indent=2))
        return summary

    def _summary(self, result: RenderResult, out: Path, png_dirs: list[str | None]) -> dict:
        cfg = self.config
        cams = []
        for i, (c, dev) in enumerate(zip(result.cameras, self.rig.cameras, strict=True)):
            depth = c.depth[np.isfinite(c.depth)]
            cams.append({
                "name": c.name, "group": f"camera_{i}", "size": list(dev.size),
                "lens": cfg.lenses[i].kind, "rays": c.n_rays,
                "seen_fraction": float(np.mean(c.object_id >= 0)),
                "lit_fraction": float(np.mean(c.lit)),
                "depth_mm": [float(depth.min()), float(depth.max())] if depth.size else None,
                "png_dir": png_dirs[i], "timings": c.timings,
            })
        return {
            "scene": str(self.source), "rig": str(self.source.parent / cfg.rig), "out": str(out),
            "zarr": str(out / "render.zarr"), "images": int(result.cameras[0].images.shape[0]),
            "bit_depth": cfg.render.camera.bit_depth, "quantized": cfg.render.camera.quantize,
            "pattern_set": cfg.patterns.model_dump(mode="json"), "cameras": cams,
            "timings": result.timings,
        }


def _projector_size(raw: object, base: Path) -> tuple[int, int] | None:
    """The rig's projector (width, height) when ``[patterns]`` gives ``fringes`` and the rig
    file reads (a rig that does not is reported by the rig's own check)."""
    if not isinstance(raw, dict):
        return None
    patterns = raw.get("patterns")
    if not (isinstance(patterns, dict) and "fringes" in patterns
            and isinstance(raw.get("rig"), str)):
        return None
    try:
        return Rig.load(_resolve(base, Path(raw["rig"]))).projector.size
    except (OSError, ValueError):
        return None


def load_scene_file(path: str | Path) -> LoadedScene:
    """Read a scene TOML file and everything it names; errors name the file and the field."""
    path = Path(path)
    raw = read_toml(path, "scene file")
    base = path.parent
    try:
        cfg = SceneFile.model_validate(raw, context={"projector_size": _projector_size(raw, base)})
    except ValidationError as exc:
        raise SimInputError(format_validation_error(str(path), exc)) from exc
    rig_path = _resolve(base, cfg.rig)
    try:
        rig = Rig.load(rig_path)
    except FileNotFoundError as exc:
        raise FileNotFoundError(f"{path}: field 'rig': {exc}") from exc
    except SimInputError as exc:
        raise SimInputError(f"{path}: field 'rig': {exc}") from exc
    if len(cfg.lenses) != len(rig.cameras):
        raise SimInputError(f"{path}: field 'lenses': {len(cfg.lenses)} lens tables for "
                         f"{len(rig.cameras)} rig cameras; give one per camera")
    lenses = [_build_lens(spec, base, path, i, cam)
              for i, (spec, cam) in enumerate(zip(cfg.lenses, rig.cameras, strict=True))]
    objects = [o.model_copy(update={"path": _resolve(base, o.path)}) if isinstance(o, MeshObject) else o
               for o in cfg.objects]
    scene = Scene(objects=objects)
    return LoadedScene(path, cfg, rig, lenses, scene, scene.trace_geometry(where=str(path)))
