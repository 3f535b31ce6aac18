"""Compiled per-ray loops of ``sim.render.trace`` (numba): world rays, hit refinement and
shading, projector coordinates, shadow rays, and the transport written in place. (The lens
bundles' ray geometry is ``sim.optics.lens_kernels``.)

The arithmetic is docs/optics.md section 3 in float64, as the vectorised numpy it replaced did it
(results agree to a few ulps; the float32 transport is unchanged). The loops release the GIL
(``nogil``), so the tracer's threads run them side by side with Embree queries, and are
compiled on first use and cached on disk (``cache``). Where it matters the work is laid out
for SIMD: loops over contiguous 1-d arrays without branches, in their own functions (the
compiler then knows the arrays apart). Hits are shaded in blocks of ``BLOCK``: a scalar pass
gathers each hit's face data (and does the rare per-face work: interpolated normals, exact
spheres), one branch-free vectorised pass does the geometry and the projector, and the
results are written out.

Small fixed parameters travel as named tuples of floats (``CameraFrame``, ``ProjectorModel``,
``Intrinsics``; numba keeps them in registers, unlike arrays, and reads a field by name at no
cost), arrays that go together as named tuples of arrays (``Hits``, ``FaceArrays``,
``ChunkTransport``, ``ShadowRays``), defined in ``sim.render.trace_records`` and re-exported
here. The shading scratch ``S`` is read by the row names defined once below, the face table by
the column names of ``trace_records``.

The rays of a chunk of n pixels with lens bundles of K samples: first the lens rays of
weight > 0 (pixel by pixel), then one chief ray per pixel. A pinhole has no bundle (K = 1,
n K = 0 lens rays): its one ray is the chief ray. A lens ray's destination (``dest``) is its
index ``i K + j`` in the bundle; the chief ray of pixel i is ``n K + i``. World rays are kept
as a (6, m) float64 array ``W``: origin x, y, z then direction x, y, z.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from sim.render.trace_records import (
    FACE_ALBEDO,
    FACE_COLUMNS,
    FACE_FLAT,
    FACE_KIND,
    FACE_NORMAL,
    FACE_OBJECT,
    FACE_OFFSET,
    FACE_SHADING,
    FACE_SMOOTH,
    TRANSPORT_ARRAYS,
    CameraFrame,
    ChunkRays,
    ChunkTransport,
    FaceArrays,
    Hits,
    Intrinsics,
    ProjectorModel,
    ShadowRays,
)

# the records are re-exported: the tracer reaches everything through this module
__all__ = [
    "CameraFrame",
    "ChunkRays",
    "ChunkTransport",
    "FACE_ALBEDO",
    "FACE_COLUMNS",
    "FACE_FLAT",
    "FACE_KIND",
    "FACE_NORMAL",
    "FACE_OBJECT",
    "FACE_OFFSET",
    "FACE_SHADING",
    "FACE_SMOOTH",
    "FaceArrays",
    "Hits",
    "Intrinsics",
    "ProjectorModel",
    "ShadowRays",
    "TRANSPORT_ARRAYS",
]

_JIT = {"nogil": True, "cache": True, "error_model": "numpy", "boundscheck": False}
_INLINE = {**_JIT, "inline": "always"}
NAN = np.nan
BLOCK = 1024  # rays shaded per block (the block's scratch stays in the L2 cache)
_SCRATCH_PAD = 8  # rows BLOCK + 8 long: not a multiple of 4 kB apart (no 4k aliasing)

# Rows of the shading scratch S (_SCRATCH_ROWS, BLOCK + _SCRATCH_PAD) float64, one column per
# hit of the block. Written by _gather: geometric normal, plane offset (mm), shading normal,
# Embree's distance (mm), the exact-sphere distance (mm; NaN but for sphere faces), albedo.
_GX, _GY, _GZ, _OFFSET, _SX, _SY, _SZ, _T_EMBREE, _T_SPHERE, _ALBEDO = range(10)
# Written by _surface: point (mm), geometric normal facing the ray's origin, unit vector L to the
# projector centre, its distance (mm), shade (albedo x N.L, 0 where unlit), shadow ray needed
# (1 or 0), projector pixel u, v; and by _gather: the scene object (-1: miss).
_PX, _PY, _PZ, _NX, _NY, _NZ, _LX, _LY, _LZ, _DIST, _SHADE, _CAND, _U, _V, _OBJ = range(10, 25)
_SCRATCH_ROWS = 25

_NO_WEIGHTS = np.zeros(0)  # a pinhole's ray: its weight is its shade


@nb.njit(**_INLINE)
def _to_world(cam, a, b, c):
    """World point of camera-frame point ``(a, b, c)``: ``R^T (a, b, c) + C``."""
    return (cam.rt00 * a + cam.rt01 * b + cam.rt02 * c + cam.ox,
            cam.rt10 * a + cam.rt11 * b + cam.rt12 * c + cam.oy,
            cam.rt20 * a + cam.rt21 * b + cam.rt22 * c + cam.oz)


@nb.njit(**_INLINE)
def _rotate(cam, p, q, s):
    """World direction of camera-frame direction ``(p, q, s)``: ``R^T (p, q, s)``."""
    return (cam.rt00 * p + cam.rt01 * q + cam.rt02 * s, cam.rt10 * p + cam.rt11 * q + cam.rt12 * s,
            cam.rt20 * p + cam.rt21 * q + cam.rt22 * s)


@nb.njit(**_INLINE)
def _pixel_uv(p, A):
    """Column and row (float64) of flat pixel index p (float64); the row
    ``floor((p + 1/2) / width)`` is exact for any image of fewer than 2^40 pixels."""
    v = math.floor((p + 0.5) * A.inv_width)
    return p - v * A.width, v


@nb.njit(**_INLINE)
def _pixel_xy(p, A):
    """Normalised coordinates of flat pixel index p (float64) of an undistorted camera: the
    distortion-free branch of ``sim.optics.projection.pixel_to_normalized``, with reciprocals (to an
    ulp or two)."""
    u, v = _pixel_uv(p, A)
    y = (v - A.cy) * A.inv_fy
    return (u - A.cx - A.skew * y) * A.inv_fx, y


@nb.njit(**_JIT)
def pixel_coordinates(pixels, A, uv, xy):
    """Pixel coordinates ``uv`` (n, 2) (column, row) and normalised coordinates ``xy`` (n, 2)
    of flat pixel indices (n,) of an undistorted camera (``_pixel_xy``)."""
    for i in range(pixels.shape[0]):
        p = np.float64(pixels[i])
        uv[i, 0], uv[i, 1] = _pixel_uv(p, A)
        xy[i, 0], xy[i, 1] = _pixel_xy(p, A)


@nb.njit(**_JIT)
def chunk_rays(rays, A, cam, W, o32, d32, dest, proj_uv, weight):
    """World rays of a chunk's ``ChunkRays`` (see the module docstring; ``Intrinsics`` ``A``,
    ``CameraFrame`` ``cam``): ``W`` (6, m) float64, their float32 copies ``o32, d32`` (m, 3)
    for Embree, and the lens rays' ``dest``. Rays not cast get ``proj_uv`` (n K, 2) NaN and
    ``weight`` (n K,) 0 now. W and the others have room for every ray. Returns the number of
    lens rays cast and of chief rays."""
    wts, k, o_cam, shared, d_cam = rays.weights, rays.k, rays.o_cam, rays.shared, rays.d_cam
    xy, pixels, run = rays.xy, rays.pixels, rays.run
    o0, o1, o2, d0, d1, d2 = W[0], W[1], W[2], W[3], W[4], W[5]
    oc, dc = o_cam.reshape(-1), d_cam.reshape(-1)
    nk = wts.shape[0]
    all_live = True
    for e in range(nk):
        all_live &= wts[e] > 0
    r = 0
    if shared and all_live and nk:  # the common case, vectorised
        ow = np.empty((3, k))
        for j in range(k):
            ow[0, j], ow[1, j], ow[2, j] = _to_world(cam, oc[3 * j], oc[3 * j + 1], oc[3 * j + 2])
        _lens_rays(dc, ow[0], ow[1], ow[2], k, cam, o0[:nk], o1[:nk], o2[:nk], d0[:nk], d1[:nk],
                   d2[:nk], dest[:nk])
        r = nk
    for i in range(nk // k if r == 0 else 0):
        for j in range(k):
            e = i * k + j
            if not wts[e] > 0:
                proj_uv[e, 0], proj_uv[e, 1], weight[e] = NAN, NAN, 0.0
                continue
            oi = 3 * j if shared else 3 * e
            o0[r], o1[r], o2[r] = _to_world(cam, oc[oi], oc[oi + 1], oc[oi + 2])
            d0[r], d1[r], d2[r] = _rotate(cam, dc[3 * e], dc[3 * e + 1], dc[3 * e + 2])
            dest[r] = e
            r += 1
    if xy.shape[1]:
        c = xy.shape[1]
        _chief_rays(xy[0], xy[1], cam, o0[r:r + c], o1[r:r + c], o2[r:r + c], d0[r:r + c],
                    d1[r:r + c], d2[r:r + c])
    elif pixels.shape[0]:
        c = pixels.shape[0]
        _pixel_chief_rays(pixels, A, cam, o0[r:r + c], o1[r:r + c], o2[r:r + c], d0[r:r + c],
                          d1[r:r + c], d2[r:r + c])
    else:  # the run of pixels first .. first + c - 1
        first, c = run
        _run_chief_rays(np.float64(first), A, cam, o0[r:r + c], o1[r:r + c], o2[r:r + c],
                        d0[r:r + c], d1[r:r + c], d2[r:r + c])
    of, df = o32.reshape(-1), d32.reshape(-1)
    for t in range(r + c):
        of[3 * t], of[3 * t + 1], of[3 * t + 2] = o0[t], o1[t], o2[t]
        df[3 * t], df[3 * t + 1], df[3 * t + 2] = d0[t], d1[t], d2[t]
    return r, c


@nb.njit(**_JIT)
def _lens_rays(dc, ow0, ow1, ow2, k, cam, o0, o1, o2, d0, d1, d2, dest):
    """World rays of every lens ray of n pixels whose K samples share their origins (world:
    ow0-ow2 (K,)), from camera-frame directions ``dc`` (3 n K,) into rows of W (each
    (n K,)), ``dest`` their index. Its own function: the loop is vectorised."""
    for i in range(dc.shape[0] // (3 * k)):
        for j in range(k):
            e = i * k + j
            o0[e], o1[e], o2[e] = ow0[j], ow1[j], ow2[j]
            d0[e], d1[e], d2[e] = _rotate(cam, dc[3 * e], dc[3 * e + 1], dc[3 * e + 2])
            dest[e] = e


@nb.njit(**_INLINE)
def _chief_ray(x, y, cam):
    """World direction of the chief ray through normalised coordinates ``(x, y)``."""
    s = 1.0 / math.sqrt(x * x + y * y + 1.0)
    return _rotate(cam, x * s, y * s, s)


@nb.njit(**_JIT)
def _chief_rays(xs, ys, cam, o0, o1, o2, d0, d1, d2):
    """Chief rays (from the camera centre) through normalised coordinates xs, ys (c,) into
    rows of ``W`` (each (c,)). Its own function: the loop over contiguous arrays is
    vectorised."""
    for i in range(xs.shape[0]):
        o0[i], o1[i], o2[i] = cam.ox, cam.oy, cam.oz
        d0[i], d1[i], d2[i] = _chief_ray(xs[i], ys[i], cam)


@nb.njit(**_JIT)
def _run_chief_rays(first, A, cam, o0, o1, o2, d0, d1, d2):
    """``_chief_rays`` through the pixels ``first, first + 1, ...`` of an undistorted
    camera."""
    for i in range(o0.shape[0]):
        x, y = _pixel_xy(first + i, A)
        o0[i], o1[i], o2[i] = cam.ox, cam.oy, cam.oz
        d0[i], d1[i], d2[i] = _chief_ray(x, y, cam)


@nb.njit(**_JIT)
def _pixel_chief_rays(pixels, A, cam, o0, o1, o2, d0, d1, d2):
    """``_chief_rays`` through the flat ``pixels`` (c,) float64 of an undistorted camera."""
    for i in range(pixels.shape[0]):
        x, y = _pixel_xy(pixels[i], A)
        o0[i], o1[i], o2[i] = cam.ox, cam.oy, cam.oz
        d0[i], d1[i], d2[i] = _chief_ray(x, y, cam)


@nb.njit(**_INLINE)
def _project(x0, x1, x2, P, distort):
    """Projector pixel ``(u, v)`` of a world point with OpenCV distortion (when ``distort``, a
    constant where inlined); NaN outside the image, behind the projector or beyond the trusted
    radius. Branch-free."""
    xp = P.r00 * x0 + P.r01 * x1 + P.r02 * x2 + P.t0
    yp = P.r10 * x0 + P.r11 * x1 + P.r12 * x2 + P.t1
    z = P.r20 * x0 + P.r21 * x1 + P.r22 * x2 + P.t2
    iz = 1.0 / z
    xn, yn = xp * iz, yp * iz
    r2 = xn * xn + yn * yn
    xd, yd = xn, yn
    if distort:
        k1, k2, p1, p2, k3 = P.k1, P.k2, P.p1, P.p2, P.k3
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy2 = 2.0 * xn * yn
        xd = xn * radial + p1 * xy2 + p2 * (r2 + 2.0 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + p2 * xy2
    u = P.fx * xd + P.skew * yd + P.cx
    v = P.fy * yd + P.cy
    out = ((z <= 0.0) | (not (r2 <= P.max_r2)) | (u < -0.5) | (u > P.width - 0.5) | (v < -0.5)
           | (v > P.height - 0.5))
    return (NAN if out else u), (NAN if out else v)


@nb.njit(**_JIT)
def projector_coordinates(x, P, u, v):
    """Projector pixels u, v (m,) of world points x (3, m) (see ``_project``)."""
    x0, x1, x2 = x[0], x[1], x[2]
    for i in range(x.shape[1]):
        u[i], v[i] = _project(x0[i], x1[i], x2[i], P, P.distorted != 0.0)


@nb.njit(**_INLINE)
def _gather(b0, n, W, hits, fa, S):
    """Face data of ``Hits`` ``b0 .. b0 + n`` into scratch ``S`` rows ``_GX .. _ALBEDO`` and
    ``_OBJ`` (the shading normal interpolated for smooth faces; for sphere faces both normals
    become the exact sphere's). All NaN for a miss (object -1). ``fa``: ``FaceArrays``."""
    prim, tfar, bu, bv = hits.prim, hits.tfar, hits.u, hits.v
    faces, vertex_normals, spheres = fa.faces, fa.vertex_normals, fa.spheres
    o0, o1, o2, d0, d1, d2 = W[0], W[1], W[2], W[3], W[4], W[5]
    g0, g1, g2, off = S[_GX], S[_GY], S[_GZ], S[_OFFSET]
    s0, s1, s2, te, tsph, alb = S[_SX], S[_SY], S[_SZ], S[_T_EMBREE], S[_T_SPHERE], S[_ALBEDO]
    obj = S[_OBJ]
    tab = fa.table.reshape(-1)
    for b in range(n):
        r = b0 + b
        f = prim[r]
        if f < 0:
            g0[b], g1[b], g2[b], off[b], s0[b] = NAN, NAN, NAN, NAN, NAN
            s1[b], s2[b], te[b], tsph[b], alb[b] = NAN, NAN, NAN, NAN, NAN
            obj[b] = -1.0
            continue
        i = FACE_COLUMNS * f
        gx, gy, gz = tab[i + FACE_NORMAL], tab[i + FACE_NORMAL + 1], tab[i + FACE_NORMAL + 2]
        sx, sy, sz = tab[i + FACE_SHADING], tab[i + FACE_SHADING + 1], tab[i + FACE_SHADING + 2]
        ts = NAN
        kind = tab[i + FACE_KIND]
        if kind == FACE_SMOOTH:  # smooth: interpolate vertex normals with Embree's barycentrics
            w1, w2 = bu[r], bv[r]
            w0 = np.float32(1.0) - w1 - w2
            a, c, e = faces[f, 0], faces[f, 1], faces[f, 2]
            vn = vertex_normals
            sx = w0 * vn[a, 0] + w1 * vn[c, 0] + w2 * vn[e, 0]
            sy = w0 * vn[a, 1] + w1 * vn[c, 1] + w2 * vn[e, 1]
            sz = w0 * vn[a, 2] + w1 * vn[c, 2] + w2 * vn[e, 2]
            nrm = math.sqrt(sx * sx + sy * sy + sz * sz)
            sx, sy, sz = sx / nrm, sy / nrm, sz / nrm
        elif kind >= 0.0:  # onto the exact sphere
            q = int(kind)
            ox, oy, oz, dx, dy, dz = o0[r], o1[r], o2[r], d0[r], d1[r], d2[r]
            cx, cy, cz, rad = spheres[q, 0], spheres[q, 1], spheres[q, 2], spheres[q, 3]
            ocx, ocy, ocz = ox - cx, oy - cy, oz - cz
            bb = ocx * dx + ocy * dy + ocz * dz
            disc = bb * bb - ((ocx * ocx + ocy * ocy + ocz * ocz) - rad * rad)
            if disc >= 0:
                ts = -bb - math.sqrt(disc)
                ir = 1.0 / rad
                sx = (ox + ts * dx - cx) * ir
                sy = (oy + ts * dy - cy) * ir
                sz = (oz + ts * dz - cz) * ir
                gx, gy, gz = sx, sy, sz
        g0[b], g1[b], g2[b], off[b] = gx, gy, gz, tab[i + FACE_OFFSET]
        s0[b], s1[b], s2[b] = sx, sy, sz
        te[b], tsph[b] = np.float64(tfar[r]), ts
        alb[b], obj[b] = tab[i + FACE_ALBEDO], tab[i + FACE_OBJECT]


@nb.njit(**_INLINE)
def _surface(n, o0, o1, o2, d0, d1, d2, S, P):
    """Branch-free per hit of rays o, d (n,) (vectorised by the compiler), from ``_gather``'s
    rows of ``S``: the float64 point (on the face's plane, Embree's distance where that is
    degenerate or grazing, or on the exact sphere), the geometric normal turned towards the
    ray's origin, the unit vector L towards the projector centre and its distance, whether
    the point faces the projector inside its image (geometric and shading N.L > 0, with the
    shading normal on the geometric normal's side) and then its shade albedo x N.L (else 0),
    and the projector pixel (u, v); into ``S`` rows ``_PX .. _V``."""
    if P.distorted != 0.0:  # one loop each way: no distortion polynomial where there is none
        _surface_loop(n, o0, o1, o2, d0, d1, d2, S, P, True)
    else:
        _surface_loop(n, o0, o1, o2, d0, d1, d2, S, P, False)


@nb.njit(**_INLINE)
def _surface_loop(n, o0, o1, o2, d0, d1, d2, S, P, distort):
    """``_surface`` with the projector's distortion applied or not (``distort``)."""
    g0, g1, g2, off = S[_GX], S[_GY], S[_GZ], S[_OFFSET]
    s0, s1, s2, te, tsph, alb = S[_SX], S[_SY], S[_SZ], S[_T_EMBREE], S[_T_SPHERE], S[_ALBEDO]
    x0, x1, x2, n0, n1, n2 = S[_PX], S[_PY], S[_PZ], S[_NX], S[_NY], S[_NZ]
    l0, l1, l2 = S[_LX], S[_LY], S[_LZ]
    dist, shade, cand, u, v = S[_DIST], S[_SHADE], S[_CAND], S[_U], S[_V]
    for b in range(n):
        ox, oy, oz, dx, dy, dz = o0[b], o1[b], o2[b], d0[b], d1[b], d2[b]
        gx, gy, gz = g0[b], g1[b], g2[b]
        t_e = te[b]
        t = (off[b] - (gx * ox + gy * oy + gz * oz)) / (gx * dx + gy * dy + gz * dz)
        t = t if abs(t - t_e) <= 1e-4 * t_e + 1e-3 else t_e
        ts = tsph[b]
        t = t if math.isnan(ts) else ts
        p0, p1, p2 = ox + t * dx, oy + t * dy, oz + t * dz
        flip = -1.0 if gx * dx + gy * dy + gz * dz > 0 else 1.0  # two-sided: face the camera
        gx, gy, gz = gx * flip, gy * flip, gz * flip
        sx, sy, sz = s0[b], s1[b], s2[b]
        side = -1.0 if sx * gx + sy * gy + sz * gz < 0 else 1.0  # shading normal on that side
        lx, ly, lz = P.px - p0, P.py - p1, P.pz - p2
        dl = math.sqrt(lx * lx + ly * ly + lz * lz)
        il = 1.0 / dl
        lx, ly, lz = lx * il, ly * il, lz * il
        cs = side * (sx * lx + sy * ly + sz * lz)
        uu, vv = _project(p0, p1, p2, P, distort)
        ok = (gx * lx + gy * ly + gz * lz > 0) & (cs > 0) & (not math.isnan(uu))
        x0[b], x1[b], x2[b] = p0, p1, p2
        n0[b], n1[b], n2[b] = gx, gy, gz
        l0[b], l1[b], l2[b] = lx, ly, lz
        dist[b] = dl
        shade[b] = alb[b] * cs if ok else 0.0
        cand[b] = 1.0 if ok else 0.0
        u[b], v[b] = uu, vv


@nb.njit(**_INLINE)
def _shade_block(b0, n, W, hits, fa, P, S):
    """``_gather`` then ``_surface`` for hits ``b0 .. b0 + n``; results in ``S`` rows
    ``_PX .. _V`` and ``_OBJ``."""
    _gather(b0, n, W, hits, fa, S)
    e = b0 + n
    _surface(n, W[0, b0:e], W[1, b0:e], W[2, b0:e], W[3, b0:e], W[4, b0:e], W[5, b0:e], S, P)


@nb.njit(**_JIT)
def shade_chunk(W, dest, nk, n_lens, all_live, pinhole, cam, hits, fa, P, offset, wts, out,
                shadow):
    """Shade a chunk's rays ``W`` (6, m) from their Embree ``Hits`` (``FaceArrays`` ``fa``,
    ``CameraFrame`` ``cam``, ``ProjectorModel`` ``P``) and write its ``ChunkTransport`` ``out``
    in place, before shadowing: per lens ray ``proj_uv`` and ``weight`` = lens weight ``wts``
    (n K,) x albedo x N.L where the point faces the projector inside its image, else 0; per
    chief ray ``depth``, ``proj_chief``, ``lit`` and ``object_id`` (and for a ``pinhole`` its
    weight). The first ``n_lens`` rays are lens rays (going to ``dest``; ``all_live``: ray r
    goes to ``r``), the rest chief rays. Sets up the ``ShadowRays`` ``shadow``, starting
    ``offset`` mm off the surface along its facing normal. Returns their number."""
    proj_uv, weight, depth, lit, object_id = out.proj_uv, out.weight, out.depth, out.lit, \
        out.object_id
    so, sd, far, sidx = shadow.origin, shadow.direction, shadow.far, shadow.dest
    prim = hits.prim
    S = np.empty((_SCRATCH_ROWS, BLOCK + _SCRATCH_PAD))
    x0, x1, x2, n0, n1, n2 = S[_PX], S[_PY], S[_PZ], S[_NX], S[_NY], S[_NZ]
    l0, l1, l2, dist, shade, cand = S[_LX], S[_LY], S[_LZ], S[_DIST], S[_SHADE], S[_CAND]
    u, v = S[_U], S[_V]
    obj = S[_OBJ]
    puf, pcf = proj_uv.reshape(-1), out.proj_chief.reshape(-1)
    sof, sdf = so.reshape(-1), sd.reshape(-1)
    m = prim.shape[0]
    s = 0
    for b0 in range(0, m, BLOCK):
        n = min(BLOCK, m - b0)
        _shade_block(b0, n, W, hits, fa, P, S)
        nl = max(0, min(n, n_lens - b0))  # lens rays of the block: 0 .. nl
        if all_live and nl:
            _lens_out(u[:nl], v[:nl], shade[:nl], wts[b0:b0 + nl], puf[2 * b0:2 * (b0 + nl)],
                      weight[b0:b0 + nl])
        elif nl:
            for b in range(nl):
                e = dest[b0 + b]
                puf[2 * e], puf[2 * e + 1] = u[b], v[b]
                weight[e] = wts[e] * shade[b]
        if n > nl:  # chief rays of the block: nl .. n, of pixels i0 .. i1
            i0, i1 = b0 + nl - n_lens, b0 + n - n_lens
            _chief_out(cam, x0[nl:n], x1[nl:n], x2[nl:n], u[nl:n], v[nl:n], cand[nl:n],
                       obj[nl:n], depth[i0:i1], pcf[2 * i0:2 * i1], lit[i0:i1], object_id[i0:i1])
            if pinhole:
                _lens_out(u[nl:n], v[nl:n], shade[nl:n], _NO_WEIGHTS, puf[2 * i0:2 * i1],
                          weight[i0:i1])
        for b in range(n):
            if cand[b] != 0.0:
                sof[3 * s] = x0[b] + offset * n0[b]
                sof[3 * s + 1] = x1[b] + offset * n1[b]
                sof[3 * s + 2] = x2[b] + offset * n2[b]
                sdf[3 * s], sdf[3 * s + 1], sdf[3 * s + 2] = l0[b], l1[b], l2[b]
                far[s] = dist[b] - 2 * offset
                r = b0 + b
                sidx[s] = dest[r] if r < n_lens else nk + r - n_lens
                s += 1
    return s


@nb.njit(**_JIT)
def _lens_out(u, v, shade, wts, puf, weight):
    """Lens rays' transport: ``puf`` (2 n,) projector coordinates, ``weight`` (n,) = ``wts``
    x shade (``wts`` empty: weight = shade, a pinhole). Its own function, with 1-d arrays, so
    the loop is vectorised."""
    if wts.shape[0] == 0:
        for b in range(u.shape[0]):
            puf[2 * b], puf[2 * b + 1], weight[b] = u[b], v[b], shade[b]
    else:
        for b in range(u.shape[0]):
            puf[2 * b], puf[2 * b + 1], weight[b] = u[b], v[b], wts[b] * shade[b]


@nb.njit(**_JIT)
def _chief_out(cam, x0, x1, x2, u, v, cand, obj, depth, pcf, lit, object_id):
    """Chief rays' truth maps: ``depth`` = ``R[2] . x + T[2]``, projector coordinates ``pcf``
    (2 n,), lit before shadowing, object. Its own function, so the loop is vectorised."""
    for b in range(x0.shape[0]):
        depth[b] = cam.depth_x * x0[b] + cam.depth_y * x1[b] + cam.depth_z * x2[b] + cam.depth_t
        pcf[2 * b], pcf[2 * b + 1] = u[b], v[b]
        lit[b], object_id[b] = cand[b] != 0.0, obj[b]


@nb.njit(**_JIT)
def shadow_chunk(occluded, sidx, nk, pinhole, weight, lit):
    """Apply a chunk's shadow rays: where ``occluded`` (s,) is not -1 (something is in the
    way) the lens ray's weight becomes 0, or the chief ray is not lit (and, for a pinhole,
    its weight becomes 0)."""
    for s in range(sidx.shape[0]):
        if occluded[s] == -1:
            continue
        e = sidx[s]
        if e < nk:
            weight[e] = 0.0
        else:
            lit[e - nk] = False
            if pinhole:
                weight[e - nk] = 0.0
