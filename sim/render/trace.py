"""Embree tracing of camera rays into a scene lit by the projector: the scene's light transport.

For every camera pixel and lens ray (docs/optics.md section 3): the first hit (embreex, refined in
float64 on the hit triangle, or on the exact sphere for built-in spheres), the interpolated
vertex normal (two-sided: turned towards the camera), ``N . L`` towards the projector centre, a
shadow ray to the projector, and the hit point's projector coordinate with the projector's
distortion. The result, ``Transport``, holds per ray the projector coordinate ``(u_p, v_p)`` and
the weight ``w_k * albedo * (N . L) * V`` (0 for misses, shadows and points outside the
projector image), plus truth maps of the chief ray (the ray through the centre of the aperture).
It depends on the scene pose and the lens only, so any number of patterns render from it.

Work is split into chunks of rays traced on a thread pool, so every core is used: per chunk,
the world rays, then Embree's first hits, then one compiled pass per ray (``sim.render.trace_kernels``:
float64 refinement, shading, projector coordinates, the shadow rays), then Embree's occlusion
queries, then the transport is written. Embree and the compiled passes release the GIL, so the
threads overlap them.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh
from tqdm import tqdm

from sim.errors import SimInputError
from sim.optics.lens import LensModel, PinholeLens
from sim.optics.rig import DeviceCalibration
from sim.render import trace_kernels as kern
from sim.tolerances import PROJECTOR_GUARD, SHADOW_OFFSET_MM, VERTEX_NORMAL_SAME_TOL

CHUNK_RAYS = 1 << 15  # rays per work item (a pinhole's: half; smaller or larger is slower)


@dataclass(frozen=True)
class TraceGeometry:
    """All triangles of a scene in world coordinates, with what shading and truth need.

    vertices (V, 3) float64 mm; faces (F, 3) int; vertex_normals (V, 3) unit;
    face_albedo (F,) in [0, 1]; face_object (F,) int, the scene object of each face;
    spheres (S, 4) float64, exact spheres ``(cx, cy, cz, r)`` mm; face_sphere (F,) int, the
    exact sphere a face approximates (-1: none), so hits on it are refined onto the sphere;
    boards: calibration boards (``sim.render.board.PlacedBoard``) whose faces carry albedo 1
    and whose printed albedo ``sim.render.images.render_camera`` applies to each traced tile.
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_normals: np.ndarray
    face_albedo: np.ndarray
    face_object: np.ndarray
    spheres: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    face_sphere: np.ndarray | None = None
    boards: tuple = ()  # sim.render.board.PlacedBoard: albedo evaluated where rays hit them

    def __post_init__(self) -> None:
        v, f = np.asarray(self.vertices), np.asarray(self.faces)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise SimInputError(f"TraceGeometry needs vertices (V, 3) and faces (F>0, 3), "
                             f"got {v.shape}, {f.shape}")
        if not np.all(np.isfinite(v)):
            raise SimInputError("TraceGeometry: vertices must be finite")
        if f.min() < 0 or f.max() >= len(v):
            raise SimInputError(f"TraceGeometry: face indices must be in [0, {len(v)}), "
                             f"got [{f.min()}, {f.max()}]")
        for name, n in (("vertex_normals", len(v)), ("face_albedo", len(f)), ("face_object", len(f))):
            if len(getattr(self, name)) != n:
                raise SimInputError(f"TraceGeometry: {name} must have {n} rows, "
                                 f"got {len(getattr(self, name))}")
        if self.face_sphere is None:
            object.__setattr__(self, "face_sphere", np.full(len(f), -1, dtype=np.int64))

    @cached_property
    def face_normals(self) -> np.ndarray:
        """Unit geometric normals (F, 3) float64, right-handed in the face's vertex order."""
        tri = self.vertices[self.faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        return n / np.where(norm > 0, norm, 1.0)

    @cached_property
    def face_offset(self) -> np.ndarray:
        """(F,) plane offsets ``n . v0`` of the faces, mm."""
        return np.einsum("ij,ij->i", self.face_normals, self.vertices[self.faces[:, 0]])

    @cached_property
    def face_smooth(self) -> np.ndarray:
        """(F,) bool: the face's vertex normals differ (interpolate them); not for sphere faces."""
        vn = self.vertex_normals[self.faces]
        same = np.all(np.abs(vn - vn[:, :1]) <= VERTEX_NORMAL_SAME_TOL, axis=(1, 2))
        assert self.face_sphere is not None, "set by __post_init__"
        return ~same & (self.face_sphere < 0)

    @cached_property
    def face_shading(self) -> np.ndarray:
        """(F, 3) shading normal of faces whose vertex normals agree (their common normal)."""
        return self.vertex_normals[self.faces[:, 0]].astype(np.float64)

    @cached_property
    def face_table(self) -> np.ndarray:
        """(F, ``trace_kernels.FACE_COLUMNS``) float64, per face what shading reads, in one
        row: geometric normal (3), plane offset, shading normal (3), albedo, object, and the
        kind of face: ``FACE_FLAT``, ``FACE_SMOOTH`` (``face_smooth``), or the index of its
        exact sphere."""
        assert self.face_sphere is not None, "set by __post_init__"
        kind = np.where(self.face_sphere >= 0, self.face_sphere,
                        np.where(self.face_smooth, kern.FACE_SMOOTH, kern.FACE_FLAT))
        return np.ascontiguousarray(np.column_stack(
            [self.face_normals, self.face_offset, self.face_shading, self.face_albedo,
             self.face_object, kind]), dtype=np.float64)

    @cached_property
    def kernel_arrays(self) -> kern.FaceArrays:
        """The arrays ``trace_kernels`` shading reads, contiguous and typed: ``face_table``,
        faces (F, 3) int64, vertex normals (V, 3) and spheres (S, 4) float64."""
        return kern.FaceArrays(self.face_table, np.ascontiguousarray(self.faces, dtype=np.int64),
                np.ascontiguousarray(self.vertex_normals, dtype=np.float64),
                np.ascontiguousarray(self.spheres, dtype=np.float64).reshape(-1, 4))

    @cached_property
    def embree(self) -> rtcore_scene.EmbreeScene:
        """The committed Embree scene (float32 copy of the triangles)."""
        scene = rtcore_scene.EmbreeScene()
        TriangleMesh(scene, np.ascontiguousarray(self.vertices, dtype=np.float32),
                     np.ascontiguousarray(self.faces, dtype=np.int32))
        return scene


@dataclass
class Transport:
    """Light transport of one camera (or a subset of its pixels) in one scene pose.

    pixels : (n,) int64 flat pixel indices ``v * width + u``.
    proj_uv : (n, K, 2) float32 projector coordinate of each ray's hit (NaN where none).
    weight : (n, K) float32 lens weight x albedo x N.L x visibility (0 where unlit).
    depth : (n,) float64 z (mm, camera frame) of the chief ray's hit, NaN where nothing.
    proj_chief : (n, 2) float64 projector coordinate of the chief ray's hit, NaN where nothing
        or outside the projector image (shadowed points keep theirs; see ``lit``).
    lit : (n,) bool, the chief ray's hit sees the projector inside its image with N.L > 0.
    object_id : (n,) int32 scene object hit by the chief ray, -1 for none.
    """

    camera_size: tuple[int, int]
    projector_size: tuple[int, int]
    pixels: np.ndarray
    proj_uv: np.ndarray
    weight: np.ndarray
    depth: np.ndarray
    proj_chief: np.ndarray
    lit: np.ndarray
    object_id: np.ndarray
    seconds: float = 0.0
    rays: int = 0  # camera rays cast (lens rays of weight > 0 plus chief rays), not shadow rays

    def _map(self, values: np.ndarray, fill) -> np.ndarray:
        w, h = self.camera_size
        out = np.full((h * w,) + values.shape[1:], fill, dtype=values.dtype)
        out[self.pixels] = values
        return out.reshape((h, w) + values.shape[1:])

    def depth_map(self) -> np.ndarray:
        """(H, W) float64 chief-ray depth z, mm; NaN where nothing (or not traced)."""
        return self._map(self.depth, np.nan)

    def projector_map(self) -> np.ndarray:
        """(H, W, 2) float64 chief-ray projector coordinate ``(u_p, v_p)``, NaN where none."""
        return self._map(self.proj_chief, np.nan)

    def lit_map(self) -> np.ndarray:
        """(H, W) bool, chief ray's hit lit by the projector."""
        return self._map(self.lit, False)

    def object_map(self) -> np.ndarray:
        """(H, W) int32 scene object index seen by the chief ray, -1 for none."""
        return self._map(self.object_id, -1)


@dataclass(frozen=True)
class _Projector:
    """The projector's pinhole model, vectorised: ``K``, OpenCV ``dist``, world-to-device R, T."""

    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    T: np.ndarray
    centre: np.ndarray
    size: tuple[int, int]
    guard_r2: float

    @classmethod
    def of(cls, dev: DeviceCalibration) -> _Projector:
        w, h = dev.size
        s = np.linspace(0.0, 1.0, 33)
        lo, u_hi, v_hi = np.full_like(s, -0.5), np.full_like(s, w - 0.5), np.full_like(s, h - 0.5)
        border = np.concatenate([np.stack(p, 1) for p in (
            (s * w - 0.5, lo), (s * w - 0.5, v_hi), (lo, s * h - 0.5), (u_hi, s * h - 0.5))])
        r2 = float(np.max(np.sum(dev.normalized(border) ** 2, axis=1)))
        return cls(dev.K_array, dev.dist_array, dev.R_array, dev.T_array, dev.centre_world,
                   dev.size, r2 * PROJECTOR_GUARD**2)

    @cached_property
    def model(self) -> kern.ProjectorModel:
        """The projector as ``sim.render.trace_kernels`` reads it."""
        K, w, h = self.K, *self.size
        return kern.ProjectorModel(*(float(x) for x in (*self.R.ravel(), *self.T, K[0, 0], K[0, 1], K[0, 2],
                                        K[1, 1], K[1, 2], *self.dist, bool(np.any(self.dist)),
                                        w, h, self.guard_r2, *self.centre)))

    def coordinates(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Projector pixels ``(u, v)``, each (m,), of world points (3, m); NaN outside the image.

        The OpenCV model of ``sim.optics.projection.project_points``, compiled
        (``trace_kernels.projector_uv``; cv2.projectPoints costs ~0.8 us a point); points beyond
        ``PROJECTOR_GUARD`` times the image's largest normalised radius are outside (so the
        distortion polynomial never folds back)."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        u, v = np.empty(x.shape[1]), np.empty(x.shape[1])
        kern.projector_coordinates(x, self.model, u, v)
        return u, v


def _shadow_buffers(m: int) -> kern.ShadowRays:
    """Room for up to m shadow rays: origins, directions (m, 3) float32, far (m,) float32,
    and what each belongs to (m,) int64."""
    return kern.ShadowRays(np.empty((m, 3), np.float32), np.empty((m, 3), np.float32),
                           np.empty(m, np.float32), np.empty(m, np.int64))


def _occluded(geom: TraceGeometry, shadow: kern.ShadowRays, s: int) -> np.ndarray:
    """Embree occlusion of the first s shadow rays: -1 where nothing is in the way."""
    if s == 0:
        return np.empty(0, np.int32)
    return geom.embree.run(shadow.origin[:s], shadow.direction[:s], dists=shadow.far[:s],
                           query="OCCLUDED")


_GRIDS: dict[str, np.ndarray] = {}  # undistorted normalised coordinates of every pixel, by camera
GRID_CACHE_CAMERAS = 4


def normalized_grid(cam: DeviceCalibration, threads: int | None = None) -> np.ndarray | None:
    """Undistorted normalised coordinates (H * W, 2) of every pixel of a distorted camera,
    computed once (in parallel) and cached for ``GRID_CACHE_CAMERAS`` cameras: undistortion
    (iterative, ~1 us a pixel) would otherwise cost more than tracing a pinhole ray.
    None for a camera without distortion (its normalised coordinates are one affine map)."""
    if not np.any(cam.dist_array):
        return None
    key = cam.model_dump_json()
    if key not in _GRIDS:
        w, h = cam.size
        grid = np.empty((w * h, 2))
        step = 1 << 16

        def part(a: int) -> None:
            p = np.arange(a, min(a + step, w * h))
            grid[a : a + len(p)] = cam.normalized(np.stack([p % w, p // w], axis=1).astype(float))

        with ThreadPoolExecutor(threads or os.cpu_count() or 1) as ex:
            list(ex.map(part, range(0, w * h, step)))
        while len(_GRIDS) >= GRID_CACHE_CAMERAS:
            _GRIDS.pop(next(iter(_GRIDS)))
        _GRIDS[key] = grid
    return _GRIDS[key]


def _camera_model(cam: DeviceCalibration) -> kern.CameraFrame:
    """The camera's pose as ``sim.render.trace_kernels`` reads it."""
    R, T = cam.R_array, cam.T_array
    return kern.CameraFrame(*(float(x) for x in (*R.T.ravel(), *(-R.T @ T), *R[2], T[2])))


_Chunk = kern.ChunkRays

_NO_BUNDLE = (np.zeros(0), 1, np.zeros((1, 3)), True, np.zeros((0, 1, 3)))
_NO_XY, _NO_PIXELS, _NO_RUN = np.zeros((2, 0)), np.zeros(0), (0, 0)


def _intrinsics(cam: DeviceCalibration) -> kern.Intrinsics:
    """The camera's intrinsics as ``trace_kernels._pixel_xy`` reads them."""
    K = cam.K_array
    return kern.Intrinsics(float(cam.width), 1.0 / cam.width, 1.0 / K[0, 0], K[0, 1], K[0, 2], 1.0 / K[1, 1],
            K[1, 2])


def _chunk(cam: DeviceCalibration, A: kern.Intrinsics, lens: LensModel, pixels: np.ndarray,
           grid: np.ndarray | None, run: bool = False) -> _Chunk:
    """The rays of pixels (flat indices; ``run``: they are consecutive): the lens rays of
    ``lens.bundle(xy_n, uv)`` (those of weight > 0 are cast) then the chief rays; a pinhole's
    one ray is its chief ray (its bundle is not built). ``A``: ``_intrinsics(cam)``; ``grid``:
    ``normalized_grid(cam)``."""
    if isinstance(lens, PinholeLens):
        if grid is not None:
            xy = np.ascontiguousarray(grid[pixels].T)
            return _Chunk(*_NO_BUNDLE, xy, _NO_PIXELS, _NO_RUN, True)
        if run and len(pixels):
            return _Chunk(*_NO_BUNDLE, _NO_XY, _NO_PIXELS, (int(pixels[0]), len(pixels)), True)
        return _Chunk(*_NO_BUNDLE, _NO_XY, pixels.astype(np.float64), _NO_RUN, True)
    if grid is None:
        uv, xy = np.empty((len(pixels), 2)), np.empty((len(pixels), 2))
        kern.pixel_coordinates(pixels, A, uv, xy)
    else:
        row, col = np.divmod(pixels, cam.width)
        uv = np.stack([col, row], axis=1).astype(np.float64)
        xy = np.ascontiguousarray(grid[pixels])
    b = lens.bundle(xy, uv)
    shared = len(xy) > 1 and b.origins.strides[0] == 0  # a broadcast of the aperture samples
    return _Chunk(np.ascontiguousarray(b.weights, dtype=np.float64).reshape(-1),
                  b.weights.shape[1],
                  np.ascontiguousarray(b.origins[0] if shared else b.origins, dtype=np.float64),
                  shared, np.ascontiguousarray(b.directions, dtype=np.float64),
                  np.ascontiguousarray(xy.T), _NO_PIXELS, _NO_RUN, False)


def _world_rays(c: _Chunk, A: kern.Intrinsics, cam_model: kern.CameraFrame, proj_uv: np.ndarray,
                weight: np.ndarray):
    """``trace_kernels.chunk_rays`` of a chunk: world rays W (6, >= m) (the first m columns),
    float32 origins and directions (m, 3), the lens rays' destinations (n_lens,), n_lens."""
    n = c.n_rays
    W, dest = np.empty((6, n)), np.empty(n, np.int64)
    o32, d32 = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
    n_lens, n_chief = kern.chunk_rays(c, A, cam_model, W, o32, d32, dest, proj_uv, weight)
    m = n_lens + n_chief
    return W, o32[:m], d32[:m], dest[:n_lens], n_lens


def camera_rays(camera: DeviceCalibration, lens: LensModel,
                pixels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The world rays ``trace_camera`` casts for ``pixels`` (default all): origins (m, 3) mm
    and unit directions (m, 3), float64; lens rays of weight > 0, then the chief rays unless
    the lens is a pinhole. For timing raw Embree on exactly our rays (Embree gets them as
    float32)."""
    w, h = camera.size
    pix = np.arange(w * h) if pixels is None else np.asarray(pixels, dtype=np.int64).ravel()
    A = _intrinsics(camera)
    c = _chunk(camera, A, lens, pix, normalized_grid(camera), run=pixels is None)
    n = len(c.weights)
    W, o32, _, _, _ = _world_rays(c, A, _camera_model(camera), np.empty((n, 2), np.float32),
                                  np.empty(n, np.float32))
    m = len(o32)
    return np.ascontiguousarray(W[:3, :m].T), np.ascontiguousarray(W[3:, :m].T)


def _trace_chunk(geom: TraceGeometry, proj: _Projector, cam: DeviceCalibration, A: kern.Intrinsics,
                 cam_model: kern.CameraFrame, lens: LensModel, pixels: np.ndarray, run: bool,
                 grid: np.ndarray | None, result: Transport, sl: slice) -> int:
    """Trace the pixels of ``result[sl]`` into it; returns the number of camera rays."""
    c = _chunk(cam, A, lens, pixels, grid, run)
    proj_uv, weight = result.proj_uv[sl].reshape(-1, 2), result.weight[sl].reshape(-1)
    W, o32, d32, dest, n_lens = _world_rays(c, A, cam_model, proj_uv, weight)
    m, nk = len(o32), len(c.weights)
    hits = geom.embree.run(o32, d32, output=1)
    shadow = _shadow_buffers(m)
    out = kern.ChunkTransport(proj_uv, weight, result.depth[sl], result.proj_chief[sl],
                              result.lit[sl], result.object_id[sl])
    s = kern.shade_chunk(W, dest, nk, n_lens, n_lens == nk, c.pinhole, cam_model,
                         kern.Hits(hits["primID"], hits["tfar"], hits["u"], hits["v"]),
                         geom.kernel_arrays, proj.model, SHADOW_OFFSET_MM, c.weights, out, shadow)
    kern.shadow_chunk(_occluded(geom, shadow, s), shadow.dest[:s], nk, c.pinhole, weight,
                      result.lit[sl])
    return m


def trace_camera(geom: TraceGeometry, camera: DeviceCalibration, projector: DeviceCalibration,
                 lens: LensModel, pixels: np.ndarray | None = None, threads: int | None = None,
                 progress: bool = False) -> Transport:
    """Trace every pixel of ``camera`` (or the flat indices ``pixels``) through ``lens``.

    Lens rays come from ``lens.bundle(xy_n, uv)`` with ``xy_n`` the pixels' undistorted
    normalised coordinates (the camera's distortion lives there). ``threads`` defaults to
    every core. Returns the ``Transport``.
    """
    t0 = time.perf_counter()
    w, h = camera.size
    if pixels is None:
        pix = np.arange(w * h, dtype=np.int64)
    else:
        pix = np.asarray(pixels, dtype=np.int64).ravel()
        if len(pix) and (pix.min() < 0 or pix.max() >= w * h):
            raise SimInputError(f"pixels must be flat indices in [0, {w * h}) of camera "
                             f"'{camera.name}'")
    k = lens.bundle(np.zeros((1, 2)), np.zeros((1, 2))).weights.shape[1]
    n = len(pix)
    # every entry is written by the chunk that holds its pixel
    res = Transport(camera.size, projector.size, pix, np.empty((n, k, 2), np.float32),
                    np.empty((n, k), np.float32), np.empty(n), np.empty((n, 2)),
                    np.empty(n, bool), np.empty(n, np.int32))
    proj = _Projector.of(projector)
    _ = proj.model
    cam_model, A = _camera_model(camera), _intrinsics(camera)
    grid = normalized_grid(camera, threads)
    for attr in ("embree", "kernel_arrays"):
        getattr(geom, attr)  # build once, before the threads share them
    step = max(1, CHUNK_RAYS // (k + 1))
    slices = [slice(s, min(s + step, n)) for s in range(0, n, step)]
    with ThreadPoolExecutor(max_workers=threads or os.cpu_count() or 1) as ex:
        futs = [ex.submit(_trace_chunk, geom, proj, camera, A, cam_model, lens, pix[s],
                          pixels is None, grid, res, s) for s in slices]
        for fut in tqdm(futs, desc=f"trace {camera.name}", unit="chunk", disable=not progress,
                        leave=False):
            res.rays += fut.result()
    res.seconds = time.perf_counter() - t0
    return res
