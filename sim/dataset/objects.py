"""The objects of a data set: built-in procedural families and the user's mesh folder.

Every object is built in its own frame, centred on the centre of its bounding box and scaled
so that its bounding sphere (about that centre) has the diameter ``size_mm``; a sample's pose
then places that frame in the world. A procedural object is a pure function of its family,
its own seed and its size, so a sample's description regenerates it exactly.

Families (``sim.dataset.config.FAMILIES``):

- ``primitive``: one trimesh primitive (box, cylinder, cone, capsule, torus, ellipsoid);
- ``union``: 2 to 4 overlapping primitives (their first-hit surface is their union's);
- ``displaced``: a height field of random Gaussian bumps and ripples (a two-sided sheet);
- ``steps``: a staircase of boxes; ``holes``: a plate with blind round holes (a height
  field: the holes' walls are resolved to 1/192 of the plate);
- ``sphere``, ``ball_bar``, ``plane``: the metrology artefacts, spheres traced exactly.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from sim.errors import SimInputError
from sim.render.scene import MESH_SUFFIXES, load_mesh

SMOOTH_ANGLE_DEG = 30.0  # edges sharper than this stay sharp (as MeshObject)
HEIGHT_FIELD_N = 192  # height-field grid (displaced, holes): cells per side


@dataclass(frozen=True)
class Parts:
    """An object in its normalised frame: meshes (mm) and exact spheres (k, 4) (centre, r)."""

    meshes: list[trimesh.Trimesh]
    spheres: np.ndarray


def mesh_files(folder: Path) -> list[Path]:
    """The PLY, STL and OBJ files of ``folder`` (not recursive), sorted by name; refuses a
    missing folder or one without meshes (errors name the folder)."""
    if not folder.is_dir():
        raise FileNotFoundError(f"mesh folder {folder} not found")
    files = sorted(p for p in folder.iterdir()
                   if p.is_file() and p.suffix.lower() in MESH_SUFFIXES)
    if not files:
        raise SimInputError(f"mesh folder {folder} holds no PLY, STL or OBJ file")
    return files


def _smooth(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    mesh.merge_vertices()
    return trimesh.graph.smooth_shade(mesh, angle=np.radians(SMOOTH_ANGLE_DEG),
                                      facet_minarea=None)


def _primitive(rng: np.random.Generator) -> trimesh.Trimesh:
    kind = int(rng.integers(6))
    a, b, c = rng.uniform(0.3, 1.0, 3)
    if kind == 0:
        return trimesh.creation.box(extents=[a, b, c])
    if kind == 1:
        return trimesh.creation.cylinder(radius=a / 2, height=b, sections=96)
    if kind == 2:
        return trimesh.creation.cone(radius=a / 2, height=b, sections=96)
    if kind == 3:
        return trimesh.creation.capsule(height=b, radius=a / 3, count=[48, 48])
    if kind == 4:
        return trimesh.creation.torus(major_radius=a / 2,
                                      minor_radius=a / 2 * rng.uniform(0.2, 0.5),
                                      major_sections=96, minor_sections=48)
    m = trimesh.creation.icosphere(4, radius=0.5)
    m.apply_scale([a, b, c])
    return m


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random rotation matrix (3, 3)."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _union(rng: np.random.Generator) -> list[trimesh.Trimesh]:
    parts = []
    for _ in range(int(rng.integers(2, 5))):
        m = _primitive(rng)
        T = np.eye(4)
        T[:3, :3] = _random_rotation(rng)
        T[:3, 3] = rng.uniform(-0.3, 0.3, 3)
        parts.append(m.apply_transform(T))
    return parts


def _height_field(z: np.ndarray) -> trimesh.Trimesh:
    """A sheet over [-0.5, 0.5]^2 with heights z (n, n)."""
    n = z.shape[0]
    g = np.linspace(-0.5, 0.5, n)
    x, y = np.meshgrid(g, g)
    v = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    i = np.arange(n * n).reshape(n, n)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, 1:].ravel(), i[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return trimesh.Trimesh(v, faces, process=False)


def _displaced(rng: np.random.Generator) -> trimesh.Trimesh:
    n = HEIGHT_FIELD_N + 1
    g = np.linspace(-0.5, 0.5, n)
    x, y = np.meshgrid(g, g)
    z = np.zeros_like(x)
    for _ in range(int(rng.integers(3, 9))):
        cx, cy = rng.uniform(-0.4, 0.4, 2)
        s = rng.uniform(0.05, 0.25)
        z += rng.uniform(-0.15, 0.15) * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
    k = rng.uniform(4, 20, 2)
    z += rng.uniform(0, 0.02) * np.sin(2 * np.pi * (k[0] * x + k[1] * y) / 4)
    return _height_field(z)


def _steps(rng: np.random.Generator) -> list[trimesh.Trimesh]:
    k = int(rng.integers(2, 6))
    depth = rng.uniform(0.4, 1.0)
    rise = rng.uniform(0.05, 0.2)
    w = 1.0 / k
    out = []
    for j in range(k):
        h = rise * (j + 1)
        out.append(trimesh.creation.box(extents=[w, depth, h]).apply_translation(
            [-0.5 + (j + 0.5) * w, 0.0, h / 2]))
    return out


def _holes(rng: np.random.Generator) -> trimesh.Trimesh:
    n = HEIGHT_FIELD_N + 1
    g = np.linspace(-0.5, 0.5, n)
    x, y = np.meshgrid(g, g)
    z = np.zeros_like(x)
    for _ in range(int(rng.integers(1, 6))):
        cx, cy = rng.uniform(-0.35, 0.35, 2)
        r = rng.uniform(0.04, 0.12)
        z = np.where((x - cx) ** 2 + (y - cy) ** 2 <= r * r, -rng.uniform(0.05, 0.2), z)
    return _height_field(z)


def _artefact(family: str, rng: np.random.Generator) -> Parts:
    if family == "sphere":
        return Parts([trimesh.creation.icosphere(5, radius=0.5)], np.array([[0, 0, 0, 0.5]]))
    if family == "ball_bar":
        r = rng.uniform(0.1, 0.25)
        half = 0.5 - r
        balls = [trimesh.creation.icosphere(5, radius=r).apply_translation([s * half, 0, 0])
                 for s in (-1, 1)]
        return Parts(balls, np.array([[-half, 0, 0, r], [half, 0, 0, r]]))
    a = rng.uniform(0.5, 1.0)
    v = np.array([[-0.5, -a / 2, 0], [0.5, -a / 2, 0], [0.5, a / 2, 0], [-0.5, a / 2, 0]])
    return Parts([trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)], np.zeros((0, 4)))


def _normalised(parts: Parts, size_mm: float) -> Parts:
    """``parts`` moved to the centre of their bounding box and scaled to a bounding sphere of
    diameter ``size_mm``."""
    v = np.concatenate([m.vertices for m in parts.meshes])
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    radius = float(np.max(np.linalg.norm(v - centre, axis=1)))
    if len(parts.spheres):
        d = np.linalg.norm(parts.spheres[:, :3] - centre, axis=1) + parts.spheres[:, 3]
        radius = max(radius, float(d.max()))
    if not radius > 0:
        raise SimInputError("the object is a single point")
    s = size_mm / (2 * radius)
    meshes = []
    for m in parts.meshes:
        m = m.copy()
        m.apply_translation(-centre)
        m.apply_scale(s)
        meshes.append(m)
    sph = parts.spheres.copy()
    if len(sph):
        sph[:, :3] = (sph[:, :3] - centre) * s
        sph[:, 3] *= s
    return Parts(meshes, sph)


def procedural(family: str, seed: list[int], size_mm: float) -> Parts:
    """The procedural object of ``family`` drawn from its own seed, normalised to a bounding
    sphere of ``size_mm``."""
    rng = np.random.default_rng(seed)
    if family in ("sphere", "ball_bar", "plane"):
        parts = _artefact(family, rng)
        return _normalised(parts, size_mm)
    build = {"primitive": lambda: [_primitive(rng)], "union": lambda: _union(rng),
             "displaced": lambda: [_displaced(rng)], "steps": lambda: _steps(rng),
             "holes": lambda: [_holes(rng)]}
    if family not in build:
        raise SimInputError(f"unknown object family {family!r}")
    return _normalised(Parts([_smooth(m) for m in build[family]()], np.zeros((0, 4))), size_mm)


@functools.lru_cache(maxsize=8)
def _mesh_file(path: str) -> trimesh.Trimesh:
    mesh = load_mesh(Path(path))
    return _smooth(mesh)


def from_file(path: Path, size_mm: float) -> Parts:
    """A mesh file (PLY, STL, OBJ, any unit) normalised to a bounding sphere of ``size_mm``;
    errors (FileNotFoundError, ValueError) name the file."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"mesh file {path} not found")
    return _normalised(Parts([_mesh_file(str(path))], np.zeros((0, 4))), size_mm)


def check_mesh(path: Path) -> None:
    """Raise (naming the file) unless ``path`` is a readable triangle mesh of some extent."""
    from_file(path, 1.0)
