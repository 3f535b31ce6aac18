"""The records the tracer's compiled loops (``sim.render.trace_kernels``) take and fill: small
fixed parameters as named tuples of floats (``CameraFrame``, ``ProjectorModel``,
``Intrinsics``), arrays that go together as named tuples of arrays (``ChunkRays``, ``Hits``,
``FaceArrays``, ``ChunkTransport``, ``ShadowRays``), and the columns of the face table.
Lengths in mm, pixel coordinates in OpenCV convention.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

# Columns of ``TraceGeometry.face_table`` (F, FACE_COLUMNS) float64: geometric normal (3),
# plane offset n . v0 (mm), shading normal (3), albedo, scene object, and the kind of face
# (FACE_FLAT, FACE_SMOOTH, or the index >= 0 of its exact sphere).
FACE_NORMAL, FACE_OFFSET, FACE_SHADING, FACE_ALBEDO, FACE_OBJECT, FACE_KIND = 0, 3, 4, 7, 8, 9
FACE_COLUMNS = 10
FACE_FLAT, FACE_SMOOTH = -1.0, -2.0


class CameraFrame(NamedTuple):
    """The camera's pose, as the kernels use it: world point ``R^T x_c + C``, world direction
    ``R^T d_c``, depth ``R[2] . x + T[2]`` (mm)."""

    rt00: float  # R^T, row-major
    rt01: float
    rt02: float
    rt10: float
    rt11: float
    rt12: float
    rt20: float
    rt21: float
    rt22: float
    ox: float  # the centre C = -R^T T, world mm
    oy: float
    oz: float
    depth_x: float  # R[2]
    depth_y: float
    depth_z: float
    depth_t: float  # T[2], mm


class ProjectorModel(NamedTuple):
    """The projector's pinhole model with OpenCV distortion: world-to-device ``R``, ``T``,
    intrinsics (px), distortion, image size (px), the largest trusted squared normalised
    radius, and its centre (world mm)."""

    r00: float  # R, row-major
    r01: float
    r02: float
    r10: float
    r11: float
    r12: float
    r20: float
    r21: float
    r22: float
    t0: float  # T, mm
    t1: float
    t2: float
    fx: float  # K: px
    skew: float
    cx: float
    fy: float
    cy: float
    k1: float  # OpenCV distortion
    k2: float
    p1: float
    p2: float
    k3: float
    distorted: float  # 1.0: any distortion coefficient is non-zero, else 0.0
    width: float  # px
    height: float
    max_r2: float  # largest trusted squared normalised radius (points beyond: outside)
    px: float  # centre, world mm
    py: float
    pz: float


class Intrinsics(NamedTuple):
    """An undistorted camera's pixel-to-normalised map, with reciprocals (px)."""

    width: float
    inv_width: float
    inv_fx: float
    skew: float
    cx: float
    inv_fy: float
    cy: float


class ChunkRays(NamedTuple):
    """A chunk's rays as ``chunk_rays`` takes them. The camera-frame lens bundle of n pixels:
    flat ``weights`` (n K,) float64 (rays of weight 0 are not cast) and ``k`` = K, origins
    ``o_cam`` (K, 3) when ``shared`` by every pixel, else (n, K, 3), directions ``d_cam``
    (n, K, 3), all float64 mm and contiguous (n = 0 for a pinhole). Then the chief rays:
    through normalised coordinates ``xy`` (2, c) float64; or when xy is empty, through the flat
    ``pixels`` (c,) (float64) of an undistorted camera (``_pixel_xy``); or when both are empty,
    through its pixels ``first .. first + c - 1``, ``run = (first, c)``. ``pinhole``: the chief
    ray is the pixel's one ray."""

    weights: np.ndarray
    k: int
    o_cam: np.ndarray
    shared: bool
    d_cam: np.ndarray
    xy: np.ndarray
    pixels: np.ndarray
    run: tuple[int, int]
    pinhole: bool

    @property
    def n_rays(self) -> int:
        """Room for every ray of the chunk: lens rays and chief rays."""
        return len(self.weights) + max(self.xy.shape[1], len(self.pixels), self.run[1])


class Hits(NamedTuple):
    """Embree's first hits of m rays: face ``prim`` (m,) int32 (-1: miss), distance ``tfar``
    (m,) float32 mm, barycentrics ``u``, ``v`` (m,) float32."""

    prim: np.ndarray
    tfar: np.ndarray
    u: np.ndarray
    v: np.ndarray


class FaceArrays(NamedTuple):
    """What shading reads of the scene: ``table`` (F, FACE_COLUMNS) float64, ``faces`` (F, 3)
    int64, ``vertex_normals`` (V, 3) float64, exact ``spheres`` (S, 4) float64 (cx, cy, cz, r
    mm)."""

    table: np.ndarray
    faces: np.ndarray
    vertex_normals: np.ndarray
    spheres: np.ndarray


TRANSPORT_ARRAYS = ("proj_uv", "weight", "depth", "proj_chief", "lit", "object_id")
ChunkTransport = NamedTuple("ChunkTransport", [(name, np.ndarray) for name in TRANSPORT_ARRAYS])
ChunkTransport.__doc__ = """A chunk's slice of the arrays of ``sim.render.trace.Transport``
(``TRANSPORT_ARRAYS``, in its order), written in place: per lens ray ``proj_uv`` (n K, 2)
float32 and ``weight`` (n K,) float32; per pixel ``depth`` (n,) float64, ``proj_chief`` (n, 2)
float64, ``lit`` (n,) bool, ``object_id`` (n,) int32."""


class ShadowRays(NamedTuple):
    """Room for s shadow rays: ``origin``, ``direction`` (s, 3) float32, ``far`` (s,) float32
    mm, ``dest`` (s,) int64 the transport entry each belongs to."""

    origin: np.ndarray
    direction: np.ndarray
    far: np.ndarray
    dest: np.ndarray
