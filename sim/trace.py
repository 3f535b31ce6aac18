"""Embree tracing of camera rays into a scene lit by the projector: the scene's light transport.

For every camera pixel and lens ray (OPTICS.md section 4): the first hit (embreex, refined in
float64 on the hit triangle, or on the exact sphere for built-in spheres), the interpolated
vertex normal (two-sided: turned towards the camera), ``N . L`` towards the projector centre, a
shadow ray to the projector, and the hit point's projector coordinate with the projector's
distortion. The result, ``Transport``, holds per ray the projector coordinate ``(u_p, v_p)`` and
the weight ``w_k * albedo * (N . L) * V`` (0 for misses, shadows and points outside the
projector image), plus truth maps of the chief ray (the ray through the centre of the aperture).
It depends on the scene pose and the lens only, so any number of patterns render from it.

Work is split into chunks of rays traced on a thread pool (embreex, OpenCV and most numpy
loops release the GIL), so every core is used.
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

from sim.lens import LensModel, PinholeLens
from sim.rig import DeviceCalibration

SHADOW_OFFSET_MM = 1e-3  # shadow rays start this far off the surface, along its normal
CHUNK_RAYS = 1 << 15  # rays per work item
PROJECTOR_GUARD = 1.2  # distortion is trusted up to this multiple of the image's largest radius


@dataclass(frozen=True)
class TraceGeometry:
    """All triangles of a scene in world coordinates, with what shading and truth need.

    vertices (V, 3) float64 mm; faces (F, 3) int; vertex_normals (V, 3) unit;
    face_albedo (F,) in [0, 1]; face_object (F,) int, the scene object of each face;
    spheres (S, 4) float64, exact spheres ``(cx, cy, cz, r)`` mm; face_sphere (F,) int, the
    exact sphere a face approximates (-1: none), so hits on it are refined onto the sphere.
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_normals: np.ndarray
    face_albedo: np.ndarray
    face_object: np.ndarray
    spheres: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    face_sphere: np.ndarray | None = None

    def __post_init__(self) -> None:
        v, f = np.asarray(self.vertices), np.asarray(self.faces)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise ValueError(f"TraceGeometry needs vertices (V, 3) and faces (F>0, 3), "
                             f"got {v.shape}, {f.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError("TraceGeometry: vertices must be finite")
        if f.min() < 0 or f.max() >= len(v):
            raise ValueError(f"TraceGeometry: face indices must be in [0, {len(v)}), "
                             f"got [{f.min()}, {f.max()}]")
        for name, n in (("vertex_normals", len(v)), ("face_albedo", len(f)), ("face_object", len(f))):
            if len(getattr(self, name)) != n:
                raise ValueError(f"TraceGeometry: {name} must have {n} rows, "
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
    def face_normals_soa(self) -> np.ndarray:
        """(3, F) copy of ``face_normals``."""
        return np.ascontiguousarray(self.face_normals.T)

    @cached_property
    def face_shading_soa(self) -> np.ndarray:
        """(3, F) copy of ``face_shading``."""
        return np.ascontiguousarray(self.face_shading.T)

    @cached_property
    def face_offset(self) -> np.ndarray:
        """(F,) plane offsets ``n . v0`` of the faces, mm."""
        return np.einsum("ij,ij->i", self.face_normals, self.vertices[self.faces[:, 0]])

    @cached_property
    def face_smooth(self) -> np.ndarray:
        """(F,) bool: the face's vertex normals differ (interpolate them); not for sphere faces."""
        vn = self.vertex_normals[self.faces]
        same = np.all(np.abs(vn - vn[:, :1]) <= 1e-9, axis=(1, 2))
        return ~same & (self.face_sphere < 0)

    @cached_property
    def face_shading(self) -> np.ndarray:
        """(F, 3) shading normal of faces whose vertex normals agree (their common normal)."""
        return self.vertex_normals[self.faces[:, 0]].astype(np.float64)

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


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot products of (3, m) column stacks (structure of arrays: contiguous rows are fast)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _affine(M: np.ndarray, x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``M x + t`` for points (3, m)."""
    return np.stack([M[i, 0] * x[0] + M[i, 1] * x[1] + M[i, 2] * x[2] + t[i] for i in range(3)])


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

    def coordinates(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Projector pixels ``(u, v)``, each (m,), of world points (3, m); NaN outside the image.

        The OpenCV model of ``sim.projection.project_points`` in plain numpy (cv2.projectPoints
        costs ~0.8 us a point); points beyond ``PROJECTOR_GUARD`` times the image's largest
        normalised radius are outside (so the distortion polynomial never folds back)."""
        xp, yp, z = _affine(self.R, x, self.T)
        with np.errstate(divide="ignore", invalid="ignore"):
            iz = 1.0 / z
        xn, yn = xp * iz, yp * iz
        r2 = xn * xn + yn * yn
        k1, k2, p1, p2, k3 = self.dist
        if np.any(self.dist):
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xy2 = 2.0 * xn * yn
            xd = xn * radial + p1 * xy2 + p2 * (r2 + 2.0 * xn * xn)
            yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + p2 * xy2
        else:
            xd, yd = xn, yn
        u = self.K[0, 0] * xd + self.K[0, 1] * yd + self.K[0, 2]
        v = self.K[1, 1] * yd + self.K[1, 2]
        w, h = self.size
        with np.errstate(invalid="ignore"):
            out = (z <= 0) | ~(r2 <= self.guard_r2)
            out |= (u < -0.5) | (u > w - 0.5) | (v < -0.5) | (v > h - 0.5)
        u[out] = np.nan
        v[out] = np.nan
        return u, v


def _refine_spheres(geom: TraceGeometry, sph: np.ndarray, o: np.ndarray, d: np.ndarray,
                    t: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Move hits on sphere faces onto the exact sphere (t (h,), normals n (3, h) in place);
    returns the indices refined. o, d: (3, h)."""
    on = np.flatnonzero(sph >= 0)
    if len(on) == 0:
        return on
    c, r = geom.spheres[sph[on], :3].T, geom.spheres[sph[on], 3]
    oc = o[:, on] - c
    b = _dot(oc, d[:, on])
    disc = b * b - (_dot(oc, oc) - r * r)
    ok = disc >= 0
    idx = on[ok]
    t[idx] = -b[ok] - np.sqrt(disc[ok])
    n[:, idx] = (o[:, idx] + t[idx] * d[:, idx] - c[:, ok]) / r[ok]
    return idx


def trace_rays(geom: TraceGeometry, proj: _Projector, o: np.ndarray, d: np.ndarray) -> dict:
    """Shade world rays given as (3, m) origins and unit directions (see the module docstring).

    Returns ``point`` (3, m) hit points (NaN for misses), ``u``, ``v`` (m,) projector
    coordinates, ``shade`` (m,) albedo x N.L x V, ``lit`` (m,) bool, ``object`` (m,) int32.
    """
    m = o.shape[1]
    res = geom.embree.run(np.ascontiguousarray(o.T, dtype=np.float32),
                          np.ascontiguousarray(d.T, dtype=np.float32), output=1)
    prim = res["primID"]
    hit = np.flatnonzero(prim >= 0)
    out = {"point": np.full((3, m), np.nan), "u": np.full(m, np.nan), "v": np.full(m, np.nan),
               "shade": np.zeros(m), "lit": np.zeros(m, bool), "object": np.full(m, -1, np.int32)}
    if len(hit) == 0:
        return out
    f = prim[hit]
    oh, dh = np.take(o, hit, axis=1), np.take(d, hit, axis=1)
    n_g = np.take(geom.face_normals_soa, f, axis=1)
    t_embree = res["tfar"][hit].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (np.take(geom.face_offset, f) - _dot(n_g, oh)) / _dot(n_g, dh)
    bad = ~(np.abs(t - t_embree) <= 1e-4 * t_embree + 1e-3)  # degenerate or grazing: keep Embree's
    t[bad] = t_embree[bad]
    n_s = np.take(geom.face_shading_soa, f, axis=1)
    smooth = np.flatnonzero(np.take(geom.face_smooth, f))
    if len(smooth):  # interpolate vertex normals with Embree's barycentrics
        vn = np.take(geom.vertex_normals, geom.faces[f[smooth]], axis=0)  # (s, 3, 3)
        bu, bv = res["u"][hit[smooth], None], res["v"][hit[smooth], None]
        ns = (1.0 - bu - bv) * vn[:, 0] + bu * vn[:, 1] + bv * vn[:, 2]
        n_s[:, smooth] = (ns / np.linalg.norm(ns, axis=1, keepdims=True)).T
    on = _refine_spheres(geom, np.take(geom.face_sphere, f), oh, dh, t, n_s)
    n_g[:, on] = n_s[:, on]
    x = oh + t * dh
    n_g *= np.where(_dot(n_g, dh) > 0, -1.0, 1.0)  # two-sided: face the camera
    n_s *= np.where(_dot(n_s, n_g) < 0, -1.0, 1.0)  # shading normal on the same side
    L = proj.centre[:, None] - x
    dist = np.sqrt(_dot(L, L))
    L /= dist
    cos = _dot(n_s, L)
    u, v = proj.coordinates(x)
    ci = np.flatnonzero((_dot(n_g, L) > 0) & (cos > 0) & ~np.isnan(u))
    lit = np.zeros(len(hit), bool)
    if len(ci):
        so = np.take(x, ci, axis=1) + SHADOW_OFFSET_MM * np.take(n_g, ci, axis=1)
        far = (dist[ci] - 2 * SHADOW_OFFSET_MM).astype(np.float32)
        occ = geom.embree.run(np.ascontiguousarray(so.T, dtype=np.float32),
                              np.ascontiguousarray(np.take(L, ci, axis=1).T, dtype=np.float32),
                              dists=far, query="OCCLUDED")
        lit[ci[occ == -1]] = True
    out["point"][:, hit] = x
    out["u"][hit], out["v"][hit], out["lit"][hit] = u, v, lit
    out["shade"][hit] = np.where(lit, np.take(geom.face_albedo, f) * cos, 0.0)
    out["object"][hit] = np.take(geom.face_object, f)
    return out


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


def _rays(cam: DeviceCalibration, lens: LensModel, pixels: np.ndarray, grid: np.ndarray | None):
    """The bundle of pixels (flat indices), its live mask (n, K), and the world rays cast:
    origins and directions (3, m), the live lens rays then (unless pinhole) the chief rays."""
    w = cam.width
    uv = np.stack([pixels % w, pixels // w], axis=1).astype(np.float64)
    xy = cam.normalized(uv) if grid is None else grid[pixels]
    b = lens.bundle(xy, uv)
    live = b.weights > 0  # (n, K): vignetted samples are not traced
    if live.all():
        o_cam, d_cam = b.origins.reshape(-1, 3).T, b.directions.reshape(-1, 3).T
    else:
        o_cam, d_cam = b.origins[live].T, b.directions[live].T
    if not isinstance(lens, PinholeLens):  # append the chief rays
        chief = np.concatenate([xy.T, np.ones((1, len(xy)))])
        chief /= np.sqrt(_dot(chief, chief))
        o_cam = np.concatenate([o_cam, np.zeros_like(chief)], axis=1)
        d_cam = np.concatenate([d_cam, chief], axis=1)
    R, T = cam.R_array, cam.T_array
    return b, live, _affine(R.T, o_cam, -R.T @ T), _affine(R.T, d_cam, np.zeros(3))


def camera_rays(camera: DeviceCalibration, lens: LensModel,
                pixels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The world rays ``trace_camera`` casts for ``pixels`` (default all): origins (m, 3) mm
    and unit directions (m, 3), float64; lens rays of weight > 0, then the chief rays unless
    the lens is a pinhole. For timing raw Embree on exactly our rays."""
    w, h = camera.size
    pix = np.arange(w * h) if pixels is None else np.asarray(pixels, dtype=np.int64).ravel()
    _, _, o, d = _rays(camera, lens, pix, normalized_grid(camera))
    return o.T, d.T


def _trace_chunk(geom, proj, cam: DeviceCalibration, lens: LensModel, pixels: np.ndarray,
                 grid: np.ndarray | None, result: Transport, sl: slice) -> int:
    b, live, o, d = _rays(cam, lens, pixels, grid)
    n, k = b.weights.shape
    all_live = bool(live.all())
    n_live = int(live.sum())
    pinhole = isinstance(lens, PinholeLens)
    R, T = cam.R_array, cam.T_array
    r = trace_rays(geom, proj, o, d)
    wt = (b.weights.reshape(-1) if all_live else b.weights[live]) * r["shade"][:n_live]
    puv = np.stack([r["u"][:n_live], r["v"][:n_live]], axis=-1)
    if all_live:
        result.proj_uv[sl] = puv.reshape(n, k, 2)
        result.weight[sl] = wt.reshape(n, k)
    else:
        full_uv = np.full((n, k, 2), np.nan, dtype=np.float32)
        full_w = np.zeros((n, k), dtype=np.float32)
        full_uv[live], full_w[live] = puv, wt
        result.proj_uv[sl], result.weight[sl] = full_uv, full_w
    c = slice(n_live, None) if not pinhole else slice(0, n_live)
    pc = r["point"][:, c]
    result.depth[sl] = R[2, 0] * pc[0] + R[2, 1] * pc[1] + R[2, 2] * pc[2] + T[2]
    result.proj_chief[sl] = np.stack([r["u"][c], r["v"][c]], axis=-1)
    result.lit[sl], result.object_id[sl] = r["lit"][c], r["object"][c]
    return o.shape[1]


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
        raise ValueError(f"pixels must be flat indices in [0, {w * h}) of camera '{camera.name}'")
    k = lens.bundle(np.zeros((1, 2)), np.zeros((1, 2))).weights.shape[1]
    n = len(pix)
    res = Transport(camera.size, projector.size, pix, np.full((n, k, 2), np.nan, np.float32),
                    np.zeros((n, k), np.float32), np.full(n, np.nan), np.full((n, 2), np.nan),
                    np.zeros(n, bool), np.full(n, -1, np.int32))
    proj = _Projector.of(projector)
    grid = normalized_grid(camera, threads)
    for attr in ("embree", "face_offset", "face_smooth", "face_normals_soa", "face_shading_soa"):
        getattr(geom, attr)  # build once, before the threads share them
    step = max(1, CHUNK_RAYS // (k + 1))
    slices = [slice(s, min(s + step, n)) for s in range(0, n, step)]
    with ThreadPoolExecutor(max_workers=threads or os.cpu_count() or 1) as ex:
        futs = [ex.submit(_trace_chunk, geom, proj, camera, lens, pix[s], grid, res, s)
                for s in slices]
        for fut in tqdm(futs, desc=f"trace {camera.name}", unit="chunk", disable=not progress,
                        leave=False):
            res.rays += fut.result()
    res.seconds = time.perf_counter() - t0
    return res
