"""Cloud-to-cloud (after ICP) and cloud-to-CAD comparison, with a colour-map image.

Distances are signed along the reference surface's outward normal: positive where the measured
cloud lies outside the reference (material excess). Lengths in mm.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from sim.errors import SimInputError
from sim.metrology.spheres import finite_points
from sim.storage.durable import durable_figure
from sim.tolerances import BALL_QUERY_SLACK_MM, ICP_RCOND, QUADRIC_RIDGE


@dataclass(frozen=True)
class RigidTransform:
    """``x' = R x + t``: R (3, 3), t (3,) mm."""

    R: np.ndarray
    t: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(points) @ self.R.T + self.t


@dataclass(frozen=True)
class CloudComparison:
    """Signed distances (n,) mm of each compared point, their mean and RMSE, and the alignment."""

    distances: np.ndarray
    mean: float
    rmse: float
    transform: RigidTransform
    iterations: int

    def as_dict(self) -> dict:
        return {
            "mean_mm": float(self.mean),
            "rmse_mm": float(self.rmse),
            "points": int(self.distances.size),
            "icp_iterations": int(self.iterations),
            "R": self.transform.R.tolist(),
            "t_mm": self.transform.t.tolist(),
        }


def estimate_normals(points: np.ndarray, k: int = 12, outward_from: np.ndarray | None = None) -> np.ndarray:
    """Unit normals (n, 3) by PCA of each point's ``k`` nearest neighbours, oriented away from
    ``outward_from`` (3,) (default: the centroid, right for convex parts)."""
    p = np.asarray(points, dtype=np.float64)
    _, idx = cKDTree(p).query(p, k=min(k, len(p)))
    nb = p[idx] - p[idx].mean(axis=1, keepdims=True)
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
    n = vecs[:, :, 0]
    ref = p.mean(axis=0) if outward_from is None else np.asarray(outward_from, dtype=np.float64)
    flip = np.sum(n * (p - ref), axis=1) < 0
    n[flip] *= -1
    return n


def _point_to_plane_step(src: np.ndarray, dst: np.ndarray, nrm: np.ndarray) -> RigidTransform:
    """Point-to-plane least squares, linearised in the rotation about the source centroid and
    re-orthonormalised. Directions the geometry cannot fix (a sphere's rotations about its
    centre, a plane's in-plane shifts) are left at zero by a truncated SVD."""
    m = src.mean(axis=0)
    scale = np.sqrt(np.mean(np.sum((src - m) ** 2, axis=1)))
    a = np.concatenate([np.cross(src - m, nrm) / scale, nrm], axis=1)
    b = np.sum((dst - src) * nrm, axis=1)
    x, *_ = np.linalg.lstsq(a, b, rcond=ICP_RCOND)
    w, t = x[:3] / scale, x[3:]
    theta = np.linalg.norm(w)
    r = np.eye(3)
    if theta > 1e-15:
        k = w / theta
        kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        r = np.eye(3) + np.sin(theta) * kx + (1 - np.cos(theta)) * kx @ kx
    return RigidTransform(r, m - r @ m + t)


def icp(
    source: np.ndarray,
    target: np.ndarray,
    target_normals: np.ndarray | None = None,
    max_iterations: int = 40,
    tolerance_mm: float = 1e-6,
    max_distance_mm: float | None = None,
) -> tuple[RigidTransform, int]:
    """Point-to-plane ICP aligning ``source`` (n, 3) to ``target`` (m, 3).

    Correspondences are nearest neighbours (cKDTree), pairs further apart than
    ``max_distance_mm`` are ignored. Stops when the update moves no point by more than
    ``tolerance_mm``, or when the RMS point-to-plane residual changes by less than
    ``tolerance_mm`` (shapes with unconstrained motions, such as spheres, stop there).
    Returns the transform mapping source onto target and the iteration count.
    """
    src0 = finite_points(source, "source cloud")
    tgt = finite_points(target, "target cloud")
    nrm = estimate_normals(tgt) if target_normals is None else np.asarray(target_normals, float)
    tree = cKDTree(tgt)
    r_tot, t_tot = np.eye(3), np.zeros(3)
    radius = np.max(np.linalg.norm(src0 - src0.mean(axis=0), axis=1))
    previous = np.inf
    iterations = 0
    while iterations < max_iterations:
        iterations += 1
        src = src0 @ r_tot.T + t_tot
        d, j = tree.query(src)
        use = np.ones(len(src), bool) if max_distance_mm is None else d <= max_distance_mm
        if use.sum() < 6:
            raise SimInputError(
                f"ICP: only {int(use.sum())} pairs closer than {max_distance_mm} mm; "
                "the clouds are not roughly aligned"
            )
        rms = np.sqrt(np.mean(np.sum((tgt[j[use]] - src[use]) * nrm[j[use]], axis=1) ** 2))
        if abs(previous - rms) < tolerance_mm:
            break
        previous = rms
        step = _point_to_plane_step(src[use], tgt[j[use]], nrm[j[use]])
        r_tot, t_tot = step.R @ r_tot, step.R @ t_tot + step.t
        moved = np.linalg.norm(step.t) + radius * np.linalg.norm(step.R - np.eye(3))
        if moved < tolerance_mm:
            break
    return RigidTransform(r_tot, t_tot), iterations


def signed_distance_to_cloud(
    points: np.ndarray, reference: np.ndarray, reference_normals: np.ndarray, k: int = 12
) -> np.ndarray:
    """Signed distance (n,) of each point to the reference surface near it.

    The surface is a local quadric height field ``h(x, y)`` fitted to the ``k`` reference points
    nearest to each point, in the tangent frame of its nearest reference point; the distance is
    ``h_p - h(x_p, y_p)`` along that point's normal (exact to second order in the curvature, so
    sparse reference sampling does not bias the mean).
    """
    ref = np.asarray(reference, dtype=np.float64)
    nrm = np.asarray(reference_normals, dtype=np.float64)
    if nrm.shape != ref.shape:
        raise SimInputError(f"reference normals have shape {nrm.shape}, expected {ref.shape}")
    k = min(k, len(ref))
    _, j = cKDTree(ref).query(points, k=k)
    n = nrm[j[:, 0]]
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    e1 = np.cross(n, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(n, e1)
    origin = ref[j[:, 0]]
    q = ref[j] - origin[:, None, :]
    x, y, h = (np.einsum("nki,ni->nk", q, e) for e in (e1, e2, n))
    a = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=2)
    ata = np.einsum("nki,nkj->nij", a, a) + QUADRIC_RIDGE * np.eye(6)
    coef = np.linalg.solve(ata, np.einsum("nki,nk->ni", a, h)[..., None])[..., 0]
    if k < 6:
        coef[:, 3:] = 0.0
    d = np.asarray(points, dtype=np.float64) - origin
    xp, yp, hp = (np.sum(d * e, axis=1) for e in (e1, e2, n))
    basis = np.stack([np.ones_like(xp), xp, yp, xp * xp, xp * yp, yp * yp], axis=1)
    return hp - np.sum(basis * coef, axis=1)


def compare_clouds(
    measured: np.ndarray,
    reference: np.ndarray,
    reference_normals: np.ndarray | None = None,
    align: bool = True,
    max_distance_mm: float | None = None,
) -> CloudComparison:
    """Align ``measured`` to ``reference`` by ICP (if ``align``), then the signed distance of each
    measured point to the reference surface (``signed_distance_to_cloud``), their mean and RMSE."""
    m = finite_points(measured, "measured cloud")
    ref = finite_points(reference, "reference cloud")
    nrm = estimate_normals(ref) if reference_normals is None else np.asarray(reference_normals, float)
    bad = ~np.isfinite(nrm).all(axis=1)
    if bad.any():  # a cloud's own normals can be missing at its edges: estimate those
        nrm = nrm.copy()
        nrm[bad] = estimate_normals(ref)[bad]
    if align:
        tf, n_it = icp(m, ref, nrm, max_distance_mm=max_distance_mm)
    else:
        tf, n_it = RigidTransform(np.eye(3), np.zeros(3)), 0
    d = signed_distance_to_cloud(tf.apply(m), ref, nrm)
    return CloudComparison(d, float(d.mean()), float(np.sqrt(np.mean(d * d))), tf, n_it)


@dataclass(frozen=True)
class PixelComparison:
    """Per-pixel distances (n,) mm of a cloud to a reference cloud from the same rig pixels,
    their mean and RMSE, the compared points' indices (n,) in the measured cloud and the
    pixels each cloud has that the other lacks (``unmatched``: measured, reference)."""

    distances: np.ndarray
    mean: float
    rmse: float
    index: np.ndarray
    unmatched: tuple[int, int]


def compare_by_pixel(measured, reference, transform: RigidTransform | None = None,
                     edge_px: int = 1) -> PixelComparison:
    """Distances between two clouds of the same rig (``PointCloud``-like: ``points``,
    ``normals`` facing the reference camera, ``fields`` with ``camera``, ``u``, ``v``) by
    pixel correspondence: for every reference pixel that both clouds measured,
    ``(p_measured - p_reference) . n_reference`` (positive: the measured point lies outside,
    towards the camera). Both points lie on the same camera ray, so the distance does not
    depend on how densely or where else either cloud has points. Pixels within ``edge_px``
    of a pixel without a reference point (silhouettes, holes) or without a finite reference
    normal are left out. ``transform``: applied to the measured points first (after ICP)."""
    keys = []
    for c in (measured, reference):
        f = c.fields
        keys.append(np.stack([f["camera"], f["v"], f["u"]], axis=1).astype(np.int64))
    km, kr = keys
    hi = np.maximum(km.max(axis=0), kr.max(axis=0)) + 1 + 2 * edge_px
    # flat pixel index of every point (the stubs type ravel_multi_index's result as a scalar)
    flat = [np.asarray(np.ravel_multi_index((k + [0, edge_px, edge_px]).T, hi)) for k in keys]
    _, im, ir = np.intersect1d(flat[0], flat[1], return_indices=True)
    unmatched = (len(km) - len(im), len(kr) - len(ir))
    nrm = np.asarray(reference.normals, dtype=np.float64)
    ok = np.isfinite(nrm[ir]).all(axis=1)
    if edge_px > 0:
        from scipy.ndimage import binary_erosion

        have = np.zeros(hi, dtype=bool)
        have.ravel()[flat[1]] = True
        inner = np.stack([binary_erosion(g, np.ones((2 * edge_px + 1,) * 2)) for g in have])
        ok &= inner.ravel()[flat[1][ir]]
    im, ir = im[ok], ir[ok]
    pm = np.asarray(measured.points, dtype=np.float64)[im]
    if transform is not None:
        pm = transform.apply(pm)
    d = np.sum((pm - np.asarray(reference.points, dtype=np.float64)[ir]) * nrm[ir], axis=1)
    if d.size == 0:
        raise SimInputError("compare_by_pixel: the clouds share no reference pixel away from "
                         "the silhouettes")
    return PixelComparison(d, float(d.mean()), float(np.sqrt(np.mean(d * d))), im,
                           unmatched)


def mesh_signed_distance(points: np.ndarray, mesh: trimesh.Trimesh) -> np.ndarray:
    """Signed distance (n,) mm of points to a triangle mesh, positive outside.

    Exact closest points: candidate triangles come from a k-d tree of triangle centroids (every
    triangle that could be closer than the nearest centroid's triangle is checked); the sign is
    that of ``(p - c) . n`` with ``n`` the vertex normals interpolated at the closest point ``c``.
    """
    p = finite_points(points, "points", 1)
    if len(mesh.faces) == 0:
        raise SimInputError("reference mesh has no triangles")
    mesh = mesh.copy()
    edge = float(np.median(mesh.edges_unique_length))
    if mesh.edges_unique_length.max() > 4 * edge:  # bound the triangle size: same surface
        v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=4 * edge)
        mesh = trimesh.Trimesh(v, f, process=False)
    tri = mesh.triangles
    cen = tri.mean(axis=1)
    reach = float(np.max(np.linalg.norm(tri - cen[:, None], axis=2)))
    tree = cKDTree(cen)
    _, j0 = tree.query(p, k=min(4, len(cen)))
    j0 = j0.reshape(len(p), -1)
    c0 = trimesh.triangles.closest_point(tri[j0.ravel()], np.repeat(p, j0.shape[1], axis=0))
    ub = np.linalg.norm(c0 - np.repeat(p, j0.shape[1], axis=0), axis=1).reshape(len(p), -1).min(1)
    lists = tree.query_ball_point(p, ub + reach + BALL_QUERY_SLACK_MM)
    counts = np.array([len(x) for x in lists])
    cand = np.concatenate([np.asarray(x, dtype=np.int64) for x in lists])
    owner = np.repeat(np.arange(len(p)), counts)
    cp = trimesh.triangles.closest_point(tri[cand], p[owner])
    dist = np.linalg.norm(cp - p[owner], axis=1)
    order = np.lexsort((dist, owner))
    first = order[np.r_[0, np.flatnonzero(np.diff(owner[order])) + 1]]
    best_tri, best_cp, best_d = cand[first], cp[first], dist[first]
    bary = trimesh.triangles.points_to_barycentric(tri[best_tri], best_cp)
    vn = mesh.vertex_normals[mesh.faces[best_tri]]
    n = np.einsum("nk,nki->ni", bary, vn)
    sign = np.where(np.sum((p - best_cp) * n, axis=1) < 0, -1.0, 1.0)
    return sign * best_d


def distance_colormap_png(
    points: np.ndarray,
    distances_mm: np.ndarray,
    path: str | Path,
    limit_mm: float | None = None,
    title: str = "signed distance",
) -> float:
    """Write a PNG of the points seen along the cloud's thinnest principal axis, coloured by
    signed distance (diverging map, symmetric limits ``+-limit_mm``, default the largest |d|).
    Returns the colour limit used, mm."""
    from matplotlib.figure import Figure

    p = np.asarray(points, dtype=np.float64)
    d = np.asarray(distances_mm, dtype=np.float64)
    if len(p) != len(d):
        raise SimInputError(f"{len(p)} points but {len(d)} distances")
    q = p - p.mean(axis=0)
    _, _, vt = np.linalg.svd(q, full_matrices=False)
    xy = q @ vt[:2].T
    lim = float(np.max(np.abs(d))) if limit_mm is None else float(limit_mm)
    lim = lim if lim > 0 else 1e-6
    fig = Figure(figsize=(6, 5), dpi=100)
    ax = fig.add_subplot()
    sc = ax.scatter(xy[:, 0], xy[:, 1], c=d, cmap="coolwarm", vmin=-lim, vmax=lim, s=2, lw=0)
    ax.set_aspect("equal")
    ax.set_xlabel("mm")
    ax.set_ylabel("mm")
    ax.set_title(title)
    fig.colorbar(sc, ax=ax, label="mm")
    durable_figure(fig, path)
    return lim
